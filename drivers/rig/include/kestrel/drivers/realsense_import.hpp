// A RealSense D4xx's factory calibration -> a Rig (`kestrel calib import-realsense`).
//
// Input: the text `rs-enumerate-devices -c` prints (librealsense
// tools/enumerate-devices): per stream and resolution an intrinsics block
//   Intrinsic of "Depth" / 848x480 / {Z16}
//     Width / Height / PPX / PPY / Fx / Fy / Distortion / Coeffs / FOV (deg)
// the IMU's "Motion Intrinsic of "Accel"" / "Gyro" blocks (bias and noise
// variances, a 3x4 sensitivity), and for every pair of streams
//   Extrinsic from "Depth"  To  "Color" :  Rotation Matrix (3 rows) + Translation Vector
// where p_to = R p_from + t (metres; librealsense's rs2_extrinsics, printed row by row).
//
// The mapping (docs/realsense.md):
//   the camera stream (Color, or Infrared 1) at WxH -> rig.rgb (fx fy cx cy, size, distortion)
//   Depth at WxH + Extrinsic Depth -> camera      -> rig.depth_camera (intrinsics, T_CD);
//                                                    none with Infrared 1 (depth is in its frame)
//   Extrinsic Gyro -> camera (p_C = T_CG p_G)      -> T_BC = T_CG^-1 (body = the IMU, as librealsense
//                                                    reports its axes)
//   Motion intrinsics noise variances [unit^2, per sample at the stream's rate]
//                                                 -> noise densities = sqrt(var / rate)
//   Distortion: None -> none; Brown Conrady -> radtan k1 k2 p1 p2 k3 exactly; Inverse / Modified
//   Brown Conrady -> radtan fitted over the image (residual in the notes); Kannala Brandt4 -> equidistant.
// What the dump does not give (depth unit and range, IMU random walks,
// ranges, time offset, gravity, camera rate) comes from the base rig and each
// is named in the notes, as is every section the dump lacks.
#pragma once

#include <array>
#include <string>
#include <vector>

#include "kestrel/msgs.hpp"

namespace kestrel::drivers {

// ---- the dump as read ------------------------------------------------------------
struct RsIntrinsics {
  std::string stream;  // "Color", "Depth", "Infrared 1", ...
  int width = 0, height = 0;
  std::string formats;  // "{Z16}"
  bool available = false;
  double fx = 0, fy = 0, ppx = 0, ppy = 0;
  std::string model;  // "Brown Conrady", "Inverse Brown Conrady", "None", ...
  std::array<double, 5> coeffs{};
  int line = 0;
};
struct RsMotionIntrinsics {
  std::string stream;  // "Accel" | "Gyro"
  bool available = false;
  std::array<double, 3> bias_variances{};
  std::array<double, 3> noise_variances{};
  std::array<double, 12> sensitivity{};  // 3 rows of 4 (scale | bias)
  bool has_sensitivity = false;
  int line = 0;
};
struct RsExtrinsics {
  std::string from, to;
  bool available = false;
  Mat4d T_to_from = kIdentity4;  // p_to = T p_from
  int line = 0;
};
struct RealSenseDump {
  std::string device_name;  // "Intel RealSense D435I" when the dump has its device info
  std::string serial;
  std::string firmware;
  std::vector<RsIntrinsics> intrinsics;
  std::vector<RsMotionIntrinsics> motion;
  std::vector<RsExtrinsics> extrinsics;
  const RsIntrinsics* find(const std::string& stream, int width, int height) const;
  const RsExtrinsics* find_extrinsics(const std::string& from, const std::string& to) const;
  const RsMotionIntrinsics* find_motion(const std::string& stream) const;
  std::string sizes_of(const std::string& stream) const;  // "640x480, 1280x720" for errors
};

// Throws std::runtime_error "NAME:LINE: FIELD: what" for anything malformed.
// Sections it does not know (device info, stream profiles, options) are skipped.
RealSenseDump parse_realsense_dump(const std::string& text, const std::string& name);

// ---- the import ---------------------------------------------------------------------
struct RealSenseImportOptions {
  std::string camera = "Color";           // the rig's camera: "Color" or "Infrared 1"
  int width = 0, height = 0;              // of the camera stream; 0 = the base rig's rgb size, else 640x480
  int depth_width = 0, depth_height = 0;  // 0 = the camera's size
  double accel_rate_hz = 250;             // the rates the IMU streams run at (noise densities depend on them)
  double gyro_rate_hz = 200;
};

struct RealSenseImport {
  Rig rig;
  std::vector<std::string> notes;    // every field taken from the base rig, every fit
  std::vector<std::string> missing;  // sections the dump lacks that the rig would use
};

// Throws std::runtime_error naming `name` and the section for anything the
// rig cannot do without (the camera's intrinsics at the size asked for; for
// the Color camera, Depth's intrinsics and Depth -> Color).
RealSenseImport import_realsense_text(const std::string& text, const std::string& name,
                                      const RealSenseImportOptions& o, const Rig& base);
// Reads the file; "PATH: cannot open" when it is missing.
RealSenseImport import_realsense(const std::string& path, const RealSenseImportOptions& o, const Rig& base);

// Least-squares radtan (k1 k2 p1 p2 k3) for a librealsense distortion model
// over the image; rms_px the fit's residual. False when the model is unknown.
bool fit_radtan(const RsIntrinsics& in, std::array<double, 5>& radtan, double& rms_px);

}  // namespace kestrel::drivers

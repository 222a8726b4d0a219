// Sensor message types shared by drivers, core, the log and the tools.
//
// Plain data only, no dependencies beyond the standard library: this header is
// the one place drivers and core agree on, so neither has to include the other.
// Conventions (docs/frames.md): int64 nanoseconds on the host CLOCK_MONOTONIC,
// frames and units in names, quaternions stored (w, x, y, z), 4x4 transforms
// stored row-major with T_AB mapping B coordinates into A.
#pragma once

#include <array>
#include <cstdint>
#include <string>

namespace kestrel {

using Vec3d = std::array<double, 3>;
using Quatd = std::array<double, 4>;   // (w, x, y, z), unit norm
using Mat4d = std::array<double, 16>;  // row-major homogeneous transform

constexpr Mat4d kIdentity4{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};

// Bits in ImuSample::flags. Drivers set them; the estimator counts and
// survives them rather than trusting the numbers.
enum ImuFlag : uint32_t {
  kImuGyroSaturated = 1u << 0,
  kImuAccSaturated = 1u << 1,
  kImuNonFinite = 1u << 2,        // a NaN or Inf reached the driver output
  kImuGapBefore = 1u << 3,        // samples were lost before this one (sequence jump)
  kImuTimeInterpolated = 1u << 4  // time back-computed from a FIFO burst, not data-ready stamped
};

struct ImuSample {
  int64_t t_ns = 0;       // sample time on the host clock
  int64_t t_recv_ns = 0;  // when the host received it
  uint32_t seq = 0;       // driver sequence number, for drop detection
  uint32_t flags = 0;     // ImuFlag bits
  Vec3d gyro_rps{};       // angular rate of B w.r.t. W, in B
  Vec3d acc_mps2{};       // specific force in B
  float temp_c = 0.0f;
};

enum class PixelFormat : uint8_t {
  kGray8 = 1,
  kRgb8 = 2,  // 3 bytes per pixel, R G B
  kBgr8 = 3,
  kYuyv = 4,
  kDepthU16 = 5  // depth units, metres = value * Rig::depth_scale_m_per_unit; 0 = invalid
};

inline int bytes_per_pixel(PixelFormat f) {
  switch (f) {
    case PixelFormat::kGray8:
      return 1;
    case PixelFormat::kRgb8:
    case PixelFormat::kBgr8:
      return 3;
    case PixelFormat::kYuyv:
    case PixelFormat::kDepthU16:
      return 2;
  }
  return 0;
}

// A view onto pixels owned elsewhere (an ObjectPool slot, a log buffer).
struct ImageView {
  int width = 0;
  int height = 0;
  int stride_bytes = 0;
  PixelFormat format = PixelFormat::kGray8;
  const uint8_t* data = nullptr;
};

// What travels through the camera ring: the pixels stay in a pool and move by
// handle, so pushing a frame copies a few dozen bytes.
struct RgbdFrameMsg {
  int64_t t_ns = 0;  // mid-exposure time on the host clock
  int64_t t_recv_ns = 0;
  uint32_t seq = 0;
  int32_t exposure_us = 0;    // 0 when unknown
  uint32_t rgb_handle = 0;    // slot in the colour image pool
  uint32_t depth_handle = 0;  // slot in the depth image pool (registered to colour)
  uint32_t flags = 0;
  // A stereo rig's right image (raw, as the camera gave it; the tracking side
  // rectifies both): a slot in the same pool. Every holder of a frame releases
  // it as it releases the other two.
  uint32_t right_handle = 0;  // 0: none (rt::kInvalidHandle)
};

enum class DistortionModel : uint8_t { kNone = 0, kRadTan = 1, kEquidistant = 2 };

struct CameraIntrinsics {
  int width = 0;
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;  // pixels
  DistortionModel distortion = DistortionModel::kNone;
  std::array<double, 5> dist{};  // radtan: k1 k2 p1 p2 k3; equidistant: k1..k4
};

// IMU noise as continuous-time densities (Kalibr / EuRoC convention).
struct ImuNoise {
  double gyro_noise_density_rad_s_sqrthz = 0;
  double gyro_random_walk_rad_s2_sqrthz = 0;
  double acc_noise_density_mps2_sqrthz = 0;
  double acc_random_walk_mps3_sqrthz = 0;
  // Paper 000 eq. 6: accelerometer bias as a bounded random walk
  // db/dt = -b/tau + w. tau <= 0 means a plain random walk.
  double acc_bias_tau_s = 0;
  double gyro_range_rps = 0;  // saturation limits, 0 = unknown
  double acc_range_mps2 = 0;
};

// Depth sensor error model: sigma(z) = depth_sigma_coeff_per_m * z^2.
struct DepthModel {
  double scale_m_per_unit = 0.001;
  double min_range_m = 0.3;
  double max_range_m = 6.0;
  double sigma_coeff_per_m = 0.0025;  // structured light: ~1.4 mm at 1 m... 4 cm at 4 m
};

// A depth sensor that is not the colour camera (Kinect v1's IR camera, a
// RealSense depth stream over UVC): its own intrinsics and where it sits.
// Depth as such a sensor delivers it is in this camera; the reader or driver
// that receives it registers it to the colour camera (drivers/depth), so
// every depth image past the drivers is registered. A log written after
// that keeps the entry as a record of where its depth came from.
struct DepthCamera {
  bool present = false;
  CameraIntrinsics intrinsics;
  Mat4d T_CD = kIdentity4;  // depth camera -> colour camera
};

// The second camera of a stereo pair (EuRoC cam1, a Kalibr chain's cam1, a
// D4xx IR pair). `Rig::rgb` and `Rig::T_BC` are then the left camera (cam0).
// Depth comes from matching the left image's features along the rows of the
// rectified pair instead of a depth image (docs/stereo.md).
struct StereoCamera {
  bool present = false;
  CameraIntrinsics intrinsics;  // right camera, as calibrated (with its distortion)
  Mat4d T_BC1 = kIdentity4;     // right camera -> body
  // Set only on the rig the rectification (drivers/stereo) hands the
  // estimator: `rgb` is then the rectified left camera (pinhole, no
  // distortion), `T_BC` the rectified left camera -> body, and the rectified
  // right camera has the same intrinsics, translated by +baseline_m along x.
  bool rectified = false;
  double baseline_m = 0;
};

// Everything a log or a live rig needs to interpret its sensors.
struct Rig {
  std::string name;
  CameraIntrinsics rgb;  // depth is registered to this camera
  DepthModel depth;
  DepthCamera depth_camera;  // present: the raw depth comes from another camera
  StereoCamera stereo;       // present: a stereo pair, depth from matching (docs/stereo.md)
  Mat4d T_BC = kIdentity4;   // camera -> body (body = IMU frame)
  Mat4d T_BI = kIdentity4;   // IMU -> body; identity unless the body frame is elsewhere
  ImuNoise imu;
  double imu_rate_hz = 0;
  double camera_rate_hz = 0;
  int64_t time_offset_cam_imu_ns = 0;  // t_imu = t_cam + offset
  double gravity_mps2 = 9.81;
};

struct GroundTruthPose {
  int64_t t_ns = 0;
  Vec3d p_WB{};
  Quatd q_WB{1, 0, 0, 0};
  bool has_velocity = false;
  Vec3d v_WB{};
};

// Driver faults, drops, resets: recorded beside the data they explain.
enum class EventCode : uint32_t {
  kInfo = 0,
  kImuDrop = 1,
  kFrameDrop = 2,
  kDriverReset = 3,
  kDriverFault = 4,
  kClockJump = 5,
  kEstimatorReset = 6
};

struct Event {
  int64_t t_ns = 0;
  EventCode code = EventCode::kInfo;
  std::string text;
};

}  // namespace kestrel

// Kalibr's calibration files -> a Rig (`kestrel calib import-kalibr`).
//
// Kalibr (ethz-asl/kalibr) writes a camera chain (`camchain-imucam-*.yaml`
// from kalibr_calibrate_imu_camera: intrinsics, distortion, T_cam_imu,
// timeshift_cam_imu) and reads or writes an IMU file (`imu.yaml`: the noise
// densities and random walks, or the `imu0:` block of its results). The
// mapping (docs/own-sensors.md):
//   intrinsics [fu, fv, pu, pv]    -> camera.fx_px, fy_px, cx_px, cy_px
//   resolution [w, h]              -> camera.width_px, height_px
//   distortion radtan [k1 k2 r1 r2] / equidistant [k1..k4] -> camera.distortion, dist_coeffs
//   T_cam_imu (p_C = T_cam_imu p_I) -> T_BC = T_cam_imu^-1 (body = IMU)
//   timeshift_cam_imu [s] (t_imu = t_cam + shift) -> time_offset_cam_imu_ns (same sign)
//   accelerometer/gyroscope_noise_density, _random_walk (continuous time) -> imu.* as they are
//   update_rate [Hz]                -> imu.rate_hz
// Kalibr has no place for the depth model, the camera's frame rate, the
// IMU's ranges and bias time constant, gravity and the name: those come
// from a base rig and each is named in the notes.
#pragma once

#include <string>
#include <vector>

#include "kestrel/msgs.hpp"

namespace kestrel::drivers {

struct KalibrImport {
  Rig rig;
  // One line per field Kalibr's files did not give, with the value used.
  std::vector<std::string> notes;
};

// camera: the camchain entry ("cam0"). Throws std::runtime_error naming the
// file and the field for anything missing or malformed ("camchain.yaml:
// cam0.T_cam_imu: missing (...)").
KalibrImport import_kalibr(const std::string& camchain_path, const std::string& imu_path,
                           const std::string& camera, const Rig& base);
// The same from YAML text (tests); the names stand in for paths in errors.
KalibrImport import_kalibr_text(const std::string& camchain_yaml, const std::string& camchain_name,
                                const std::string& imu_yaml, const std::string& imu_name,
                                const std::string& camera, const Rig& base);

}  // namespace kestrel::drivers

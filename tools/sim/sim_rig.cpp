// Rigs for the simulator: the built-in one, rig YAML files and EuRoC sensor files.
#include <filesystem>
#include <optional>
#include <stdexcept>
#include <utility>

#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/tools/simulator.hpp"

namespace kestrel::tools {

Eigen::Isometry3d to_isometry(const Mat4d& T) {
  Eigen::Matrix4d M;
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) M(r, c) = T[static_cast<size_t>(4 * r + c)];
  Eigen::Isometry3d out = Eigen::Isometry3d::Identity();
  // Re-orthonormalise: files carry 9-12 digits.
  out.linear() = Eigen::Quaterniond(Eigen::Matrix3d(M.topLeftCorner<3, 3>())).normalized().toRotationMatrix();
  out.translation() = M.topRightCorner<3, 1>();
  return out;
}

Mat4d to_mat4(const Eigen::Isometry3d& T) {
  Mat4d out = kIdentity4;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) out[static_cast<size_t>(4 * r + c)] = T.linear()(r, c);
    out[static_cast<size_t>(4 * r + 3)] = T.translation()[r];
  }
  return out;
}

Rig default_sim_rig(int width, int height, double fps, double imu_rate_hz) {
  Rig rig;
  rig.name = "kestrel-sim";
  // Kinect-class field of view (62 x 48 deg at 640x480) at any resolution.
  rig.rgb.width = width;
  rig.rgb.height = height;
  rig.rgb.fx = rig.rgb.fy = 525.0 * width / 640.0;
  rig.rgb.cx = 0.5 * (width - 1);
  rig.rgb.cy = 0.5 * (height - 1);
  rig.rgb.distortion = DistortionModel::kRadTan;
  rig.rgb.dist = {0.04, -0.03, 5e-4, -3e-4, 0.0};
  // Camera looking forward along body x (body x fwd, y left, z up; camera
  // z fwd, x right, y down), 6 cm ahead of the IMU.
  Eigen::Isometry3d T_BC = Eigen::Isometry3d::Identity();
  T_BC.linear() << 0, 0, 1, -1, 0, 0, 0, -1, 0;
  T_BC.translation() = Eigen::Vector3d(0.06, 0.015, 0.02);
  rig.T_BC = to_mat4(T_BC);
  rig.imu_rate_hz = imu_rate_hz;
  rig.camera_rate_hz = fps;
  rig.imu = ImuModel::bmx055().to_rig();
  return rig;
}

void load_sim_rig_yaml(const std::string& path, Rig& rig, ImuModel& imu) {
  // The project's rig schema (drivers/rig_yaml.hpp, docs/log-format.md), so
  // any configs/*.yaml rig can be simulated as is.
  const Rig file = drivers::load_rig_file(path);
  rig = file;
  if (rig.camera_rate_hz <= 0.0) rig.camera_rate_hz = 30.0;
  if (rig.imu_rate_hz <= 0.0) rig.imu_rate_hz = 400.0;
  const ImuNoise& n = file.imu;
  const bool has_noise = n.gyro_noise_density_rad_s_sqrthz > 0 || n.gyro_random_walk_rad_s2_sqrthz > 0 ||
                         n.acc_noise_density_mps2_sqrthz > 0 || n.acc_random_walk_mps3_sqrthz > 0;
  // A rig without IMU noise figures keeps the BMX055; one with them gets
  // exactly those (the turn-on bias and resolution stay the BMX055's: the
  // rig schema has no place for them).
  if (has_noise) {
    imu.gyro_noise_density_rad_s_sqrthz = n.gyro_noise_density_rad_s_sqrthz;
    imu.gyro_random_walk_rad_s2_sqrthz = n.gyro_random_walk_rad_s2_sqrthz;
    imu.acc_noise_density_mps2_sqrthz = n.acc_noise_density_mps2_sqrthz;
    imu.acc_random_walk_mps3_sqrthz = n.acc_random_walk_mps3_sqrthz;
    imu.acc_bias_tau_s = n.acc_bias_tau_s;
  }
  if (n.gyro_range_rps > 0) imu.gyro_range_rps = n.gyro_range_rps;
  if (n.acc_range_mps2 > 0) imu.acc_range_mps2 = n.acc_range_mps2;
}

// Both through the one EuRoC sensor-file reader (drivers/folder_logs.hpp), so
// the simulator and the EuRoC reader can never read a file differently.
bool read_euroc_imu_yaml(const std::string& path, ImuModel& model, double& rate_hz) {
  if (!std::filesystem::exists(path)) return false;
  const drivers::EurocSensorYaml y = drivers::read_euroc_sensor_yaml(path);
  // The hybrid log claims the real IMU's noise: all four figures or none.
  const std::pair<const char*, const std::optional<double>*> noise[] = {
      {"gyroscope_noise_density", &y.gyro_noise_density_rad_s_sqrthz},
      {"gyroscope_random_walk", &y.gyro_random_walk_rad_s2_sqrthz},
      {"accelerometer_noise_density", &y.acc_noise_density_mps2_sqrthz},
      {"accelerometer_random_walk", &y.acc_random_walk_mps3_sqrthz}};
  for (const auto& [key, value] : noise)
    if (!*value) throw std::runtime_error(path + ": missing key '" + key + "'");
  model = ImuModel{};
  model.gyro_noise_density_rad_s_sqrthz = *y.gyro_noise_density_rad_s_sqrthz;
  model.gyro_random_walk_rad_s2_sqrthz = *y.gyro_random_walk_rad_s2_sqrthz;
  model.acc_noise_density_mps2_sqrthz = *y.acc_noise_density_mps2_sqrthz;
  model.acc_random_walk_mps3_sqrthz = *y.acc_random_walk_mps3_sqrthz;
  if (y.rate_hz) rate_hz = *y.rate_hz;
  return true;
}

bool read_euroc_T_BS(const std::string& path, Eigen::Isometry3d& T_BS) {
  if (!std::filesystem::exists(path)) return false;
  T_BS = to_isometry(drivers::read_euroc_sensor_yaml(path).T_BS);
  return true;
}

}  // namespace kestrel::tools

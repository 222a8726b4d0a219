// Rigs for the simulator: the built-in one, rig YAML files and EuRoC sensor files.
#include <yaml-cpp/yaml.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/tools/simulator.hpp"

namespace kestrel::tools {
namespace {

// EuRoC files start with "%YAML:1.0", an OpenCV-style directive yaml-cpp rejects.
YAML::Node load_yaml_file(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error(path + ": cannot open");
  std::stringstream text;
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("%YAML", 0) != 0) text << line << '\n';
  try {
    return YAML::Load(text.str());
  } catch (const YAML::Exception& e) {
    throw std::runtime_error(path + ":" + std::to_string(e.mark.line + 1) + ": " + e.msg);
  }
}

template <typename T>
void get(const YAML::Node& node, const char* key, T& out, const std::string& where) {
  const YAML::Node v = node[key];
  if (!v) return;
  try {
    out = v.as<T>();
  } catch (const YAML::Exception&) {
    throw std::runtime_error(where + ": key '" + key + "' has a bad value");
  }
}

bool read_matrix4(const YAML::Node& node, Mat4d& out, const std::string& where) {
  if (!node) return false;
  const YAML::Node data = node.IsMap() ? node["data"] : node;
  if (!data || !data.IsSequence() || data.size() != 16) throw std::runtime_error(where + ": expected 16 numbers (row-major 4x4)");
  for (size_t i = 0; i < 16; ++i) {
    try {
      out[i] = data[i].as<double>();
    } catch (const YAML::Exception&) {
      throw std::runtime_error(where + ": element " + std::to_string(i) + " is not a number");
    }
  }
  return true;
}

}  // namespace

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

bool read_euroc_imu_yaml(const std::string& path, ImuModel& model, double& rate_hz) {
  if (!std::filesystem::exists(path)) return false;
  const YAML::Node root = load_yaml_file(path);
  const char* keys[4] = {"gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
                         "accelerometer_random_walk"};
  double v[4];
  for (int i = 0; i < 4; ++i) {
    if (!root[keys[i]]) throw std::runtime_error(path + ": missing key '" + keys[i] + "'");
    get(root, keys[i], v[i], path);
  }
  model = ImuModel{};
  model.gyro_noise_density_rad_s_sqrthz = v[0];
  model.gyro_random_walk_rad_s2_sqrthz = v[1];
  model.acc_noise_density_mps2_sqrthz = v[2];
  model.acc_random_walk_mps3_sqrthz = v[3];
  get(root, "rate_hz", rate_hz, path);
  return true;
}

bool read_euroc_T_BS(const std::string& path, Eigen::Isometry3d& T_BS) {
  if (!std::filesystem::exists(path)) return false;
  const YAML::Node root = load_yaml_file(path);
  Mat4d M = kIdentity4;
  if (!read_matrix4(root["T_BS"], M, path + ": T_BS")) throw std::runtime_error(path + ": missing key 'T_BS'");
  T_BS = to_isometry(M);
  return true;
}

}  // namespace kestrel::tools

// IMU synthesis and the real-IMU CSV reader for hybrid logs.
#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/drivers/text.hpp"
#include "kestrel/tools/sim_imu.hpp"

namespace kestrel::tools {
namespace {

constexpr double kDeg = 3.14159265358979323846 / 180.0;

double quantise(double v, double lsb) { return lsb > 0.0 ? std::round(v / lsb) * lsb : v; }

// Clips to +-range; true when it had to.
bool saturate(double& v, double range) {
  if (range <= 0.0 || std::abs(v) <= range) return false;
  v = std::copysign(range, v);
  return true;
}

}  // namespace

ImuModel ImuModel::bmx055(double acc_bias_tau_s) {
  ImuModel m;
  m.gyro_noise_density_rad_s_sqrthz = 0.014 * kDeg;  // 2.443e-4 rad/s/sqrt(Hz)
  // Table 1 gives no rate random walk. 2e-5 rad/s^2/sqrt(Hz) (the order of
  // the ADIS16448's Kalibr figure) lets the bias wander 2e-5 * sqrt(189 s) =
  // 2.7e-4 rad/s = 57 deg/h over paper 000's flight, inside the 360 deg/h RMS.
  m.gyro_random_walk_rad_s2_sqrthz = 2.0e-5;
  m.acc_noise_density_mps2_sqrthz = 150e-6 * kStandardGravity;  // 1.471e-3 m/s^2/sqrt(Hz)
  m.acc_bias_tau_s = acc_bias_tau_s;
  m.gyro_bias_init_sigma_rps = 360.0 / 3600.0 * kDeg;    // 360 deg/h = 1.745e-3 rad/s
  m.acc_bias_init_sigma_mps2 = 4e-3 * kStandardGravity;  // 4 mg = 3.923e-2 m/s^2
  // The 4 mg RMS read as the stationary std of eq. 6: sigma_w * sqrt(tau/2).
  m.acc_random_walk_mps3_sqrthz =
      acc_bias_tau_s > 0.0 ? m.acc_bias_init_sigma_mps2 / std::sqrt(0.5 * acc_bias_tau_s) : 1.0e-3;
  m.gyro_resolution_rps = 0.004 * kDeg;                // 6.98e-5 rad/s
  m.acc_resolution_mps2 = 0.98e-3 * kStandardGravity;  // 9.61e-3 m/s^2
  m.gyro_range_rps = 2000.0 * kDeg;                    // 34.9 rad/s
  m.acc_range_mps2 = 16.0 * kStandardGravity;          // 156.9 m/s^2
  return m;
}

ImuModel ImuModel::ideal() const {
  ImuModel m;
  m.acc_bias_tau_s = acc_bias_tau_s;
  m.gyro_range_rps = gyro_range_rps;
  m.acc_range_mps2 = acc_range_mps2;
  return m;
}

ImuNoise ImuModel::to_rig() const {
  ImuNoise n;
  n.gyro_noise_density_rad_s_sqrthz = gyro_noise_density_rad_s_sqrthz;
  n.gyro_random_walk_rad_s2_sqrthz = gyro_random_walk_rad_s2_sqrthz;
  n.acc_noise_density_mps2_sqrthz = acc_noise_density_mps2_sqrthz;
  n.acc_random_walk_mps3_sqrthz = acc_random_walk_mps3_sqrthz;
  n.acc_bias_tau_s = acc_bias_tau_s;
  n.gyro_range_rps = gyro_range_rps;
  n.acc_range_mps2 = acc_range_mps2;
  return n;
}

void true_imu(const TrajectoryState& s, double gravity_mps2, Eigen::Vector3d& gyro_rps,
              Eigen::Vector3d& acc_mps2) {
  const Eigen::Vector3d g_W(0.0, 0.0, -gravity_mps2);
  acc_mps2 = s.q_WB.conjugate() * (s.a_WB - g_W);
  gyro_rps = s.w_B;
}

ImuSynth::ImuSynth(const ImuModel& model, double rate_hz, double gravity_mps2, uint64_t seed)
    : model_(model), rate_hz_(rate_hz), gravity_(gravity_mps2), rng_(seed, RngStream::kImu) {
  if (!(rate_hz > 0.0)) throw std::invalid_argument("IMU rate must be > 0");
  bg_ = model_.gyro_bias_init_sigma_rps * gauss3();
  ba_ = model_.acc_bias_init_sigma_mps2 * gauss3();
}

Eigen::Vector3d ImuSynth::gauss3() {
  const double x = rng_.normal();
  const double y = rng_.normal();
  const double z = rng_.normal();
  return {x, y, z};
}

ImuSample ImuSynth::sample(const TrajectoryState& s, int64_t t_ns) {
  const double dt = 1.0 / rate_hz_;
  // Every sample draws the same count of normals whatever the model, so the
  // stream stays aligned when a density is zero.
  const Eigen::Vector3d n_bg = gauss3(), n_ba = gauss3(), n_g = gauss3(), n_a = gauss3();
  if (count_ > 0) {
    bg_ += model_.gyro_random_walk_rad_s2_sqrthz * std::sqrt(dt) * n_bg;
    if (model_.acc_bias_tau_s > 0.0) {
      // Exact discretisation of db = -b/tau dt + w: stays bounded, with the
      // stationary std sigma_w sqrt(tau/2).
      const double phi = std::exp(-dt / model_.acc_bias_tau_s);
      const double sd =
          model_.acc_random_walk_mps3_sqrthz * std::sqrt(0.5 * model_.acc_bias_tau_s * (1.0 - phi * phi));
      ba_ = phi * ba_ + sd * n_ba;
    } else {
      ba_ += model_.acc_random_walk_mps3_sqrthz * std::sqrt(dt) * n_ba;
    }
  }
  Eigen::Vector3d gyro, acc;
  true_imu(s, gravity_, gyro, acc);
  // Discrete white noise: density * sqrt(rate).
  gyro += bg_ + model_.gyro_noise_density_rad_s_sqrthz * std::sqrt(rate_hz_) * n_g;
  acc += ba_ + model_.acc_noise_density_mps2_sqrthz * std::sqrt(rate_hz_) * n_a;

  ImuSample out;
  out.t_ns = t_ns;
  out.t_recv_ns = t_ns;
  out.seq = static_cast<uint32_t>(count_);
  out.temp_c = 25.0f;
  for (int k = 0; k < 3; ++k) {
    double g = gyro[k], a = acc[k];
    if (saturate(g, model_.gyro_range_rps)) out.flags |= kImuGyroSaturated;
    if (saturate(a, model_.acc_range_mps2)) out.flags |= kImuAccSaturated;
    out.gyro_rps[static_cast<size_t>(k)] = quantise(g, model_.gyro_resolution_rps);
    out.acc_mps2[static_cast<size_t>(k)] = quantise(a, model_.acc_resolution_mps2);
  }
  ++count_;
  return out;
}

std::vector<ImuSample> load_euroc_imu_csv(const std::string& path) {
  namespace text = drivers::text;
  std::vector<std::string> lines;
  const text::LinesRead read = text::read_lines(path, lines);
  if (!read.opened) throw std::runtime_error(path + ": cannot open IMU file");
  if (!read) throw std::runtime_error(path + ": read error");
  std::vector<ImuSample> out;
  for (size_t k = 0; k < lines.size(); ++k) {
    const std::string line = text::trim(lines[k]);
    if (line.empty() || line[0] == '#') continue;
    const std::string at = path + ":" + std::to_string(k + 1);
    // Columns past the seventh are ignored, as EuRoC-derived files sometimes carry more.
    const std::vector<std::string> f = text::split(line, ',');
    if (f.size() < 7) {
      throw std::runtime_error(at + ": expected 7 fields (t_ns, w_xyz, a_xyz), got " +
                               std::to_string(f.size()));
    }
    ImuSample s;
    if (!text::parse_i64(f[0], s.t_ns)) throw std::runtime_error(at + ": bad timestamp '" + f[0] + "'");
    double v[6];
    for (int j = 0; j < 6; ++j) {
      if (!text::parse_finite_f64(f[j + 1], v[j])) {
        throw std::runtime_error(at + ": field " + std::to_string(j + 2) + " is not a number: '" + f[j + 1] +
                                 "'");
      }
    }
    if (!out.empty() && s.t_ns <= out.back().t_ns)
      throw std::runtime_error(at + ": time " + f[0] + " does not increase");
    s.t_recv_ns = s.t_ns;
    s.seq = static_cast<uint32_t>(out.size());
    s.gyro_rps = {v[0], v[1], v[2]};
    s.acc_mps2 = {v[3], v[4], v[5]};
    out.push_back(s);
  }
  if (out.empty()) throw std::runtime_error(path + ": no IMU samples");
  return out;
}

}  // namespace kestrel::tools

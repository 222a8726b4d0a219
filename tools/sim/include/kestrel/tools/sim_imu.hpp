// Synthetic IMU: exact specific force and body rate from a trajectory, plus
// the BMX055 error model of paper 000 (Table 1, eq. 6).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/msgs.hpp"
#include "kestrel/tools/sim_random.hpp"
#include "kestrel/tools/sim_trajectory.hpp"

namespace kestrel::tools {

// Continuous-time densities (Kalibr convention) plus what a real part adds:
// an initial bias, quantisation and saturation. All SI units.
struct ImuModel {
  double gyro_noise_density_rad_s_sqrthz = 0.0;
  double gyro_random_walk_rad_s2_sqrthz = 0.0;
  double acc_noise_density_mps2_sqrthz = 0.0;
  double acc_random_walk_mps3_sqrthz = 0.0;
  double acc_bias_tau_s = 0.0;            // eq. 6 bounded random walk; <= 0: plain random walk
  double gyro_bias_init_sigma_rps = 0.0;  // per-axis std of the turn-on bias
  double acc_bias_init_sigma_mps2 = 0.0;
  double gyro_resolution_rps = 0.0;  // LSB; 0 = no quantisation
  double acc_resolution_mps2 = 0.0;
  double gyro_range_rps = 0.0;  // |value| clipped here and flagged; 0 = unlimited
  double acc_range_mps2 = 0.0;

  // Paper 000 Table 1 converted to SI (docs/simulator.md shows the numbers):
  // gyro 0.014 deg/s/sqrt(Hz), bias RMS 360 deg/h, resolution 0.004 deg/s;
  // accel 150 ug/sqrt(Hz), bias RMS 4 mg, resolution 0.98 mg; ranges
  // +-2000 deg/s and +-16 g; tau 300 s.
  static ImuModel bmx055(double acc_bias_tau_s = 300.0);
  // Noise, biases and quantisation off; saturation limits kept.
  ImuModel ideal() const;
  // The Rig's view of the model (what an estimator is told).
  ImuNoise to_rig() const;
};

constexpr double kStandardGravity = 9.80665;  // m/s^2 per g

// True IMU readings for a trajectory state: a_B = R_WB^T (a_W - g_W) with
// g_W = (0, 0, -g), and the body rate.
void true_imu(const TrajectoryState& s, double gravity_mps2, Eigen::Vector3d& gyro_rps,
              Eigen::Vector3d& acc_mps2);

// Generates consecutive samples at a fixed rate. Bias processes advance by
// exactly one sample period per call, so call it once per sample, in order.
class ImuSynth {
 public:
  ImuSynth(const ImuModel& model, double rate_hz, double gravity_mps2, uint64_t seed);

  ImuSample sample(const TrajectoryState& s, int64_t t_ns);

  const Eigen::Vector3d& gyro_bias_rps() const { return bg_; }
  const Eigen::Vector3d& acc_bias_mps2() const { return ba_; }
  const ImuModel& model() const { return model_; }
  uint64_t count() const { return count_; }

 private:
  Eigen::Vector3d gauss3();
  ImuModel model_;
  double rate_hz_;
  double gravity_;
  SimRng rng_;
  Eigen::Vector3d bg_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d ba_ = Eigen::Vector3d::Zero();
  uint64_t count_ = 0;
};

// A real IMU log in EuRoC ASL CSV: `t_ns, w_xyz [rad/s], a_xyz [m/s^2]`.
// Throws std::runtime_error naming "file:line" on a malformed line or time
// that does not increase.
std::vector<ImuSample> load_euroc_imu_csv(const std::string& path);

}  // namespace kestrel::tools

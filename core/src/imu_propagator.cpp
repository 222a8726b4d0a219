#include "kestrel/core/imu_propagator.hpp"

#include <cmath>

#include "kestrel/core/so3.hpp"

namespace kestrel::core {
namespace {

Eigen::Vector3d to_eigen(const Vec3d& v) { return {v[0], v[1], v[2]}; }

}  // namespace

bool imu_sample_usable(const ImuSample& s) {
  for (int i = 0; i < 3; ++i) {
    if (!std::isfinite(s.gyro_rps[i]) || !std::isfinite(s.acc_mps2[i])) return false;
  }
  return (s.flags & (kImuNonFinite | kImuGyroSaturated | kImuAccSaturated)) == 0;
}

void ImuPropagator::reset(const NavState& s) {
  state_ = s;
  initialized_ = true;
  have_prev_ = false;
}

bool ImuPropagator::propagate(const ImuSample& s) {
  if (!imu_sample_usable(s)) {
    bool finite = true;
    for (int i = 0; i < 3; ++i) finite = finite && std::isfinite(s.gyro_rps[i]) && std::isfinite(s.acc_mps2[i]);
    if (!finite || (s.flags & kImuNonFinite)) {
      ++counts_.non_finite;
    } else {
      ++counts_.saturated;
    }
    return false;
  }
  if (!initialized_) return false;
  const Eigen::Vector3d gyro = to_eigen(s.gyro_rps);
  const Eigen::Vector3d acc = to_eigen(s.acc_mps2);
  if (!have_prev_) {
    // The state time may precede the first sample (initialiser output): the
    // first sample only anchors the integration.
    if (s.t_ns < state_.t_ns) {
      ++counts_.out_of_order;
      return false;
    }
    prev_gyro_ = gyro;
    prev_acc_ = acc;
    state_.t_ns = s.t_ns;
    have_prev_ = true;
    return true;
  }
  const int64_t dt_ns = s.t_ns - state_.t_ns;
  if (dt_ns <= 0) {
    ++counts_.out_of_order;
    return false;
  }
  if (dt_ns > opt_.max_gap_ns) ++counts_.gaps;
  if (dt_ns > opt_.max_integration_step_ns) {
    // Integrating a long gap with one sample pair invents motion; hold the
    // state and restart from this sample instead.
    prev_gyro_ = gyro;
    prev_acc_ = acc;
    state_.t_ns = s.t_ns;
    return true;
  }
  const double dt = 1e-9 * static_cast<double>(dt_ns);
  const Eigen::Vector3d g_W(0.0, 0.0, -opt_.gravity_mps2);

  const Eigen::Vector3d w_mid = 0.5 * (prev_gyro_ + gyro) - state_.bg_rps;
  const Eigen::Quaterniond q0 = state_.q_WB;
  const Eigen::Quaterniond q1 = (q0 * so3::exp_quat(w_mid * dt)).normalized();
  const Eigen::Vector3d a0_W = q0 * (prev_acc_ - state_.ba_mps2) + g_W;
  const Eigen::Vector3d a1_W = q1 * (acc - state_.ba_mps2) + g_W;
  const Eigen::Vector3d a_mid = 0.5 * (a0_W + a1_W);

  state_.p_WB += state_.v_WB * dt + 0.5 * a_mid * dt * dt;
  state_.v_WB += a_mid * dt;
  state_.q_WB = q1;
  state_.t_ns = s.t_ns;
  prev_gyro_ = gyro;
  prev_acc_ = acc;
  return true;
}

void StaticInitializer::reset() {
  t_start_ns_ = -1;
  n_ = 0;
  sum_g_.setZero();
  sum_gg_.setZero();
  sum_a_.setZero();
  sum_aa_.setZero();
}

bool StaticInitializer::add(const ImuSample& s, NavState& out) {
  if (!imu_sample_usable(s)) return false;
  if (t_start_ns_ < 0 || s.t_ns < t_start_ns_) {
    reset();
    t_start_ns_ = s.t_ns;
  }
  const Eigen::Vector3d g = to_eigen(s.gyro_rps);
  const Eigen::Vector3d a = to_eigen(s.acc_mps2);
  ++n_;
  sum_g_ += g;
  sum_gg_ += g.cwiseProduct(g);
  sum_a_ += a;
  sum_aa_ += a.cwiseProduct(a);
  if (s.t_ns - t_start_ns_ < opt_.window_ns || n_ < 10) return false;

  const double n = static_cast<double>(n_);
  const Eigen::Vector3d mean_g = sum_g_ / n;
  const Eigen::Vector3d mean_a = sum_a_ / n;
  const Eigen::Vector3d var_g = (sum_gg_ / n - mean_g.cwiseProduct(mean_g)).cwiseMax(0.0);
  const Eigen::Vector3d var_a = (sum_aa_ / n - mean_a.cwiseProduct(mean_a)).cwiseMax(0.0);
  const bool still = std::sqrt(var_g.maxCoeff()) < opt_.max_gyro_std_rps &&
                     std::sqrt(var_a.maxCoeff()) < opt_.max_acc_std_mps2 &&
                     std::abs(mean_a.norm() - opt_.gravity_mps2) < 0.5;
  if (!still) {
    // Tumbling window: start over from this sample.
    reset();
    t_start_ns_ = s.t_ns;
    return false;
  }
  // At rest the accelerometer measures -g rotated into B, i.e. +z_W up in B.
  const Eigen::Quaterniond q_WB =
      Eigen::Quaterniond::FromTwoVectors(mean_a.normalized(), Eigen::Vector3d::UnitZ());
  out = NavState{};
  out.t_ns = s.t_ns;
  out.q_WB = q_WB;
  out.bg_rps = mean_g;
  return true;
}

}  // namespace kestrel::core

#include "kestrel/core/imu_propagator.hpp"

#include <algorithm>
#include <cmath>

#include "kestrel/core/so3.hpp"

namespace kestrel::core {
namespace {}  // namespace

ImuPropagatorOptions imu_propagator_options(const Rig& rig) {
  ImuPropagatorOptions o;
  o.gravity_mps2 = rig.gravity_mps2;
  if (rig.imu_rate_hz > 0) o.max_gap_ns = static_cast<int64_t>(5e9 / rig.imu_rate_hz);
  return o;
}

bool imu_sample_usable(const ImuSample& s) {
  for (int i = 0; i < 3; ++i) {
    if (!std::isfinite(s.gyro_rps[i]) || !std::isfinite(s.acc_mps2[i])) return false;
  }
  return (s.flags & (kImuNonFinite | kImuGyroSaturated | kImuAccSaturated)) == 0;
}

PackedNavState pack(const NavState& x) {
  PackedNavState o{};
  o.t_ns = x.t_ns;
  for (int i = 0; i < 3; ++i) {
    o.p[i] = x.p_WB[i];
    o.v[i] = x.v_WB[i];
    o.bg[i] = x.bg_rps[i];
    o.ba[i] = x.ba_mps2[i];
  }
  o.q[0] = x.q_WB.w();
  o.q[1] = x.q_WB.x();
  o.q[2] = x.q_WB.y();
  o.q[3] = x.q_WB.z();
  return o;
}

NavState unpack(const PackedNavState& o) {
  NavState x;
  x.t_ns = o.t_ns;
  x.p_WB = Eigen::Vector3d(o.p[0], o.p[1], o.p[2]);
  x.q_WB = Eigen::Quaterniond(o.q[0], o.q[1], o.q[2], o.q[3]);
  x.v_WB = Eigen::Vector3d(o.v[0], o.v[1], o.v[2]);
  x.bg_rps = Eigen::Vector3d(o.bg[0], o.bg[1], o.bg[2]);
  x.ba_mps2 = Eigen::Vector3d(o.ba[0], o.ba[1], o.ba[2]);
  return x;
}

void ImuPropagator::reset(const NavState& s) {
  state_ = s;
  initialized_ = true;
  have_prev_ = false;
}

void ImuPropagator::correct(const NavState& s) {
  if (!initialized_ || s.t_ns != state_.t_ns) {
    reset(s);
    return;
  }
  state_ = s;
}

bool ImuPropagator::propagate(const ImuSample& s) {
  if (!imu_sample_usable(s)) {
    bool finite = true;
    for (int i = 0; i < 3; ++i)
      finite = finite && std::isfinite(s.gyro_rps[i]) && std::isfinite(s.acc_mps2[i]);
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

int StaticInitializer::ring_size() const {
  const int64_t n = opt_.window_ns / std::max<int64_t>(1, opt_.block_ns);
  return static_cast<int>(std::clamp<int64_t>(n, 1, kMaxBlocks));
}

void StaticInitializer::reset() {
  n_blocks_ = 0;
  head_ = 0;
  cur_ = Block{};
  cur_start_ns_ = -1;
  last_t_ns_ = -1;
}

bool StaticInitializer::window_stats(Eigen::Vector3d* mean_g, Eigen::Vector3d* mean_a, double* dev_g,
                                     double* dev_a) const {
  const int ring = ring_size();
  if (n_blocks_ < ring) return false;
  Eigen::Vector3d sg = Eigen::Vector3d::Zero(), sa = Eigen::Vector3d::Zero();
  int n = 0;
  for (int k = 0; k < n_blocks_; ++k) {
    const Block& b = blocks_[(head_ + k) % ring];
    sg += b.sum_g;
    sa += b.sum_a;
    n += b.n;
  }
  if (n < 10) return false;
  *mean_g = sg / n;
  *mean_a = sa / n;
  double dg = 0, da = 0;
  for (int k = 0; k < n_blocks_; ++k) {
    const Block& b = blocks_[(head_ + k) % ring];
    if (b.n == 0) continue;
    dg = std::max(dg, (b.sum_g / b.n - *mean_g).cwiseAbs().maxCoeff());
    da = std::max(da, (b.sum_a / b.n - *mean_a).cwiseAbs().maxCoeff());
  }
  *dev_g = dg;
  *dev_a = da;
  return true;
}

bool StaticInitializer::window_means(Eigen::Vector3d* gyro_mean, Eigen::Vector3d* acc_mean) const {
  double dg, da;
  return window_stats(gyro_mean, acc_mean, &dg, &da);
}

bool StaticInitializer::add(const ImuSample& s, NavState& out) {
  if (!imu_sample_usable(s)) return false;
  if (last_t_ns_ >= 0 && s.t_ns <= last_t_ns_) return false;  // out of order: counted by the propagator
  if (last_t_ns_ >= 0 && s.t_ns - last_t_ns_ > opt_.block_ns) reset();  // a gap breaks the window
  last_t_ns_ = s.t_ns;
  if (cur_start_ns_ < 0) cur_start_ns_ = s.t_ns;
  cur_.sum_g += to_eigen(s.gyro_rps);
  cur_.sum_a += to_eigen(s.acc_mps2);
  ++cur_.n;
  if (s.t_ns - cur_start_ns_ < opt_.block_ns) return false;

  // Block complete: slide the window of blocks.
  const int ring = ring_size();
  if (n_blocks_ < ring) {
    blocks_[(head_ + n_blocks_) % ring] = cur_;
    ++n_blocks_;
  } else {
    blocks_[head_] = cur_;
    head_ = (head_ + 1) % ring;
  }
  cur_ = Block{};
  cur_start_ns_ = s.t_ns;

  Eigen::Vector3d mean_g, mean_a;
  double dev_g, dev_a;
  if (!window_stats(&mean_g, &mean_a, &dev_g, &dev_a)) return false;
  const bool still = dev_g < opt_.max_gyro_dev_rps && dev_a < opt_.max_acc_dev_mps2 &&
                     std::abs(mean_a.norm() - opt_.gravity_mps2) < 0.5;
  if (!still) return false;
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

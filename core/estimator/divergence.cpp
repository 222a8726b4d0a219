#include "kestrel/core/divergence.hpp"

#include <algorithm>
#include <cmath>

namespace kestrel::core {
namespace {

// Gaps between fixes shorter than this are the frame period and the odd
// dropped frame, not coasting.
constexpr int64_t kCoastGraceNs = 100'000'000;

bool finite_state(const NavState& x) {
  return x.p_WB.allFinite() && x.v_WB.allFinite() && x.q_WB.coeffs().allFinite() && x.bg_rps.allFinite() &&
         x.ba_mps2.allFinite();
}

}  // namespace

std::string DivergenceOptions::validate() const {
  std::string e;
  if (!(max_coast_s > 0)) e += "max_coast_s: must be > 0\n";
  if (!(max_lost_s > 0)) e += "max_lost_s: must be > 0\n";
  if (!(max_speed_mps > 0)) e += "max_speed_mps: must be > 0\n";
  if (!(max_acc_bias_mps2 > 0)) e += "max_acc_bias_mps2: must be > 0\n";
  if (!(max_gyro_bias_rps > 0)) e += "max_gyro_bias_rps: must be > 0\n";
  if (!(max_position_sigma_m > 0)) e += "max_position_sigma_m: must be > 0\n";
  if (max_rejected_fixes < 0) e += "max_rejected_fixes: must be >= 0\n";
  return e;
}

const char* to_string(DivergenceCause c) {
  switch (c) {
    case DivergenceCause::kNone:
      return "none";
    case DivergenceCause::kCoastTimeout:
      return "coast_timeout";
    case DivergenceCause::kSpeed:
      return "speed";
    case DivergenceCause::kAccBias:
      return "acc_bias";
    case DivergenceCause::kGyroBias:
      return "gyro_bias";
    case DivergenceCause::kCovariance:
      return "covariance";
    case DivergenceCause::kVisualImuDisagreement:
      return "visual_imu_disagreement";
    case DivergenceCause::kNonFinite:
      return "non_finite";
  }
  return "unknown";
}

void DivergenceMonitor::advance_clock(int64_t t_ns) {
  if (clock_t_ns_ < 0) {
    clock_t_ns_ = t_ns;
    return;
  }
  if (t_ns <= clock_t_ns_) return;
  if (lost_) {
    counts_.lost_ns += t_ns - clock_t_ns_;
  } else if (last_fix_t_ns_ >= 0) {
    // The part of [clock, t] that lies beyond the grace after the last fix.
    counts_.coast_ns += std::max<int64_t>(0, t_ns - std::max(clock_t_ns_, last_fix_t_ns_ + kCoastGraceNs));
  }
  clock_t_ns_ = t_ns;
}

bool DivergenceMonitor::coasting(int64_t t_ns) const {
  return !lost_ && last_fix_t_ns_ >= 0 && t_ns - last_fix_t_ns_ > kCoastGraceNs;
}

void DivergenceMonitor::on_frame(int64_t t_ns, bool fix, bool rejected) {
  advance_clock(t_ns);
  // A leaky count: a refusal adds one, a fix takes two away, a frame with
  // no pose at all changes nothing. A diverged state that the tracker keeps
  // re-anchoring to (a new keyframe at the predicted pose every few frames,
  // the odd refusal slipping through the widened gate) refuses most frames
  // without ever refusing many in a row; a healthy one refuses few.
  if (fix) {
    last_fix_t_ns_ = std::max(last_fix_t_ns_, t_ns);
    lost_ = false;
    restarted_ = false;
    rejected_in_a_row_ = std::max(0, rejected_in_a_row_ - 2);
  } else if (rejected) {
    ++rejected_in_a_row_;
  }
}

DivergenceCause DivergenceMonitor::check(const NavState& x, const PoseCovariance* cov) {
  if (!finite_state(x)) return DivergenceCause::kNonFinite;
  advance_clock(x.t_ns);
  const int64_t max_coast_ns = static_cast<int64_t>(opt_.max_coast_s * 1e9);
  const int64_t max_lost_ns = static_cast<int64_t>(opt_.max_lost_s * 1e9);
  // The coast clock starts with the backend's first state: a camera that
  // never gives a fix is as much an outage as one that stops.
  if (last_fix_t_ns_ < 0) last_fix_t_ns_ = x.t_ns;
  if (!lost_ && x.t_ns - last_fix_t_ns_ > max_coast_ns) {
    lost_ = true;
    lost_since_t_ns_ = x.t_ns;
    ++counts_.coast_timeouts;
  }
  // A long outage: restart once per max_lost_s, so the placeholder pose
  // stays near where it was lost instead of running away on the IMU.
  if (lost_ && x.t_ns - lost_since_t_ns_ > max_lost_ns) return DivergenceCause::kCoastTimeout;
  if (x.v_WB.norm() > opt_.max_speed_mps) return DivergenceCause::kSpeed;
  if (x.ba_mps2.norm() > opt_.max_acc_bias_mps2) return DivergenceCause::kAccBias;
  if (x.bg_rps.norm() > opt_.max_gyro_bias_rps) return DivergenceCause::kGyroBias;
  if (cov != nullptr && cov->valid) {
    const double var = cov->cov.diagonal().head<3>().maxCoeff();
    if (!(var <= opt_.max_position_sigma_m * opt_.max_position_sigma_m)) return DivergenceCause::kCovariance;
  }
  if (opt_.max_rejected_fixes > 0 && rejected_in_a_row_ >= opt_.max_rejected_fixes)
    return DivergenceCause::kVisualImuDisagreement;
  return DivergenceCause::kNone;
}

void DivergenceMonitor::on_reinitialised(int64_t t_ns, DivergenceCause why) {
  advance_clock(t_ns);
  if (restarted_) {
    ++counts_.restarts_while_lost;
  } else {
    ++counts_.divergences;
    ++counts_.by_cause[static_cast<size_t>(why)];
  }
  restarted_ = true;
  lost_ = true;
  lost_since_t_ns_ = t_ns;
  rejected_in_a_row_ = 0;
}

}  // namespace kestrel::core

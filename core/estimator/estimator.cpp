#include "kestrel/core/estimator.hpp"

#include <cmath>

namespace kestrel::core {

namespace {
StaticInitOptions init_options(const Rig& rig) {
  StaticInitOptions o;
  o.gravity_mps2 = rig.gravity_mps2;
  // Two 0.1 s blocks: enough to average the gyro bias far below what the
  // window then refines, short enough that a log starting on the ground gets
  // poses for more than 99 % of its frames, and shorter than the window
  // backend's dynamic start (0.25 s), which must not pre-empt a still start.
  o.window_ns = 200'000'000;
  return o;
}
}  // namespace

DeadReckoningEstimator::DeadReckoningEstimator(const Rig& rig, int64_t moving_start_after_ns)
    : init_(init_options(rig)),
      prop_(imu_propagator_options(rig)),
      moving_start_after_ns_(moving_start_after_ns) {}

bool DeadReckoningEstimator::add_imu(const ImuSample& s) {
  ++counters_.imu_in;
  if (!prop_.initialized()) {
    if (first_t_ns_ < 0) first_t_ns_ = s.t_ns;
    NavState s0;
    if (init_.add(s, s0)) {
      prop_.reset(s0);
    } else if (imu_sample_usable(s) && s.t_ns - first_t_ns_ > moving_start_after_ns_) {
      // Never saw a still window (a moving start): take gravity from the
      // mean specific force of the last window, motion and all. Crude; the
      // optimizer's dynamic initialiser replaces it, dead reckoning has
      // nothing better.
      Eigen::Vector3d mean_g, mean_a;
      if (!init_.window_means(&mean_g, &mean_a)) {
        mean_g.setZero();
        mean_a = Eigen::Vector3d(s.acc_mps2[0], s.acc_mps2[1], s.acc_mps2[2]);
      }
      s0 = NavState{};
      s0.t_ns = s.t_ns;
      s0.q_WB = Eigen::Quaterniond::FromTwoVectors(mean_a.normalized(), Eigen::Vector3d::UnitZ());
      // The mean rate of a moving window is motion, not bias.
      s0.bg_rps.setZero();
      prop_.reset(s0);
      started_moving_ = true;
    } else {
      return false;
    }
    ++counters_.resets;
    out_.reset_counter = static_cast<uint32_t>(counters_.resets);
  }
  if (!prop_.propagate(s)) return false;
  ++counters_.imu_used;
  out_.state = prop_.state();
  out_.quality = TrackingQuality::kImuOnly;
  return true;
}

bool DeadReckoningEstimator::add_frame(const RgbdFrame&) {
  ++counters_.frames_in;
  return false;
}

const EstimatorCounters& DeadReckoningEstimator::counters() const {
  counters_.imu_rejects = prop_.counts();
  return counters_;
}

const char* tracking_quality_name(TrackingQuality q) {
  switch (q) {
    case TrackingQuality::kUninitialized:
      return "uninitialized";
    case TrackingQuality::kImuOnly:
      return "imu_only";
    case TrackingQuality::kTracking:
      return "tracking";
    case TrackingQuality::kLost:
      return "lost";
    case TrackingQuality::kVisionOnly:
      return "vision_only";
  }
  return "unknown";
}

}  // namespace kestrel::core

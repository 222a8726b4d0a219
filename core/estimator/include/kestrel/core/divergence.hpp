// Divergence detection shared by every backend that uses vision (vo, window,
// ekf). A backend that has lost the truth must say so and start over rather
// than keep publishing a pose that runs away on the IMU alone: PX4's EKF2 is
// trusted because it times out stale aiding and resets with a flag, and a
// flight controller fed by us must get at least that.
//
// The monitor only decides; the backend acts (zero the velocity, drop the
// tracker's keyframe, restart its window or filter), because what a clean
// re-initialisation means differs per backend. Fixed size, no allocation:
// it runs on the tracking and IMU threads.
#pragma once

#include <array>
#include <cstdint>
#include <string>

#include "kestrel/core/estimator.hpp"

namespace kestrel::core {

struct DivergenceOptions {
  // Longest IMU-only coast after the last visual fix before the pose is
  // reported lost. A BMX055-class accelerometer with a 0.1 m/s^2 bias error
  // drifts 5 cm in 1 s and 1.25 m in 5 s: beyond about a second the pose is
  // no longer worth flying on. The state itself is kept: vision that comes
  // back within max_lost_s usually finds it good (measured: restarting here
  // doubled the error on the hard flights, docs/safety.md).
  double max_coast_s = 1.0;
  // Reported lost this long without a fix: the velocity is no longer known
  // to better than ~0.5 m/s either, and the backend re-initialises.
  double max_lost_s = 5.0;
  // Physical bounds of a quadrotor; an estimate beyond them is a runaway, not a flight.
  double max_speed_mps = 25.0;
  // Bias estimates beyond what the sensor class can have (BMX055: +-80 mg
  // accelerometer offset, +-1 deg/s gyro zero-rate offset; x2 and x10 margin).
  double max_acc_bias_mps2 = 1.6;
  double max_gyro_bias_rps = 0.2;
  // Covariance growth: a position standard deviation beyond this (backends
  // that keep a covariance: ekf, window) means the estimate is no longer
  // constrained by anything.
  double max_position_sigma_m = 1.0;
  // Frames on which the tracker had a confident pose and the backend refused
  // it (the IMU-predicted motion and the visual motion disagree beyond the
  // gate), counted leakily (a fix takes two away): past this, one of them is
  // wrong, and vision that agrees with itself frame after frame is the
  // likelier one.
  int max_rejected_fixes = 8;

  // Empty when usable, else one line per problem naming the key.
  std::string validate() const;
};

class DivergenceMonitor {
 public:
  explicit DivergenceMonitor(const DivergenceOptions& o = {}) : opt_(o) {}

  // One camera frame was processed. fix: vision corrected the state.
  // rejected: the tracker had a pose and the backend refused it.
  void on_frame(int64_t t_ns, bool fix, bool rejected);

  // Checks the newest state (and covariance, when the backend has one).
  // kNone when the backend need not act (all is well, or a coast timeout
  // that only makes lost() true); otherwise the backend must re-initialise
  // and then call on_reinitialised(). Whether that counts as a new
  // divergence or a restart within one outage is the monitor's business.
  DivergenceCause check(const NavState& x, const PoseCovariance* cov);

  // The backend re-initialised at t_ns because check() said so.
  void on_reinitialised(int64_t t_ns, DivergenceCause why);

  // From a coast timeout or a divergence until the next visual fix: the
  // pose is not to be flown on.
  bool lost() const { return lost_; }
  // The state is coasting on the IMU alone (no fix for more than a frame or two).
  bool coasting(int64_t t_ns) const;
  const DivergenceCounts& counts() const { return counts_; }
  const DivergenceOptions& options() const { return opt_; }

 private:
  void advance_clock(int64_t t_ns);

  DivergenceOptions opt_;
  DivergenceCounts counts_;
  bool lost_ = false;
  int64_t last_fix_t_ns_ = -1;
  int64_t lost_since_t_ns_ = -1;  // lost, or last restarted, at this time
  bool restarted_ = false;        // a re-initialisation happened in this outage
  int64_t clock_t_ns_ = -1;       // newest time seen, for the time accounting
  int rejected_in_a_row_ = 0;
};

}  // namespace kestrel::core

// Front-end-only visual-inertial odometry: IMU propagation between frames,
// the tracker (paper 000's IMU-accelerated pose calculation) correcting the
// pose at every frame, no window optimisation. It is both a backend of its
// own (for comparisons, and the fallback when the optimizer is late) and what
// the optimizer builds on.
#pragma once

#include <memory>

#include "kestrel/core/divergence.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/core/tracker.hpp"

namespace kestrel::core {

struct FrontendOdometryOptions {
  TrackerOptions tracker;
  // Position/velocity fusion: per world axis a two-state Kalman filter whose
  // prediction is the IMU propagation and whose measurement is the tracked
  // position. The IMU carries velocity between frames; the tracker pulls it
  // back when the accelerometer bias makes it drift, without feeding every
  // centimetre of tracking noise into the velocity.
  double accel_noise_mps2_sqrthz = 0.2;     // white acceleration error incl. unmodelled bias
  double position_sigma_m = 0.005;          // tracked position noise
  double initial_velocity_sigma_mps = 2.0;  // at the first keyframe: the vehicle may already move
  // Attitude: the gyro is far better than the tracker over one frame (0.0001
  // vs ~0.05 deg), the tracker is drift-free over many. Each tracked frame
  // pulls the propagated attitude this share of the way to the tracked one.
  double attitude_gain = 0.5;
  double gyro_bias_gain = 0.02;  // integral share per tracked frame
  double gate_sigma = 6.0;       // innovations beyond this many sigma are not believed
  // Consecutive untracked frames before the keyframe is dropped and a new one
  // taken at the IMU-predicted pose (a re-initialisation, counted).
  int max_lost_frames = 3;
  // No still window within this span: start moving, gravity from the mean
  // specific force, velocity unknown (initial_velocity_sigma_mps). The same
  // 0.25 s as the window backend's: a log that starts on a running airframe
  // (rotor vibration) may show no still window for a second or more, and a
  // flight controller needs a pose from the start; the still window (0.2 s)
  // still wins whenever there is one. 2 s (the old value) left the first
  // second of the EuRoC MH_01 flights without a pose (96.6 % posed).
  int64_t moving_start_after_ns = 250'000'000;
  // Prediction uncertainty growth for the search window [px per second since the last tracked frame].
  double pred_sigma_px_per_s = 60.0;
  double pred_sigma_min_px = 4.0;
  // Divergence detection (the config's safety: section, docs/safety.md).
  DivergenceOptions divergence;
  // IMU failure in flight (unplugged, bus error): a frame this long after the
  // last IMU sample finds the IMU lost. Tracking then goes on in 6 DoF on the
  // camera alone (a constant-velocity prediction, quality kVisionOnly); when
  // samples return the propagation restarts from the camera's pose and
  // velocity with the biases it had. 0: never (the pose coasts on the last
  // IMU state and the tracker trusts its stale rotation).
  int64_t imu_outage_after_ns = 200'000'000;
  double vision_only_pred_sigma_px =
      10.0;  // the constant-velocity prediction's pixel uncertainty at one frame

  // One line per bad key ("gate_sigma: must be > 0"); empty when all are usable.
  [[nodiscard]] std::string validate() const;
};

class FrontendOdometry final : public Estimator {
 public:
  FrontendOdometry(const Rig& rig, const FrontendOdometryOptions& opt = {});
  const char* name() const override { return "frontend-vo"; }
  bool add_imu(const ImuSample& s) override;
  bool add_frame(const RgbdFrame& f) override;
  const EstimatorOutput& output() const override { return out_; }
  const EstimatorCounters& counters() const override;
  const TrackResult& last_track() const { return tracker_.last(); }

  // For a back end built on this front end (window_estimator.hpp).
  bool started() const { return started_; }
  Tracker& tracker() { return tracker_; }
  const Tracker& tracker() const { return tracker_; }
  EstimatorView view() const override {
    EstimatorView v;
    v.tracker = &tracker_;
    return v;
  }
  // A better estimate of the propagated state, at its time (propagated().t_ns):
  // replaces it, keeping the IMU integration anchor.
  void correct_state(const NavState& x);
  const NavState& propagated() const { return prop_.state(); }
  // The back end re-initialised: count it in the reset counter the output carries
  // (and drop the back end's covariance: it described the old estimate).
  void count_reset();
  // A back end's covariance of the pose, carried in the output until the next
  // one or a reset (the front end has none of its own).
  void set_pose_covariance(const PoseCovariance& c) { out_.pose_cov = c; }
  // Increments on every re-initialisation after a divergence: a back end
  // built on this front end restarts its own state when it changes.
  uint64_t divergence_epoch() const { return divergence_epoch_; }
  const DivergenceMonitor& divergence() const { return monitor_; }
  // A back end's own finding (its window solves keep failing, say): handled
  // like the front end's own, so both re-initialise together.
  void report_divergence(DivergenceCause why);
  // A back end's map: where W sits in the map frame, carried in the output.
  void set_map_frame(const MapFrameState& m) { out_.map = m; }
  // The IMU is silent (imu_outage_after_ns): frames are tracked on the camera alone.
  bool vision_only() const { return vision_only_; }
  uint64_t imu_outages() const { return outages_; }

 private:
  bool add_frame_vision_only(const RgbdFrame& f);
  void note_pose(const Eigen::Isometry3d& T_WC, int64_t t_ns);
  // A frame tracked (the state already corrected) / not tracked: the output's
  // quality and the lost-frame count that restarts the tracker.
  bool took_frame(const Eigen::Isometry3d& T_WC, int64_t t_ns, TrackingQuality q, bool fix);
  bool missed_frame(int64_t t_ns, TrackingQuality q, bool rejected);

  FrontendOdometryOptions opt_;
  Eigen::Isometry3d T_BC_ = Eigen::Isometry3d::Identity();
  DeadReckoningEstimator init_and_imu_;  // static initialisation + IMU propagation
  Tracker tracker_;
  ImuPropagator prop_;
  bool started_ = false;
  EstimatorOutput out_;
  mutable EstimatorCounters counters_;
  int lost_frames_ = 0;
  int64_t last_tracked_t_ns_ = -1;
  uint64_t frames_tracked_ = 0;
  Eigen::Vector3d last_gyro_rps_ = Eigen::Vector3d::Zero();
  // Per-axis covariance of (p, v), shared by x, y, z (same noise on each).
  Eigen::Matrix2d P_pv_ = Eigen::Matrix2d::Identity();
  int64_t P_t_ns_ = -1;
  uint64_t gated_ = 0;
  bool tracker_has_tracked_ = false;
  bool refused_in_streak_ = false;  // a frame of the current untracked streak was refused by the gate
  DivergenceMonitor monitor_;
  uint64_t divergence_epoch_ = 0;
  NavState last_fix_state_;  // the state after the newest visual fix: a finite anchor to restart from
  bool have_fix_state_ = false;

  void supervise();
  void reinitialise(DivergenceCause why);
  // IMU outage: the last sample used, and the last two camera poses for the
  // constant-velocity prediction while the IMU is silent.
  int64_t last_imu_t_ns_ = -1;
  bool vision_only_ = false;
  uint64_t outages_ = 0;
  Eigen::Isometry3d T_WC_last_ = Eigen::Isometry3d::Identity(), T_WC_prev_ = Eigen::Isometry3d::Identity();
  int64_t t_last_ns_ = -1, t_prev_ns_ = -1;
};

}  // namespace kestrel::core

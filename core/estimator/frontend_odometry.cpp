#include "kestrel/core/frontend_odometry.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "kestrel/core/rig_transforms.hpp"
#include "kestrel/core/so3.hpp"

namespace kestrel::core {
std::string FrontendOdometryOptions::validate() const {
  std::string e;
  const std::string t = tracker.validate();
  if (!t.empty()) e += t;
  if (!(accel_noise_mps2_sqrthz > 0)) e += "accel_noise_mps2_sqrthz: must be > 0\n";
  if (!(position_sigma_m > 0)) e += "position_sigma_m: must be > 0\n";
  if (!(initial_velocity_sigma_mps > 0)) e += "initial_velocity_sigma_mps: must be > 0\n";
  // Gains are shares of the way to the tracked value: above 1 overshoots
  // every frame and the attitude oscillates.
  if (!(attitude_gain >= 0 && attitude_gain <= 1)) e += "attitude_gain: in [0, 1]\n";
  if (!(gyro_bias_gain >= 0 && gyro_bias_gain <= 1)) e += "gyro_bias_gain: in [0, 1]\n";
  if (!(gate_sigma > 0)) e += "gate_sigma: must be > 0\n";
  if (max_lost_frames < 1) e += "max_lost_frames: at least 1\n";
  if (moving_start_after_ns < 0) e += "moving_start_after_ns: must be >= 0\n";
  if (!(pred_sigma_min_px >= 0 && pred_sigma_px_per_s >= 0)) e += "pred_sigma_*: min >= 0, rate >= 0\n";
  if (imu_outage_after_ns < 0) e += "imu_outage_after_ns: must be >= 0 (0: never)\n";
  if (!(vision_only_pred_sigma_px > 0)) e += "vision_only_pred_sigma_px: must be > 0\n";
  const std::string d = divergence.validate();
  if (!d.empty()) e += d;
  return e;
}

FrontendOdometry::FrontendOdometry(const Rig& rig, const FrontendOdometryOptions& opt)
    : opt_(opt),
      T_BC_(to_isometry(rig.T_BC)),
      init_and_imu_(rig, opt.moving_start_after_ns),
      tracker_(rig, opt.tracker),
      prop_(imu_propagator_options(rig)),
      monitor_(opt.divergence) {
  const std::string err = opt.validate();
  if (!err.empty()) throw std::invalid_argument("FrontendOdometryOptions:\n" + err);
}

bool FrontendOdometry::add_imu(const ImuSample& s) {
  ++counters_.imu_in;
  if (!started_) {
    // Until the static initialiser has a state, the dead-reckoning backend
    // owns the samples; then this backend takes over the propagation.
    if (!init_and_imu_.add_imu(s)) return false;
    prop_.reset(init_and_imu_.output().state);
    started_ = true;
    ++counters_.resets;
    out_.reset_counter = static_cast<uint32_t>(counters_.resets);
  }
  if (vision_only_ && imu_sample_usable(s)) {
    // The IMU is back: restart the propagation at this sample from the
    // camera's pose moved on by its velocity, with the biases from before.
    NavState x = prop_.state();
    const double ahead_s = 1e-9 * static_cast<double>(s.t_ns - x.t_ns);
    if (ahead_s > 0 && ahead_s < 0.5) x.p_WB += x.v_WB * ahead_s;
    x.t_ns = s.t_ns;
    prop_.reset(x);
    vision_only_ = false;
  }
  if (!prop_.propagate(s)) return false;
  last_imu_t_ns_ = s.t_ns;
  last_gyro_rps_ = Eigen::Vector3d(s.gyro_rps[0], s.gyro_rps[1], s.gyro_rps[2]);
  ++counters_.imu_used;
  out_.state = prop_.state();
  if (out_.quality == TrackingQuality::kUninitialized) out_.quality = TrackingQuality::kImuOnly;
  supervise();
  return true;
}
void FrontendOdometry::supervise() {
  const DivergenceCause why = monitor_.check(prop_.state(), &out_.pose_cov);
  if (why != DivergenceCause::kNone) reinitialise(why);
  // A coast timeout only flags the output; the state runs on.
  if (monitor_.lost()) out_.quality = TrackingQuality::kLost;
}

void FrontendOdometry::report_divergence(DivergenceCause why) {
  if (!started_ || monitor_.lost()) return;
  reinitialise(why);
}

// A clean restart: the velocity and any implausible bias are forgotten, the
// tracker's keyframe is dropped (its pose came from the diverged state), and
// the next keyframe re-anchors the pose with the velocity unknown, as at the
// start. The attitude is kept: the gyro holds it far longer than the
// accelerometer holds position. The output says kLost until a visual fix.
void FrontendOdometry::reinitialise(DivergenceCause why) {
  NavState x = prop_.state();
  const bool finite =
      x.p_WB.allFinite() && x.q_WB.coeffs().allFinite() && x.bg_rps.allFinite() && x.ba_mps2.allFinite();
  if (!finite && have_fix_state_) {
    const int64_t t = x.t_ns;
    x = last_fix_state_;
    x.t_ns = t;
  } else if (!finite) {
    x.p_WB.setZero();
    x.q_WB.setIdentity();
  }
  x.v_WB.setZero();
  const DivergenceOptions& d = opt_.divergence;
  if (!finite || why == DivergenceCause::kAccBias || !(x.ba_mps2.norm() <= d.max_acc_bias_mps2))
    x.ba_mps2.setZero();
  if (!finite || why == DivergenceCause::kGyroBias || !(x.bg_rps.norm() <= d.max_gyro_bias_rps))
    x.bg_rps.setZero();
  prop_.correct(x);
  out_.state = prop_.state();
  tracker_.reset();
  tracker_has_tracked_ = false;
  last_tracked_t_ns_ = -1;
  lost_frames_ = 0;
  P_pv_ << opt_.position_sigma_m * opt_.position_sigma_m, 0, 0,
      opt_.initial_velocity_sigma_mps * opt_.initial_velocity_sigma_mps;
  ++counters_.resets;
  out_.reset_counter = static_cast<uint32_t>(counters_.resets);
  out_.pose_cov.valid = false;
  ++divergence_epoch_;
  monitor_.on_reinitialised(x.t_ns, why);
  out_.quality = TrackingQuality::kLost;
}

bool FrontendOdometry::add_frame(const RgbdFrame& f) {
  ++counters_.frames_in;
  if (!started_) return false;
  if (opt_.imu_outage_after_ns > 0 && last_imu_t_ns_ >= 0 &&
      f.t_ns - last_imu_t_ns_ > opt_.imu_outage_after_ns)
    return add_frame_vision_only(f);
  const NavState& s = prop_.state();
  // The propagated state is at the last IMU sample, up to one IMU period
  // before the frame; extrapolate to the frame time with the last rate and
  // the velocity (at 300 deg/s, 2.5 ms is 0.75 deg: several pixels).
  const double ahead_s = 1e-9 * static_cast<double>(f.t_ns - s.t_ns);
  const Eigen::Vector3d w_B = last_gyro_rps_ - s.bg_rps;
  Eigen::Isometry3d T_WB_pred = Eigen::Isometry3d::Identity();
  T_WB_pred.linear() =
      (s.q_WB * Eigen::Quaterniond(Eigen::AngleAxisd(
                    w_B.norm() * ahead_s,
                    w_B.norm() > 1e-12 ? Eigen::Vector3d(w_B.normalized()) : Eigen::Vector3d::UnitZ())))
          .toRotationMatrix();
  T_WB_pred.translation() = s.p_WB + s.v_WB * ahead_s;
  const Eigen::Isometry3d T_WC_pred = T_WB_pred * T_BC_;
  const double since_s = last_tracked_t_ns_ < 0
                             ? 1.0
                             : 1e-9 * static_cast<double>(std::max<int64_t>(0, f.t_ns - last_tracked_t_ns_));
  const double sigma_px = std::max(opt_.pred_sigma_min_px, opt_.pred_sigma_px_per_s * since_s);

  const TrackResult& r = tracker_.track(f.t_ns, f.rgb, f.depth, f.right, T_WC_pred, sigma_px);
  // Predict the (p, v) covariance to the frame time.
  if (P_t_ns_ >= 0) {
    const double dt = std::max(0.0, 1e-9 * static_cast<double>(f.t_ns - P_t_ns_));
    Eigen::Matrix2d F;
    F << 1, dt, 0, 1;
    const double q = opt_.accel_noise_mps2_sqrthz * opt_.accel_noise_mps2_sqrthz;
    Eigen::Matrix2d Q;
    Q << q * dt * dt * dt / 3, q * dt * dt / 2, q * dt * dt / 2, q * dt;
    P_pv_ = F * P_pv_ * F.transpose() + Q;
  }
  P_t_ns_ = f.t_ns;
  bool accept = r.tracked() || r.status == TrackStatus::kNewKeyframe;
  bool rejected = false;
  Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();
  Eigen::Vector3d innovation = Eigen::Vector3d::Zero();
  const double S = P_pv_(0, 0) + opt_.position_sigma_m * opt_.position_sigma_m;
  if (accept) {
    T_WB = r.T_WC * T_BC_.inverse();
    innovation = T_WB.translation() - T_WB_pred.translation();
    if (r.tracked() && innovation.norm() > opt_.gate_sigma * std::sqrt(S)) {
      // A jump the IMU cannot explain: wrong matches more likely than wrong physics.
      accept = false;
      rejected = true;
      ++gated_;
    }
  }
  if (accept) {
    NavState corrected = s;
    // The tracked pose holds at the frame time; the propagated state is at
    // the last IMU sample, up to one IMU period earlier: move the tracked
    // pose back by that span so both refer to the state's time (at 1 m/s and
    // 400 Hz the difference is 2.5 mm, the size of the errors we care about).
    const double back_s = 1e-9 * static_cast<double>(f.t_ns - s.t_ns);
    const Eigen::Vector3d w = last_gyro_rps_ - s.bg_rps;
    const Eigen::Quaterniond q_meas =
        Eigen::Quaterniond(T_WB.linear()) *
        Eigen::Quaterniond(Eigen::AngleAxisd(-w.norm() * back_s, w.norm() > 1e-12
                                                                     ? Eigen::Vector3d(w.normalized())
                                                                     : Eigen::Vector3d::UnitZ()));
    const Eigen::Vector3d p_meas = T_WB.translation() - s.v_WB * back_s;
    if (r.status == TrackStatus::kNewKeyframe && !tracker_has_tracked_) {
      // First keyframe: it defines the pose; the velocity is still unknown.
      corrected.p_WB = p_meas;
      P_pv_ << opt_.position_sigma_m * opt_.position_sigma_m, 0, 0,
          opt_.initial_velocity_sigma_mps * opt_.initial_velocity_sigma_mps;
    } else if (r.tracked()) {
      tracker_has_tracked_ = true;
      const Eigen::Vector3d y = p_meas - s.p_WB;
      const Eigen::Vector2d K = P_pv_.col(0) / S;
      corrected.p_WB = s.p_WB + K(0) * y;
      corrected.v_WB = s.v_WB + K(1) * y;
      P_pv_ = (Eigen::Matrix2d::Identity() - K * Eigen::RowVector2d(1, 0)) * P_pv_;
      // Mahony-style: a proportional pull of the attitude towards the tracked
      // one, and an integral term that learns the gyro bias from the same
      // rotation error (the static initialiser's bias is only as good as the
      // still period it had, and some flights have none).
      const Eigen::Vector3d e = so3::Log(Eigen::Quaterniond(s.q_WB.conjugate() * q_meas).toRotationMatrix());
      corrected.q_WB = (s.q_WB * so3::exp_quat(opt_.attitude_gain * e)).normalized();
      const double dt_frame =
          last_tracked_t_ns_ < 0 ? 0.0 : 1e-9 * static_cast<double>(f.t_ns - last_tracked_t_ns_);
      if (dt_frame > 1e-3 && dt_frame < 0.5) corrected.bg_rps -= opt_.gyro_bias_gain * e / dt_frame;
    }
    // A keyframe taken while coasting keeps the IMU pose: nothing to correct.
    corrected.t_ns = s.t_ns;
    prop_.correct(corrected);
    return took_frame(r.T_WC, f.t_ns, TrackingQuality::kTracking, r.tracked());
  }
  // Not tracked: coast on the IMU; after a few frames, start over from a new
  // keyframe at the predicted pose rather than matching an ever staler one.
  return missed_frame(f.t_ns, TrackingQuality::kImuOnly, rejected);
}

// fix: the frame was tracked (a keyframe alone is an anchor at the predicted
// pose, not a fix, and claims q only when the last frame did).
bool FrontendOdometry::took_frame(const Eigen::Isometry3d& T_WC, int64_t t_ns, TrackingQuality q, bool fix) {
  note_pose(T_WC, t_ns);
  out_.state = prop_.state();
  monitor_.on_frame(t_ns, fix, false);
  if (fix) {
    last_fix_state_ = out_.state;
    have_fix_state_ = true;
    refused_in_streak_ = false;
  }
  if (monitor_.lost()) {
    out_.quality = TrackingQuality::kLost;
  } else if (fix || out_.quality == q) {
    out_.quality = q;
  } else if (q == TrackingQuality::kTracking) {
    out_.quality = TrackingQuality::kImuOnly;
  }
  last_tracked_t_ns_ = t_ns;
  lost_frames_ = 0;
  ++frames_tracked_;
  ++counters_.frames_used;
  supervise();
  return true;
}

// rejected: the tracker had a pose the gate refused (vision and the IMU disagree).
bool FrontendOdometry::missed_frame(int64_t t_ns, TrackingQuality q, bool rejected) {
  ++lost_frames_;
  refused_in_streak_ = refused_in_streak_ || rejected;
  monitor_.on_frame(t_ns, false, rejected);
  out_.quality = monitor_.lost() ? TrackingQuality::kLost : q;
  supervise();
  if (lost_frames_ >= opt_.max_lost_frames && tracker_.has_keyframe()) {
    // Frames refused for disagreeing with the prediction: the velocity is
    // the suspect, so the frames after the new keyframe may correct it at
    // the start-up rate instead of the steady-state one.
    if (refused_in_streak_) {
      P_pv_(0, 1) = P_pv_(1, 0) = 0.0;
      P_pv_(1, 1) = std::max(P_pv_(1, 1), opt_.initial_velocity_sigma_mps * opt_.initial_velocity_sigma_mps);
      refused_in_streak_ = false;
    }
    tracker_.reset();
    ++counters_.resets;
    out_.reset_counter = static_cast<uint32_t>(counters_.resets);
    out_.pose_cov.valid = false;
    lost_frames_ = 0;
  }
  return false;
}

void FrontendOdometry::note_pose(const Eigen::Isometry3d& T_WC, int64_t t_ns) {
  T_WC_prev_ = T_WC_last_;
  t_prev_ns_ = t_last_ns_;
  T_WC_last_ = T_WC;
  t_last_ns_ = t_ns;
}

// The IMU is silent: constant-velocity prediction, 6-DoF tracking, and the
// tracked pose (with the velocity between the last two) becomes the state.
bool FrontendOdometry::add_frame_vision_only(const RgbdFrame& f) {
  if (!vision_only_) {
    vision_only_ = true;
    ++outages_;
  }
  if (t_last_ns_ <= last_imu_t_ns_) {
    // No frame tracked since the last sample (frames tracked while the IMU
    // was silent but not yet given up on are newer, and better): the last
    // IMU state's pose and velocity start the motion model.
    const NavState& s = prop_.state();
    Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();
    T_WB.linear() = s.q_WB.toRotationMatrix();
    T_WB.translation() = s.p_WB;
    T_WC_prev_ = T_WB * T_BC_;
    t_prev_ns_ = s.t_ns;
    T_WB.translation() += s.v_WB * 0.001;
    T_WC_last_ = T_WB * T_BC_;
    t_last_ns_ = s.t_ns + 1'000'000;
  }
  Eigen::Isometry3d T_WC_pred = T_WC_last_;
  if (t_prev_ns_ >= 0 && t_last_ns_ > t_prev_ns_) {
    const double ratio = std::clamp(
        static_cast<double>(f.t_ns - t_last_ns_) / static_cast<double>(t_last_ns_ - t_prev_ns_), 0.0, 100.0);
    const Eigen::Isometry3d D = T_WC_prev_.inverse() * T_WC_last_;
    Eigen::Isometry3d Ds = Eigen::Isometry3d::Identity();
    Ds.linear() = so3::Exp(ratio * so3::Log(D.linear()));
    Ds.translation() = ratio * D.translation();
    T_WC_pred = T_WC_last_ * Ds;
  }
  const double since_s =
      last_tracked_t_ns_ < 0 ? 1.0 : 1e-9 * static_cast<double>(f.t_ns - last_tracked_t_ns_);
  const double sigma_px =
      opt_.vision_only_pred_sigma_px + opt_.pred_sigma_px_per_s * std::max(0.0, since_s - 0.034);
  const TrackResult& r =
      tracker_.track(f.t_ns, f.rgb, f.depth, f.right, T_WC_pred, sigma_px, /*rotation_known=*/false);
  if (r.tracked() || r.status == TrackStatus::kNewKeyframe) {
    const Eigen::Isometry3d T_WB = r.T_WC * T_BC_.inverse();
    const double dt_s = 1e-9 * static_cast<double>(f.t_ns - t_last_ns_);
    NavState x = prop_.state();
    if (dt_s > 1e-3) x.v_WB = (T_WB.translation() - (T_WC_last_ * T_BC_.inverse()).translation()) / dt_s;
    x.p_WB = T_WB.translation();
    x.q_WB = Eigen::Quaterniond(T_WB.linear()).normalized();
    x.t_ns = f.t_ns;
    prop_.reset(x);
    return took_frame(r.T_WC, f.t_ns, TrackingQuality::kVisionOnly, r.tracked());
  }
  // Neither camera nor IMU: the pose coasts on the motion model, and says so.
  return missed_frame(f.t_ns, TrackingQuality::kLost, false);
}

void FrontendOdometry::correct_state(const NavState& x) {
  prop_.correct(x);
  out_.state = prop_.state();
  // While the IMU is silent the motion model runs on these poses: it takes the back end's too.
  if (vision_only_ && x.t_ns == t_last_ns_) {
    Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();
    T_WB.linear() = x.q_WB.normalized().toRotationMatrix();
    T_WB.translation() = x.p_WB;
    T_WC_last_ = T_WB * T_BC_;
  }
}

void FrontendOdometry::count_reset() {
  ++counters_.resets;
  out_.reset_counter = static_cast<uint32_t>(counters_.resets);
  out_.pose_cov.valid = false;
}

const EstimatorCounters& FrontendOdometry::counters() const {
  counters_.imu_rejects = prop_.counts();
  counters_.divergence = monitor_.counts();
  return counters_;
}

}  // namespace kestrel::core

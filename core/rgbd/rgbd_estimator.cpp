#include "kestrel/core/rgbd_estimator.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "kestrel/core/rig_transforms.hpp"
#include "kestrel/core/so3.hpp"

namespace kestrel::core {
namespace {

// The window's bias factor needs IMU densities even when no state has an IMU
// factor; nominal ones, never used for a residual.
WindowOptions vision_only(WindowOptions w, const Rig& rig) {
  ImuNoise n;
  n.gyro_noise_density_rad_s_sqrthz = 1e-4;
  n.acc_noise_density_mps2_sqrthz = 1e-3;
  n.gyro_random_walk_rad_s2_sqrthz = 1e-5;
  n.acc_random_walk_mps3_sqrthz = 1e-4;
  w.imu = ImuNoiseParams::from_imu_noise(n, 200.0);
  w.depth_sigma_coeff_per_m =
      rig.depth.sigma_coeff_per_m > 0 ? rig.depth.sigma_coeff_per_m : w.depth_sigma_coeff_per_m;
  return w;
}

}  // namespace

std::string RgbdEstimatorOptions::validate() const {
  std::ostringstream e;
  e << tracker.validate() << window.validate();
  if (min_observations < 3) e << "min_observations: at least 3\n";
  if (!(pred_sigma_px > 0) || !(pred_sigma_px_per_s >= 0))
    e << "pred_sigma_px > 0, pred_sigma_px_per_s >= 0\n";
  if (max_lost_frames < 1) e << "max_lost_frames: at least 1\n";
  if (!(map_pose_sigma_m > 0) || !(map_pose_sigma_rad > 0)) e << "map_pose_sigma_m/rad: must be > 0\n";
  if (!(max_correction_m > 0)) e << "max_correction_m: must be > 0\n";
  return e.str();
}

RgbdEstimator::RgbdEstimator(const Rig& rig, const RgbdEstimatorOptions& opt)
    : opt_([&] {
        RgbdEstimatorOptions o = opt;
        o.window = vision_only(o.window, rig);
        return o;
      }()),
      T_BC_(to_isometry(rig.T_BC)),
      T_CB_(T_BC_.inverse()),
      tracker_(rig, opt.tracker),
      monitor_(opt.divergence) {
  const std::string err = opt_.validate();
  if (!err.empty()) throw std::invalid_argument("RgbdEstimatorOptions:\n" + err);
  if (opt_.use_window)
    window_ = std::make_unique<WindowOptimizer>(WindowOptimizer::pinhole_of(rig), T_BC_, opt_.window);
  // The world is the first body pose.
  T_WC_last_ = T_WC_prev_ = T_BC_;
}

RgbdEstimator::~RgbdEstimator() = default;

bool RgbdEstimator::add_imu(const ImuSample&) {
  ++counters_.imu_in;
  return false;
}

// Constant velocity: the last frame-to-frame motion, scaled to the time step.
Eigen::Isometry3d RgbdEstimator::predict(int64_t t_ns) const {
  if (t_last_ns_ < 0 || t_prev_ns_ < 0 || t_last_ns_ <= t_prev_ns_) return T_WC_last_;
  const double ratio = std::clamp(
      static_cast<double>(t_ns - t_last_ns_) / static_cast<double>(t_last_ns_ - t_prev_ns_), 0.0, 3.0);
  const Eigen::Isometry3d D = T_WC_prev_.inverse() * T_WC_last_;  // last in prev
  Eigen::Isometry3d Ds = Eigen::Isometry3d::Identity();
  Ds.linear() = so3::Exp(ratio * so3::Log(D.linear()));
  Ds.translation() = ratio * D.translation();
  return T_WC_last_ * Ds;
}

void RgbdEstimator::restart() {
  tracker_.reset();
  if (window_) window_->reset();
  window_started_ = false;
  ++rc_.restarts;
  ++counters_.resets;
  out_.reset_counter = static_cast<uint32_t>(counters_.resets);
  lost_frames_ = 0;
}

bool RgbdEstimator::add_frame(const RgbdFrame& f) {
  ++counters_.frames_in;
  if (t_last_ns_ >= 0 && f.t_ns <= t_last_ns_) return false;
  const Eigen::Isometry3d T_WC_pred = predict(f.t_ns);
  const double since_s = last_tracked_t_ns_ < 0
                             ? 0.0
                             : 1e-9 * static_cast<double>(std::max<int64_t>(0, f.t_ns - last_tracked_t_ns_));
  const double sigma_px = opt_.pred_sigma_px + opt_.pred_sigma_px_per_s * std::max(0.0, since_s - 0.034);
  const TrackResult& r =
      tracker_.track(f.t_ns, f.rgb, f.depth, f.right, T_WC_pred, sigma_px, /*rotation_known=*/false);
  const bool accepted = r.tracked() || r.status == TrackStatus::kNewKeyframe;
  Eigen::Isometry3d T_WC = T_WC_pred;
  if (accepted) {
    T_WC = r.T_WC;
    rc_.tracked += r.tracked() ? 1 : 0;
    rc_.motion_model += r.tracked() && r.motion_model ? 1 : 0;
    if (r.tracked()) rc_.refined_rms_px_sum += r.refined_rms_px;
    rc_.keyframes += r.keyframe ? 1 : 0;
    rc_.model_estimates += static_cast<uint64_t>(r.model_estimates);
    const int n_obs = tracker_.num_observations();
    // A motion-model pose (no depth, no consensus) stays out of the window:
    // its depth-less observations would pull the frames that have depth.
    if (window_ && n_obs >= opt_.min_observations && !r.motion_model) {
      WindowFrameInput in;
      in.t_ns = f.t_ns;
      const Eigen::Isometry3d T_WB = T_WC * T_CB_;
      in.guess.t_ns = f.t_ns;
      in.guess.p_WB = T_WB.translation();
      in.guess.q_WB = Eigen::Quaterniond(T_WB.linear());
      in.vision_only = true;
      in.obs = tracker_.observations();
      in.n_obs = std::min(n_obs, opt_.window.max_obs_per_frame);
      in.keyframe = r.keyframe || !window_started_;
      in.has_pose_prior = opt_.use_map_pose && r.keyframe && r.map_pose_valid;
      if (in.has_pose_prior) {
        const Eigen::Isometry3d T_WB_map = r.T_WC_map * T_CB_;
        in.prior_p_WB = T_WB_map.translation();
        in.prior_q_WB = Eigen::Quaterniond(T_WB_map.linear());
        in.prior_sigma_p_m = std::max(opt_.map_pose_sigma_m, r.map_sigma_p_m);
        in.prior_sigma_rad = std::max(opt_.map_pose_sigma_rad, r.map_sigma_rad);
        ++rc_.map_poses;
      }
      if (!window_started_) window_->reset();
      if (window_->add_frame(in)) {
        window_started_ = true;
        const WindowOptimizer::Result res = window_->optimize();
        const NavState& x = window_->latest();
        Eigen::Isometry3d T_WB_opt = Eigen::Isometry3d::Identity();
        T_WB_opt.linear() = x.q_WB.normalized().toRotationMatrix();
        T_WB_opt.translation() = x.p_WB;
        const bool ok = res.ok && x.t_ns == f.t_ns && x.p_WB.allFinite() && x.q_WB.coeffs().allFinite() &&
                        (T_WB_opt.translation() - T_WB.translation()).norm() <= opt_.max_correction_m;
        if (ok) {
          ++rc_.solves_ok;
          T_WC = T_WB_opt * T_BC_;
          NavState kf;
          if (tracker_.has_keyframe() && window_->state_of(tracker_.keyframe_t_ns(), &kf)) {
            Eigen::Isometry3d T_WB_kf = Eigen::Isometry3d::Identity();
            T_WB_kf.linear() = kf.q_WB.normalized().toRotationMatrix();
            T_WB_kf.translation() = kf.p_WB;
            tracker_.set_keyframe_pose(tracker_.keyframe_t_ns(), T_WB_kf * T_BC_);
          }
        } else {
          ++rc_.solves_rejected;
        }
      }
    }
    last_tracked_t_ns_ = f.t_ns;
    lost_frames_ = 0;
    hold_ = false;
    ++counters_.frames_used;
    out_.quality = TrackingQuality::kVisionOnly;
  } else {
    ++rc_.lost;
    rc_.lost_few_matches += r.status == TrackStatus::kTooFewMatches ? 1 : 0;
    rc_.lost_no_motion += r.status == TrackStatus::kMotionFailed ? 1 : 0;
    out_.quality = TrackingQuality::kLost;
    if (++lost_frames_ >= opt_.max_lost_frames) {
      restart();
      hold_ = true;
    }
    // Past the restart nothing measures the motion: the pose holds where the
    // last frames put it instead of running on at the last velocity (2 s of
    // a covered lens at 1 m/s would publish a pose 2 m away).
    if (hold_) T_WC = T_WC_last_;
  }
  // The motion model follows the output; a lost frame coasts on it.
  const double dt_s = t_last_ns_ < 0 ? 0.0 : 1e-9 * static_cast<double>(f.t_ns - t_last_ns_);
  Eigen::Vector3d v_W = Eigen::Vector3d::Zero();
  const Eigen::Isometry3d T_WB_out = T_WC * T_CB_;
  if (dt_s > 0) v_W = (T_WB_out.translation() - (T_WC_last_ * T_CB_).translation()) / dt_s;
  T_WC_prev_ = T_WC_last_;
  t_prev_ns_ = t_last_ns_;
  T_WC_last_ = T_WC;
  t_last_ns_ = f.t_ns;
  out_.state.t_ns = f.t_ns;
  out_.state.p_WB = T_WB_out.translation();
  out_.state.q_WB = Eigen::Quaterniond(T_WB_out.linear()).normalized();
  out_.state.v_WB = v_W;
  // No covariance: the window's is relative to a gauge without the drift of a
  // vision-only chain's roll and pitch; reporting it would understate the error.
  out_.pose_cov.valid = false;
  monitor_.on_frame(f.t_ns, r.tracked(), false);
  const DivergenceCause why = monitor_.check(out_.state, nullptr);
  if (why != DivergenceCause::kNone) {
    // A runaway motion model (or a non-finite pose): start over where the
    // last good pose was, at rest, and say so.
    restart();
    monitor_.on_reinitialised(f.t_ns, why);
    T_WC_prev_ = T_WC_last_;
    t_prev_ns_ = -1;
    out_.state.v_WB.setZero();
    if (!out_.state.p_WB.allFinite() || !out_.state.q_WB.coeffs().allFinite()) {
      out_.state.p_WB.setZero();
      out_.state.q_WB.setIdentity();
      T_WC_last_ = T_BC_;
    }
  }
  if (monitor_.lost()) out_.quality = TrackingQuality::kLost;
  counters_.divergence = monitor_.counts();
  return true;
}

std::string RgbdEstimator::backend_summary() const {
  std::ostringstream o;
  o << "rgbd: tracked " << rc_.tracked << " (motion model " << rc_.motion_model << "), keyframes "
    << rc_.keyframes << ", lost " << rc_.lost << " (few matches " << rc_.lost_few_matches << ", no motion "
    << rc_.lost_no_motion << "), restarts " << rc_.restarts << ", solves ok " << rc_.solves_ok
    << ", rejected " << rc_.solves_rejected << ", map poses " << rc_.map_poses << ", inlier rms "
    << (rc_.tracked > 0 ? rc_.refined_rms_px_sum / static_cast<double>(rc_.tracked) : 0.0)
    << " px, rigid fits/frame "
    << (rc_.tracked > 0 ? static_cast<double>(rc_.model_estimates) / static_cast<double>(rc_.tracked) : 0.0);
  return o.str();
}

}  // namespace kestrel::core

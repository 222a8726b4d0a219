#include "kestrel/core/ekf_estimator.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>
#include <stdexcept>

#include "kestrel/core/rig_transforms.hpp"
#include "kestrel/rt/clock.hpp"

namespace kestrel::core {
namespace {

double positive_or(double v, double fallback) { return v > 0.0 ? v : fallback; }

bool finite_state(const EkfSlam& f) {
  return f.pose().R.allFinite() && f.pose().p.allFinite() && f.v_WB().allFinite() &&
         f.gyro_bias().allFinite() && f.acc_bias().allFinite();
}

// A depth sensor with no error model: the structured-light default of msgs.hpp.
constexpr double kDefaultDepthCoeffPerM = 0.0025;
// Any value works (the disparity noise is set to match the depth noise); one
// that keeps the virtual right pixel near the image is easier to read in logs.
constexpr double kVirtualBaselineM = 0.1;

}  // namespace

std::string EkfEstimatorOptions::validate() const {
  std::ostringstream e;
  const std::string t = tracker.validate();
  if (!t.empty()) e << t;
  if (landmark_capacity < 4 || landmark_capacity > 512) e << "landmark_capacity: in [4, 512]\n";
  if (!(pixel_sigma_px > 0)) e << "pixel_sigma_px: must be > 0\n";
  if (!(imu_noise_inflation > 0)) e << "imu_noise_inflation: must be > 0\n";
  if (!(min_frame_interval_ms <= 1000))
    e << "min_frame_interval_ms: at most 1000 (0: every frame, below 0: the default)\n";
  if (max_missed_frames < 0) e << "max_missed_frames: must be >= 0\n";
  if (spread_grid_cols < 0 || spread_grid_cols > 32 || spread_grid_rows < 0 || spread_grid_rows > 32 ||
      (spread_grid_cols > 0) != (spread_grid_rows > 0))
    e << "spread_grid_cols/rows: both 0 (off) or both in [1, 32]\n";
  if (!(gate_chi2 > 0)) e << "gate_chi2: must be > 0\n";
  if (!(mono_gate_chi2 > 0)) e << "mono_gate_chi2: must be > 0\n";
  if (!(init_position_sigma_m > 0 && init_attitude_sigma_rad > 0 && init_velocity_sigma_mps > 0 &&
        init_gyro_bias_sigma_rps > 0 && init_acc_bias_sigma_mps2 > 0))
    e << "init_*_sigma: must be > 0\n";
  if (!(pred_sigma_min_px > 0 && pred_sigma_px_per_s >= 0)) e << "pred_sigma_*: min > 0, rate >= 0\n";
  if (!(map_pose_sigma_m > 0 && map_pose_sigma_rad > 0)) e << "map_pose_sigma_m/rad: must be > 0\n";
  if (!(map_pose_gate_chi2 > 0)) e << "map_pose_gate_chi2: must be > 0\n";
  if (!(map_pose_min_interval_s >= 0)) e << "map_pose_min_interval_s: must be >= 0\n";
  if (moving_start_after_ns < 0) e << "moving_start_after_ns: must be >= 0\n";
  if (!(restart_position_sigma_m > 0)) e << "restart_position_sigma_m: must be > 0\n";
  if (max_lost_frames < 1) e << "max_lost_frames: at least 1\n";
  return e.str();
}

EkfSlamOptions ekf_slam_options_for(const Rig& rig, const EkfEstimatorOptions& opt, ekf::StereoCamera* cam,
                                    double* baseline_m) {
  EkfSlamOptions o;
  o.motion = EkfMotionModel::kImu;
  o.landmark_capacity = opt.landmark_capacity;
  o.max_observations = std::max(1, opt.tracker.orb.n_features);
  o.pixel_sigma_px = opt.pixel_sigma_px;
  o.gate_chi2 = opt.gate_chi2;
  o.mono_gate_chi2 = opt.mono_gate_chi2;
  o.min_depth_m = positive_or(rig.depth.min_range_m, 0.1);
  o.max_init_depth_m = std::max(positive_or(rig.depth.max_range_m, 8.0), o.min_depth_m + 0.1);
  o.max_missed_frames = opt.max_missed_frames;
  o.spread_grid_cols = rig.rgb.width > 0 && rig.rgb.height > 0 ? opt.spread_grid_cols : 0;
  o.spread_grid_rows = o.spread_grid_cols > 0 ? opt.spread_grid_rows : 0;
  o.image_width_px = rig.rgb.width;
  o.image_height_px = rig.rgb.height;
  o.gyro_noise_density = positive_or(rig.imu.gyro_noise_density_rad_s_sqrthz, opt.default_gyro_noise_density);
  o.acc_noise_density = positive_or(rig.imu.acc_noise_density_mps2_sqrthz, opt.default_acc_noise_density);
  o.gyro_random_walk = positive_or(rig.imu.gyro_random_walk_rad_s2_sqrthz, opt.default_gyro_random_walk);
  o.acc_random_walk = positive_or(rig.imu.acc_random_walk_mps3_sqrthz, opt.default_acc_random_walk);
  o.gravity_mps2 = positive_or(rig.gravity_mps2, 9.81);
  // Depth noise sigma_z = k z^2 is a disparity noise fx b k, the same at every depth.
  const double k = positive_or(rig.depth.sigma_coeff_per_m, kDefaultDepthCoeffPerM);
  o.rgbd_disparity_sigma_px = rig.rgb.fx * kVirtualBaselineM * k;
  if (cam != nullptr) {
    cam->fsu = rig.rgb.fx;
    cam->fsv = rig.rgb.fy;
    cam->cu = rig.rgb.cx;
    cam->cv = rig.rgb.cy;
    cam->baseline_m = kVirtualBaselineM;
    const Eigen::Isometry3d T_CB = to_isometry(rig.T_BC).inverse();
    cam->T_CB = ekf::Pose(T_CB.linear(), T_CB.translation());
  }
  if (baseline_m != nullptr) *baseline_m = kVirtualBaselineM;
  return o;
}

namespace {
EkfSlam make_filter(const Rig& rig, const EkfEstimatorOptions& opt) {
  const std::string err = opt.validate();
  if (!err.empty()) throw std::invalid_argument("EkfEstimatorOptions:\n" + err);
  if (rig.rgb.fx <= 0 || rig.rgb.fy <= 0)
    throw std::invalid_argument("ekf estimator: the rig has no camera intrinsics (camera.fx_px, fy_px)");
  ekf::StereoCamera cam;
  const EkfSlamOptions o = ekf_slam_options_for(rig, opt, &cam, nullptr);
  return EkfSlam(o, cam);
}
}  // namespace

EkfEstimator::EkfEstimator(const Rig& rig, const EkfEstimatorOptions& opt)
    : opt_(opt),
      T_BC_(to_isometry(rig.T_BC)),
      fx_(rig.rgb.fx),
      init_(rig, opt.moving_start_after_ns),
      tracker_(rig, opt.tracker),
      ekf_(make_filter(rig, opt)),
      monitor_(opt.divergence) {
  ekf_slam_options_for(rig, opt_, nullptr, &baseline_m_);
  const ImuPropagatorOptions p = imu_propagator_options(rig);
  max_gap_ns_ = p.max_gap_ns;
  max_step_ns_ = p.max_integration_step_ns;
  obs_.resize(static_cast<size_t>(std::max(1, opt_.tracker.orb.n_features)));
  ekf_.set_imu_noise_scale(opt_.imu_noise_inflation);
  if (opt_.mapping && opt_.map.mapping) {
    MapCamera cam;
    cam.K = PinholeK{rig.rgb.fx, rig.rgb.fy, rig.rgb.cx, rig.rgb.cy};
    cam.width = rig.rgb.width;
    cam.height = rig.rgb.height;
    cam.depth_sigma_coeff_per_m = positive_or(rig.depth.sigma_coeff_per_m, kDefaultDepthCoeffPerM);
    cam.keypoint_sigma_px = opt_.tracker.keypoint_sigma_px;
    cam.level_scale = opt_.tracker.orb.scale_factor;
    map_ = std::make_unique<MapSystem>(cam, opt_.tracker.orb.n_features, opt_.map);
    map_->set_T_CB(T_BC_.inverse());
    if (!rig.stereo.present) map_->enable_depth_grid(rig.rgb, rig.depth);
  }
}

EkfEstimator::~EkfEstimator() = default;

// Before tracking: the newest refined points go into the tracker's local map
// (emptied first when the map's frame moved), and the output carries the
// map's frame.
void EkfEstimator::map_before_tracking() {
  if (const MapUpdate* u = map_->take_update()) {
    if (u->realigned) tracker_.clear_map();
    tracker_.apply_map_points(u->points, u->n);
    map_->release_update(u);
  }
  out_.map = map_->frame();
}

// After the update: a new keyframe goes to the map at once, at the filter's
// updated pose. The window holds its keyframe until its solve has refined it;
// the filter never revisits a past pose, so there is nothing to wait for.
void EkfEstimator::map_after_update(const TrackResult& r, const RgbdFrame& f) {
  // Once per loss: a restart while already lost is the same gap.
  const bool lost = out_.quality == TrackingQuality::kLost;
  if ((lost && !map_chain_lost_) || (!lost && starts_ != map_chain_starts_)) ++map_chain_;
  map_chain_lost_ = lost;
  map_chain_starts_ = starts_;
  if (!r.keyframe || !tracker_.has_keyframe()) return;
  KeyframePacket* p = map_->begin_keyframe();
  if (p == nullptr) return;  // every packet in flight: counted by the map
  p->t_ns = tracker_.keyframe_t_ns();
  p->T_WC = tracker_.keyframe_pose();
  p->n = tracker_.keyframe_features(p->features, opt_.tracker.orb.n_features);
  p->chain = map_chain_;
  if (tracker_.keyframe_t_ns() == f.t_ns) map_->fill_depth_grid(p, f.depth);
  map_->submit_keyframe(p);
}

// The update's consistency, for the summary: a filter whose noise models fit
// shows NIS / dof near 1 and a pose NIS near 6 (EkfUpdateStats).
void EkfEstimator::record_consistency(const EkfUpdateStats& st) {
  if (st.nis_dof > 0 && std::isfinite(st.nis)) {
    ekf_counters_.nis_sum += st.nis;
    ekf_counters_.nis_dof_sum += st.nis_dof;
  }
  if (st.pose_nis > 0 && std::isfinite(st.pose_nis)) {
    ekf_counters_.pose_nis_sum += st.pose_nis;
    ++ekf_counters_.pose_nis_n;
  }
}

void EkfEstimator::start(const NavState& s0, bool moving, bool restart) {
  const double att = moving ? opt_.moving_init_attitude_sigma_rad : opt_.init_attitude_sigma_rad;
  const double pos = restart ? std::max(opt_.init_position_sigma_m, opt_.restart_position_sigma_m)
                             : opt_.init_position_sigma_m;
  ekf::Mat6 P0 = ekf::Mat6::Zero();
  P0.diagonal().head<3>().setConstant(pos * pos);
  P0.diagonal().tail<3>().setConstant(att * att);
  ekf_.reset_imu(ekf::Pose(s0.q_WB.normalized().toRotationMatrix(), s0.p_WB), s0.v_WB, s0.bg_rps, s0.ba_mps2,
                 P0, moving ? opt_.moving_init_velocity_sigma_mps : opt_.init_velocity_sigma_mps,
                 opt_.init_gyro_bias_sigma_rps, opt_.init_acc_bias_sigma_mps2);
  t_state_ns_ = s0.t_ns;
  started_ = true;
  ++starts_;
  tracker_.reset();
  last_tracked_t_ns_ = -1;
  last_frame_t_ns_ = -1;
  last_frame_fixed_ = false;
  last_map_pose_t_ns_ = -1;
  reanchor_pending_ = restart;
  lost_frames_ = 0;
  ++counters_.resets;
  out_.reset_counter = static_cast<uint32_t>(counters_.resets);
}

void EkfEstimator::publish(int64_t t_ns) {
  NavState& s = out_.state;
  s.t_ns = t_ns;
  s.p_WB = ekf_.pose().p;
  s.q_WB = Eigen::Quaterniond(ekf_.pose().R).normalized();
  s.v_WB = ekf_.v_WB();
  s.bg_rps = ekf_.gyro_bias();
  s.ba_mps2 = ekf_.acc_bias();
  // The filter's error is [rho, theta] with T = T_hat exp([rho; theta]^): to
  // first order theta is the body-frame rotation error and R_hat rho the
  // position error in W (EstimatorOutput's order and frames).
  Eigen::Matrix<double, 6, 6> J = Eigen::Matrix<double, 6, 6>::Identity();
  J.topLeftCorner<3, 3>() = ekf_.pose().R;
  out_.pose_cov.cov.noalias() = J * ekf_.pose_covariance() * J.transpose();
  out_.pose_cov.cov = (0.5 * (out_.pose_cov.cov + out_.pose_cov.cov.transpose())).eval();
  out_.pose_cov.t_ns = t_ns;
  out_.pose_cov.valid = started_ && out_.pose_cov.cov.allFinite();
}

void EkfEstimator::propagate_to(int64_t t_ns) {
  const int64_t dt_ns = t_ns - t_state_ns_;
  if (dt_ns <= 0 || !have_last_) return;
  if (dt_ns > max_step_ns_) {
    // Integrating a long gap with one held sample invents motion; hold.
    t_state_ns_ = t_ns;
    return;
  }
  ekf_.propagate_imu(last_gyro_, last_acc_, 1e-9 * static_cast<double>(dt_ns));
  t_state_ns_ = t_ns;
}

bool EkfEstimator::add_imu(const ImuSample& s) {
  ++counters_.imu_in;
  if (!started_) {
    // The dead-reckoning backend's static initialiser gives the first state.
    if (!init_.add_imu(s)) {
      counters_.imu_rejects = init_.counters().imu_rejects;
      return false;
    }
    start(init_.output().state, init_.started_moving());
  }
  if (!imu_sample_usable(s)) {
    bool finite = true;
    for (int i = 0; i < 3; ++i)
      finite = finite && std::isfinite(s.gyro_rps[i]) && std::isfinite(s.acc_mps2[i]);
    if (!finite || (s.flags & kImuNonFinite)) {
      ++counters_.imu_rejects.non_finite;
    } else {
      ++counters_.imu_rejects.saturated;
    }
    return false;
  }
  if (last_imu_t_ns_ >= 0 && s.t_ns <= last_imu_t_ns_) {
    ++counters_.imu_rejects.out_of_order;
    return false;
  }
  const Eigen::Vector3d gyro(s.gyro_rps[0], s.gyro_rps[1], s.gyro_rps[2]);
  const Eigen::Vector3d acc(s.acc_mps2[0], s.acc_mps2[1], s.acc_mps2[2]);
  if (last_imu_t_ns_ >= 0 && s.t_ns - last_imu_t_ns_ > max_gap_ns_) ++counters_.imu_rejects.gaps;
  if (have_last_ && s.t_ns > t_state_ns_) {
    // The filter holds one input over the step; the mean of the two samples
    // around it is the midpoint rule (the step may start at a frame time).
    const int64_t dt_ns = s.t_ns - t_state_ns_;
    if (dt_ns <= max_step_ns_) {
      ekf_.propagate_imu(0.5 * (last_gyro_ + gyro), 0.5 * (last_acc_ + acc),
                         1e-9 * static_cast<double>(dt_ns));
    }
  }
  if (s.t_ns > t_state_ns_) t_state_ns_ = s.t_ns;
  last_gyro_ = gyro;
  last_acc_ = acc;
  have_last_ = true;
  last_imu_t_ns_ = s.t_ns;
  ++counters_.imu_used;
  if (!finite_state(ekf_)) {
    ++ekf_counters_.filter_resets;
    NavState s0 = out_.state;
    s0.t_ns = s.t_ns;
    start(s0, false, true);
  }
  publish(t_state_ns_);
  if (out_.quality == TrackingQuality::kUninitialized) out_.quality = TrackingQuality::kImuOnly;
  supervise();
  return true;
}

void EkfEstimator::set_quality(bool tracking) {
  if (monitor_.lost()) {
    out_.quality = TrackingQuality::kLost;
  } else {
    out_.quality = tracking ? TrackingQuality::kTracking : TrackingQuality::kImuOnly;
  }
}

// After a divergence the filter restarts from its attitude and position with
// the velocity unknown and any implausible bias forgotten, and says kLost
// until an update uses observations again (docs/safety.md).
void EkfEstimator::supervise() {
  const DivergenceCause why = monitor_.check(out_.state, &out_.pose_cov);
  if (why == DivergenceCause::kNone) {
    // A coast timeout only flags the output; the filter runs on.
    if (monitor_.lost()) out_.quality = TrackingQuality::kLost;
    return;
  }
  NavState s0 = out_.state;
  const bool finite =
      s0.p_WB.allFinite() && s0.q_WB.coeffs().allFinite() && s0.bg_rps.allFinite() && s0.ba_mps2.allFinite();
  if (!finite && have_fix_state_) {
    const int64_t t = s0.t_ns;
    s0 = last_fix_state_;
    s0.t_ns = t;
  } else if (!finite) {
    s0.p_WB.setZero();
    s0.q_WB.setIdentity();
  }
  s0.v_WB.setZero();
  const DivergenceOptions& d = opt_.divergence;
  if (!finite || why == DivergenceCause::kAccBias || !(s0.ba_mps2.norm() <= d.max_acc_bias_mps2))
    s0.ba_mps2.setZero();
  if (!finite || why == DivergenceCause::kGyroBias || !(s0.bg_rps.norm() <= d.max_gyro_bias_rps))
    s0.bg_rps.setZero();
  start(s0, true, true);
  publish(s0.t_ns);
  monitor_.on_reinitialised(s0.t_ns, why);
  out_.quality = TrackingQuality::kLost;
}

bool EkfEstimator::add_frame(const RgbdFrame& f) {
  ++counters_.frames_in;
  if (!started_) return false;
  // Only after a fix: a frame that did not track is followed by every frame
  // until one does, so a loss (a fast yaw, a blurred pass) lasts as long as
  // at the camera's full rate instead of twice as long. An out-of-order stamp
  // is not skipped here: the tracker and the filter have their own handling.
  const int64_t min_interval_ns = static_cast<int64_t>(opt_.frame_interval_ms() * 1e6);
  if (last_frame_fixed_ && f.t_ns > last_frame_t_ns_ && f.t_ns - last_frame_t_ns_ < min_interval_ns) {
    ++ekf_counters_.frames_skipped;
    return false;
  }
  last_frame_t_ns_ = f.t_ns;
  if (map_) map_before_tracking();
  // The mean is at the last IMU sample, up to one IMU period before the
  // frame: carry it to the frame time with that sample, so the update and
  // the tracker's prediction refer to the exposure.
  propagate_to(f.t_ns);
  const ekf::Pose& T = ekf_.pose();
  Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();
  T_WB.linear() = T.R;
  T_WB.translation() = T.p;
  const double since_s = last_tracked_t_ns_ < 0
                             ? 1.0
                             : 1e-9 * static_cast<double>(std::max<int64_t>(0, f.t_ns - last_tracked_t_ns_));
  const double sigma_px = std::max(opt_.pred_sigma_min_px, opt_.pred_sigma_px_per_s * since_s);
  const TrackResult& r = tracker_.track(f.t_ns, f.rgb, f.depth, f.right, T_WB * T_BC_, sigma_px);

  const int n_in = tracker_.num_observations();
  const WindowObservation* in = tracker_.observations();
  int n = 0;
  for (int i = 0; i < n_in; ++i) {
    const WindowObservation& o = in[i];
    const bool has_depth = o.depth_m > 0.0;
    if (!has_depth) {
      ++ekf_counters_.observations_no_depth;
      if (!opt_.depthless_observations) continue;
    }
    if (n >= static_cast<int>(obs_.size())) {
      ++ekf_counters_.observations_dropped;
      continue;
    }
    StereoObservation& so = obs_[static_cast<size_t>(n++)];
    so = has_depth ? virtual_stereo(o.landmark_id, o.uv.x(), o.uv.y(), o.depth_m, fx_, baseline_m_)
                   : pixel_only(o.landmark_id, o.uv.x(), o.uv.y());
    if (opt_.map_point_landmarks && o.map_sigma_m > 0.0f) {
      so.prior_p_W = o.map_p_W;
      so.prior_sigma_m = o.map_sigma_m;
    }
  }
  ekf_counters_.observations_in += static_cast<uint64_t>(n_in);

  int used = 0;
  // The frame's filter time: the visual update and the map pose's, together.
  const int64_t t0 = rt::now_ns();
  bool updated = false;
  if (n > 0) {
    // Also freezes the landmarks the tracker no longer sees (none of their
    // ids in this frame's list) after max_missed_frames.
    const EkfUpdateStats st = ekf_.update(obs_.data(), n);
    updated = true;
    used = st.used;
    ++ekf_counters_.frames_updated;
    record_consistency(st);
  } else if (r.status != TrackStatus::kNoImage && r.status != TrackStatus::kFeatureError) {
    // An empty update still counts the miss of every active landmark.
    ekf_.update(nullptr, 0);
  }
  const bool map_pose_due =
      last_map_pose_t_ns_ < 0 ||
      1e-9 * static_cast<double>(f.t_ns - last_map_pose_t_ns_) >= opt_.map_pose_min_interval_s;
  if (opt_.use_map_pose && r.keyframe && r.map_pose_valid && map_pose_due) {
    const Eigen::Isometry3d T_WB_map = r.T_WC_map * T_BC_.inverse();
    const double sp = std::max(opt_.map_pose_sigma_m, r.map_sigma_p_m);
    const double sr = std::max(opt_.map_pose_sigma_rad, r.map_sigma_rad);
    ekf::Mat6 R = ekf::Mat6::Zero();
    R.diagonal() << sp * sp, sp * sp, sp * sp, sr * sr, sr * sr, sr * sr;
    updated = true;
    if (ekf_.update_pose(ekf::Pose(T_WB_map.linear(), T_WB_map.translation()), R, opt_.map_pose_gate_chi2)) {
      ++ekf_counters_.map_poses_used;
      last_map_pose_t_ns_ = f.t_ns;
      if (reanchor_pending_) {
        // The first map pose after a restart moves the coasted position
        // back onto the map by up to restart_position_sigma_m's worth: a
        // step in the output, announced as PX4 announces its resets.
        reanchor_pending_ = false;
        ++ekf_counters_.map_reanchors;
        ++counters_.resets;
        out_.reset_counter = static_cast<uint32_t>(counters_.resets);
      }
    } else {
      ++ekf_counters_.map_poses_gated;
    }
  }
  if (updated) update_latency_.record(rt::now_ns() - t0);
  // The estimator keeps no map: frozen landmarks are dropped here.
  ekf_.clear_frozen();
  if (!finite_state(ekf_)) {
    ++ekf_counters_.filter_resets;
    NavState s0 = out_.state;
    s0.t_ns = f.t_ns;
    start(s0, false, true);
    return false;
  }
  if (r.keyframe && tracker_.has_keyframe()) {
    // The keyframe was made at the tracker's own pose for it (chained from
    // the previous keyframe, or the filter's prediction after a reset); its
    // points enter the local map, and are tracked against, at the filter's
    // updated pose instead. After the finite check: never a NaN into the map.
    Eigen::Isometry3d T_WB_post = Eigen::Isometry3d::Identity();
    T_WB_post.linear() = ekf_.pose().R;
    T_WB_post.translation() = ekf_.pose().p;
    tracker_.set_keyframe_pose(tracker_.keyframe_t_ns(), T_WB_post * T_BC_);
  }
  publish(f.t_ns);

  const bool tracked = r.tracked() && used >= opt_.min_used_for_tracking;
  last_frame_fixed_ = tracked;
  // The tracker found a motion the filter would not take: IMU and vision disagree.
  monitor_.on_frame(f.t_ns, tracked, r.tracked() && !tracked);
  if (tracked) {
    last_fix_state_ = out_.state;
    have_fix_state_ = true;
  }
  if (tracked || r.status == TrackStatus::kNewKeyframe) {
    // A keyframe alone is not a fix: it claims tracking only when the last frame did.
    set_quality(tracked || out_.quality == TrackingQuality::kTracking);
    last_tracked_t_ns_ = f.t_ns;
    lost_frames_ = 0;
    ++counters_.frames_used;
    supervise();
    if (map_) map_after_update(r, f);
    return true;
  }
  // Not tracked: coast on the IMU; after a few frames take a new keyframe at
  // the filter's pose rather than matching an ever staler one.
  ++lost_frames_;
  set_quality(false);
  supervise();
  if (lost_frames_ >= opt_.max_lost_frames && tracker_.has_keyframe()) {
    tracker_.reset();
    ++ekf_counters_.tracker_resets;
    lost_frames_ = 0;
  }
  if (map_) map_after_update(r, f);
  return true;
}

std::string EkfEstimator::backend_summary() const {
  const EkfCounters& c = ekf_.counters();
  const EkfEstimatorCounters& e = ekf_counters_;
  char buf[1200];
  auto ms = [this](double p) {
    return update_latency_.count() > 0 ? 1e-6 * static_cast<double>(update_latency_.percentile(p)) : 0.0;
  };
  std::snprintf(
      buf, sizeof buf,
      "ekf: %d of %d landmarks active; initialised %llu (%llu at map points), frozen %llu, dropped %llu, "
      "capacity full %llu; "
      "observations %llu in (%llu without depth), %llu used (%llu without depth), %llu gated; tracker resets "
      "%llu, filter "
      "resets %llu; frames skipped %llu (closer than %.0f ms); map poses %llu used, %llu gated, %llu "
      "re-anchoring a restart; update p50 %.2f ms, p99 "
      "%.2f ms, max %.2f ms; IMU noise x%.1f; NIS / dof %.2f, pose NIS %.1f (consistent: 1 and 6)",
      ekf_.num_active(), ekf_.options().landmark_capacity, (unsigned long long)c.landmarks_initialised,
      (unsigned long long)c.landmarks_from_prior, (unsigned long long)c.landmarks_frozen,
      (unsigned long long)c.landmarks_dropped, (unsigned long long)c.capacity_full,
      (unsigned long long)e.observations_in, (unsigned long long)e.observations_no_depth,
      (unsigned long long)c.observations_used, (unsigned long long)c.observations_used_without_depth,
      (unsigned long long)c.observations_gated, (unsigned long long)e.tracker_resets,
      (unsigned long long)e.filter_resets, (unsigned long long)e.frames_skipped, opt_.frame_interval_ms(),
      (unsigned long long)e.map_poses_used, (unsigned long long)e.map_poses_gated,
      (unsigned long long)e.map_reanchors, ms(50), ms(99),
      update_latency_.count() > 0 ? 1e-6 * static_cast<double>(update_latency_.max()) : 0.0,
      ekf_.imu_noise_scale(), e.nis_dof_sum > 0 ? e.nis_sum / e.nis_dof_sum : 0.0,
      e.pose_nis_n > 0 ? e.pose_nis_sum / static_cast<double>(e.pose_nis_n) : 0.0);
  if (map_) return std::string(buf) + "\n" + map_->summary();
  return buf;
}

}  // namespace kestrel::core

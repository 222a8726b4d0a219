#include "kestrel/core/window_estimator.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "kestrel/core/rig_transforms.hpp"
#include "kestrel/rt/clock.hpp"

namespace kestrel::core {
namespace {

bool finite(const NavState& x) {
  return x.p_WB.allFinite() && x.v_WB.allFinite() && x.q_WB.coeffs().allFinite() && x.bg_rps.allFinite() &&
         x.ba_mps2.allFinite();
}

}  // namespace

std::string WindowEstimatorOptions::validate() const {
  std::ostringstream e;
  e << window.validate() << frontend.tracker.validate() << map.validate();
  if (!(imu_noise_inflation > 0)) e << "imu_noise_inflation: must be > 0\n";
  if (min_observations < 3) e << "min_observations: at least 3\n";
  if (!(max_correction_m > 0)) e << "max_correction_m: must be > 0\n";
  if (!(max_speed_mps > 0)) e << "max_speed_mps: must be > 0\n";
  if (max_consecutive_failures < 1) e << "max_consecutive_failures: at least 1\n";
  if (max_imu_gap_ns <= 0) e << "max_imu_gap_ns: must be > 0\n";
  if (time_offset_min_matches < 6) e << "time_offset_min_matches: at least 6\n";
  const std::string to = time_offset.validate();
  if (!to.empty()) e << "time_offset: " << to << "\n";
  return e.str();
}

WindowEstimator::WindowEstimator(const Rig& rig, const WindowEstimatorOptions& opt)
    : opt_([&] {
        WindowEstimatorOptions o = opt;
        o.window.imu = ImuNoiseParams::from_rig(rig).scaled(o.imu_noise_inflation);
        // One accelerometer bias model for prediction and for the bias factor:
        // the rig's tau describes the sensor, the window's model is a choice.
        // (predict() used to decay the bias with the rig's tau while the factor
        // held it as a random walk: two models in one estimator.)
        o.window.imu.acc_bias_tau_s =
            o.window.acc_bias_model == WindowOptions::AccBiasModel::kBoundedRandomWalk
                ? o.window.acc_bias_tau_s
                : 0.0;
        o.window.depth_sigma_coeff_per_m = rig.depth.sigma_coeff_per_m;
        return o;
      }()),
      T_BC_(to_isometry(rig.T_BC)),
      pim_params_([&] {
        PreintegrationParams p = PreintegrationParams::from_rig(rig);
        p.noise = opt_.window.imu;
        return p;
      }()),
      front_(rig, opt.frontend),
      pim_(pim_params_),
      still_([&] {
        StaticInitOptions o;
        o.gravity_mps2 = rig.gravity_mps2;
        o.window_ns = 300'000'000;
        return o;
      }()) {
  const std::string err = opt_.validate();
  if (!err.empty()) throw std::invalid_argument("WindowEstimatorOptions:\n" + err);
  window_ = std::make_unique<WindowOptimizer>(WindowOptimizer::pinhole_of(rig), T_BC_, opt_.window);
  max_obs_ = opt.window.max_obs_per_frame;
  jobs_.reset(new Job[kPool]);
  for (int i = 0; i < kPool; ++i) jobs_[i].pim = Preintegrated(pim_params_);
  obs_pool_.reset(new WindowObservation[static_cast<size_t>(kPool) * max_obs_]);
  vel_pool_.reset(new Eigen::Vector2d[static_cast<size_t>(kPool) * max_obs_]);
  dvel_pool_.reset(new double[static_cast<size_t>(kPool) * max_obs_]);
  prev_cap_ = std::max(opt.frontend.tracker.orb.n_features, max_obs_);
  prev_obs_.reset(new PrevObs[static_cast<size_t>(prev_cap_)]);
  K_ = WindowOptimizer::pinhole_of(rig);
  if (opt_.window.estimate_time_offset) {
    calib_ = std::make_unique<TimeOffsetCalibrator>(opt_.time_offset, T_BC_.linear());
    corr_.reset(new Correspondence2D3D[static_cast<size_t>(prev_cap_)]);
    kf_obs_.reset(new PrevObs[static_cast<size_t>(prev_cap_)]);
  }
  for (int i = kPool - 1; i >= 0; --i) free_slots_[n_free_++] = i;
  for (auto& c : chain_) c = Preintegrated(pim_params_);
  set_threaded_optimizer(false);
  if (opt_.map.mapping) {
    MapCamera cam;
    cam.K = WindowOptimizer::pinhole_of(rig);
    cam.width = rig.rgb.width;
    cam.height = rig.rgb.height;
    cam.depth_sigma_coeff_per_m = rig.depth.sigma_coeff_per_m;
    cam.keypoint_sigma_px = opt_.frontend.tracker.keypoint_sigma_px;
    cam.level_scale = opt_.frontend.tracker.orb.scale_factor;
    map_ = std::make_unique<MapSystem>(cam, opt_.frontend.tracker.orb.n_features, opt_.map);
    map_->set_T_CB(T_BC_.inverse());
    if (!rig.stereo.present) map_->enable_depth_grid(rig.rgb, rig.depth);
  }
}

WindowEstimator::~WindowEstimator() = default;

void WindowEstimator::set_threaded_optimizer(bool on) {
  threaded_ = on;
  window_->problem().opt.time_budget_ms = on ? opt_.window.time_budget_ms : 1e9;
}

std::string WindowEstimator::backend_summary() const {
  std::ostringstream o;
  o << "window: jobs " << wc_.jobs << ", solves ok " << solves_ok_.load(std::memory_order_relaxed)
    << ", applied " << wc_.applied << ", failures " << wc_.failures << ", window resets " << wc_.window_resets
    << ", skipped (busy " << wc_.skipped_busy << ", few obs " << wc_.skipped_few_obs << ", no imu "
    << wc_.skipped_no_imu << "), stale " << wc_.stale_results << ", imu gaps " << wc_.imu_gaps
    << ", still frames " << wc_.stationary_frames << ", map poses " << wc_.map_poses
    << ", vision-only frames " << wc_.vision_only_frames;
  const WindowOptimizer::Counters& oc = window_->counters();
  o << "; landmarks from depth " << oc.landmarks_from_depth << ", triangulated " << oc.landmarks_triangulated
    << ", observations skipped (budget " << oc.obs_skipped_budget << ", invalid " << oc.obs_skipped_invalid
    << "), far tracks " << wc_.far_observations;
  if (calib_) {
    const TimeOffsetEstimate e = calib_->estimate();
    o << ", time offset " << 1e3 * td_s_ << " ms (rotation correlation: ";
    if (e.sigma_s > 0.0) {
      o << 1e3 * e.td_s << " +- " << 1e3 * e.sigma_s << " ms, residual " << 1e3 * e.residual_rad << " mrad"
        << (e.valid ? "" : " (too loose, unused)");
    } else {
      o << "none";
    }
    o << ", " << calib_->used_intervals() << " intervals, " << calib_->gated_intervals() << " gated)";
  }
  if (map_) o << "\n" << map_->summary();
  return o.str();
}

bool WindowEstimator::estimated_time_offset_s(double* td_s) const {
  if (!opt_.window.estimate_time_offset) return false;
  if (td_s) *td_s = td_s_;
  return true;
}

// Backward differences over the previous tracked frame (VINS-Mono's feature
// velocity): the velocity half a frame earlier, good enough to move a pixel
// by the few milliseconds of an offset. None across a gap or a lost track.
void WindowEstimator::image_velocities(int64_t t_ns, const WindowObservation* obs, int n,
                                       Eigen::Vector2d* vel) {
  const double dt_s = 1e-9 * static_cast<double>(t_ns - prev_t_ns_);
  const bool usable = prev_t_ns_ >= 0 && dt_s > 0.0 && dt_s <= 0.1;
  for (int k = 0; k < n; ++k) {
    vel[k].setZero();
    if (!usable) continue;
    const PrevObs* begin = prev_obs_.get();
    const PrevObs* end = begin + n_prev_;
    const PrevObs* p = std::lower_bound(begin, end, obs[k].landmark_id,
                                        [](const PrevObs& a, uint32_t id) { return a.id < id; });
    if (p != end && p->id == obs[k].landmark_id) vel[k] = (obs[k].uv - p->uv) / dt_s;
  }
}

// ---- tracking side -------------------------------------------------------------

// The front end re-initialised after a divergence: the window restarts with
// it at the next frame, and nothing queued before is applied.
void WindowEstimator::follow_front_end_restart() {
  if (front_.divergence_epoch() == epoch_) return;
  epoch_ = front_.divergence_epoch();
  first_seq_of_epoch_ = next_seq_;
  pim_active_ = false;
  consecutive_failures_ = 0;
  ++wc_.window_resets;
  if (pending_slot_ >= 0) {
    free_slots_[n_free_++] = pending_slot_;
    pending_slot_ = -1;
  }
}

// Before tracking: the newest refined points go into the tracker's local map,
// and the held keyframe takes the pose the window has refined meanwhile.
void WindowEstimator::map_before_tracking() {
  Tracker& tracker = front_.tracker();
  if (const MapUpdate* u = map_->take_update()) {
    if (u->realigned) tracker.clear_map();
    tracker.apply_map_points(u->points, u->n);
    map_->release_update(u);
  }
  front_.set_map_frame(map_->frame());
  if (map_pending_ != nullptr && tracker.has_keyframe() && tracker.keyframe_t_ns() == map_pending_->t_ns)
    map_pending_->T_WC = at_capture_time(tracker.keyframe_pose());
}

// The window's poses are at the frames' stamps t; a keyframe's pixels and
// depths were taken at t + t_d. The map places the keyframe's points with the
// pose it is given, so it gets the pose at t + t_d (first order, the motion
// when the keyframe was taken); without it every map point sits v t_d + w t_d
// x p off, and the map's priors pull the window's t_d back.
Eigen::Isometry3d WindowEstimator::at_capture_time(const Eigen::Isometry3d& T_WC) const {
  if (!calib_ || td_s_ == 0.0) return T_WC;
  Eigen::Isometry3d T_WB = T_WC * T_BC_.inverse();
  const double a = map_pending_w_B_.norm() * td_s_;
  if (map_pending_w_B_.norm() > 0.0)
    T_WB.linear() = T_WB.linear() * Eigen::AngleAxisd(a, map_pending_w_B_.normalized()).toRotationMatrix();
  T_WB.translation() += map_pending_v_W_ * td_s_;
  return T_WB * T_BC_;
}

// After tracking: a new keyframe sends the held one to the map (the window
// has refined it for a keyframe's span) and is held in its place.
void WindowEstimator::map_after_tracking(const RgbdFrame& f) {
  // Once per loss: a re-initialisation while already lost is the same gap.
  const bool lost = front_.output().quality == TrackingQuality::kLost;
  if ((lost && !map_chain_lost_) || (!lost && front_.divergence_epoch() != map_chain_epoch_)) ++map_chain_;
  map_chain_lost_ = lost;
  map_chain_epoch_ = front_.divergence_epoch();
  const TrackResult& r = front_.last_track();
  if (!r.keyframe) return;
  if (map_pending_ != nullptr) map_->submit_keyframe(map_pending_);
  map_pending_ = map_->begin_keyframe();
  if (map_pending_ == nullptr) return;
  Tracker& tracker = front_.tracker();
  map_pending_->t_ns = tracker.keyframe_t_ns();
  map_pending_v_W_ = front_.propagated().v_WB;
  map_pending_w_B_ = last_gyro_rps_ - front_.propagated().bg_rps;
  map_pending_->T_WC = at_capture_time(tracker.keyframe_pose());
  map_pending_->n = tracker.keyframe_features(map_pending_->features, opt_.frontend.tracker.orb.n_features);
  map_pending_->chain = map_chain_;
  if (tracker.keyframe_t_ns() == f.t_ns) map_->fill_depth_grid(map_pending_, f.depth);
}

bool WindowEstimator::add_frame(const RgbdFrame& f) {
  if (map_) map_before_tracking();
  bool changed = front_.add_frame(f);
  follow_front_end_restart();
  if (!front_.started()) return changed;
  if (map_) map_after_tracking(f);
  const TrackResult& r = front_.last_track();
  wc_.far_observations += static_cast<uint64_t>(r.far_tracked);
  if (!(r.tracked() || r.status == TrackStatus::kNewKeyframe)) return changed;
  if (calib_) measure_camera_rotation(f.t_ns, r);
  queue_job(f, r);
  if (opt_.window.estimate_time_offset) remember_observations(f.t_ns);
  return changed;
}

namespace {
// Observations by landmark id, sorted, into a fixed array.
int copy_sorted(const WindowObservation* obs, int n, WindowEstimator::PrevObsView out, int cap) {
  n = std::min(n, cap);
  for (int k = 0; k < n; ++k) out[k] = {obs[k].landmark_id, obs[k].uv, obs[k].depth_m};
  std::sort(out, out + n, [](const auto& a, const auto& b) { return a.id < b.id; });
  return n;
}
}  // namespace

// This frame's observations by id, for the next frame's image velocities.
void WindowEstimator::remember_observations(int64_t t_ns) {
  const Tracker& tracker = front_.tracker();
  n_prev_ = copy_sorted(tracker.observations(), tracker.num_observations(), prev_obs_.get(), prev_cap_);
  prev_t_ns_ = t_ns;
}

// The tracker's own pose takes its rotation from the gyro (LONSC with the IMU
// rotation), so it cannot show the offset between the two; a plain 6-DoF PnP
// of this frame's pixels on the keyframe's depth can. Against the keyframe
// rather than the previous frame: the angular velocity differs more between
// the ends of a longer interval while the PnP's noise stays the same
// (tests/imu/test_time_offset_calibrator.cpp). The PnP starts from the
// tracker's relative pose, which only speeds it up.
void WindowEstimator::measure_camera_rotation(int64_t t_ns, const TrackResult& r) {
  const Tracker& tracker = front_.tracker();
  if (r.keyframe) {
    n_kf_obs_ = copy_sorted(tracker.observations(), tracker.num_observations(), kf_obs_.get(), prev_cap_);
    kf_t_ns_ = t_ns;
    kf_T_WC_ = r.T_WC;
    return;
  }
  if (kf_t_ns_ < 0 || t_ns <= kf_t_ns_) return;
  const int n = std::min(tracker.num_observations(), prev_cap_);
  const PrevObs* begin = kf_obs_.get();
  const PrevObs* end = begin + n_kf_obs_;
  int m = 0;
  for (int k = 0; k < n; ++k) {
    const WindowObservation& o = tracker.observations()[k];
    const PrevObs* p =
        std::lower_bound(begin, end, o.landmark_id, [](const PrevObs& a, uint32_t id) { return a.id < id; });
    if (p == end || p->id != o.landmark_id || !(p->depth_m > 0.0)) continue;
    Correspondence2D3D& c = corr_[m++];
    c.p_prev = Eigen::Vector3d((p->uv.x() - K_.cx) / K_.fx, (p->uv.y() - K_.cy) / K_.fy, 1.0) * p->depth_m;
    c.u_cur = o.uv;
    c.sigma_px = 1.0f;
    c.id = o.landmark_id;
  }
  if (m < opt_.time_offset_min_matches) return;
  const Eigen::Isometry3d T_cur_kf = r.T_WC.inverse() * kf_T_WC_;
  Eigen::Matrix3d R = T_cur_kf.linear();
  Eigen::Vector3d t = T_cur_kf.translation();
  PoseRefineOptions ro;
  ro.max_iterations = 6;
  const PoseRefineResult res =
      refine_pose_gauss_newton(&R, &t, K_, corr_.get(), static_cast<std::size_t>(m), nullptr, 0, ro);
  if (!res.ok || !R.allFinite()) return;
  // R maps the keyframe's camera into the current one: R_CcCk; the calibrator wants R_CkCc.
  calib_->add_camera_rotation(kf_t_ns_, t_ns, R.transpose());
}

// Where the time offset moves a depth-backed observation: d p_C / dt for a
// static point seen by a moving camera (p_B = R_WB^T (l - p_WB) changes by
// -w x p_B - R_WB^T v_WB), projected: the pixel's and the depth's rates. From
// the motion rather than from the previous frame's pixel, so a landmark seen
// for the first time (every new point of a keyframe) moves too. Observations
// without depth keep the backward difference of image_velocities.
void WindowEstimator::depth_velocities(const NavState& x, const WindowObservation* obs, int n,
                                       Eigen::Vector2d* vel, double* dvel) const {
  const Eigen::Matrix3d R_BC = T_BC_.linear();
  const Eigen::Vector3d v_B = x.q_WB.conjugate() * x.v_WB;
  const Eigen::Vector3d w_B = last_gyro_rps_ - x.bg_rps;
  for (int k = 0; k < n; ++k) {
    dvel[k] = 0.0;
    if (!(obs[k].depth_m > 0.0)) continue;
    const Eigen::Vector3d p_C =
        Eigen::Vector3d((obs[k].uv.x() - K_.cx) / K_.fx, (obs[k].uv.y() - K_.cy) / K_.fy, 1.0) *
        obs[k].depth_m;
    const Eigen::Vector3d p_B = R_BC * p_C + T_BC_.translation();
    const Eigen::Vector3d pdot_C = R_BC.transpose() * (-w_B.cross(p_B) - v_B);
    dvel[k] = pdot_C.z();
    const double iz = 1.0 / p_C.z();
    vel[k] = Eigen::Vector2d(K_.fx * (pdot_C.x() * p_C.z() - p_C.x() * pdot_C.z()) * iz * iz,
                             K_.fy * (pdot_C.y() * p_C.z() - p_C.y() * pdot_C.z()) * iz * iz);
  }
}

// A tracked frame becomes a job for the optimizer (unless it is left out).
void WindowEstimator::queue_job(const RgbdFrame& f, const TrackResult& r) {
  Tracker& tracker = front_.tracker();
  const int n = tracker.num_observations();
  if (n < opt_.min_observations) {
    ++wc_.skipped_few_obs;
    return;
  }
  if (pending_slot_ >= 0) {
    // The previous frame never saw the IMU sample after it: leave it out.
    free_slots_[n_free_++] = pending_slot_;
    pending_slot_ = -1;
    ++wc_.skipped_no_imu;
  }
  if (opt_.keyframes_only && !r.keyframe && pim_active_) return;
  if (!have_last_sample_) return;
  if (front_.vision_only() && !opt_.continue_without_imu) return;
  // Reclaim the slots the optimizer is done with.
  while (const uint8_t* s = done_.front()) {
    free_slots_[n_free_++] = *s;
    done_.pop();
  }
  if (n_free_ == 0) {
    ++wc_.skipped_busy;
    return;
  }
  const int slot = free_slots_[--n_free_];
  Job& job = jobs_[slot];
  job.t_ns = f.t_ns;
  job.keyframe = r.keyframe;
  job.tracker_kf_t_ns = tracker.has_keyframe() ? tracker.keyframe_t_ns() : -1;
  job.guess = front_.propagated();
  job.n_obs = std::min(n, max_obs_);
  std::copy(tracker.observations(), tracker.observations() + job.n_obs, obs_of(slot));
  if (opt_.window.estimate_time_offset) {
    image_velocities(f.t_ns, obs_of(slot), job.n_obs, vel_of(slot));
    depth_velocities(job.guess, obs_of(slot), job.n_obs, vel_of(slot), dvel_of(slot));
    const TimeOffsetEstimate e = calib_->estimate();
    job.td_meas_s = e.valid ? e.td_s : 0.0;
    job.td_meas_sigma_s = e.valid ? e.sigma_s : 0.0;
  }
  job.stationary = opt_.zero_velocity_when_still && still_t_ns_ >= 0 && f.t_ns - still_t_ns_ <= 150'000'000 &&
                   front_.propagated().v_WB.norm() < opt_.still_max_speed_mps;
  wc_.stationary_frames += job.stationary ? 1 : 0;
  job.has_map_pose = opt_.use_map_pose && r.keyframe && r.map_pose_valid;
  if (job.has_map_pose) {
    job.T_WB_map = r.T_WC_map * T_BC_.inverse();
    if (job.td_meas_sigma_s > 0.0) {
      // The PnP saw the camera at t + t_d: moved back to the state's time.
      const double td = job.td_meas_s;
      const Eigen::Vector3d w_B = last_gyro_rps_ - job.guess.bg_rps;
      job.T_WB_map.translation() -= job.guess.v_WB * td;
      if (w_B.norm() > 0.0) {
        job.T_WB_map.linear() =
            job.T_WB_map.linear() * Eigen::AngleAxisd(-td * w_B.norm(), w_B.normalized()).toRotationMatrix();
      }
    }
    job.map_sigma_p_m = std::max(opt_.map_pose_sigma_m, r.map_sigma_p_m);
    job.map_sigma_rad = std::max(opt_.map_pose_sigma_rad, r.map_sigma_rad);
    ++wc_.map_poses;
  }
  job.reset = !window_started_ || reset_requested_ || (!pim_active_ && !opt_.continue_without_imu);
  reset_requested_ = false;
  // Without the IMU chain (silent IMU, or the first frame after it returned)
  // the frame enters without an IMU factor and the chain restarts here.
  job.vision_only = !job.reset && (!pim_active_ || front_.vision_only());
  wc_.vision_only_frames += job.vision_only ? 1 : 0;
  pending_slot_ = slot;
  if (job.reset || job.vision_only) {
    // The window (re)starts here, or the chain does: nothing to preintegrate from.
    job.has_pim = false;
    window_started_ = true;
    submit_pending();
    if (front_.vision_only()) {
      pim_active_ = false;  // the next frame too, until samples return
      // No IMU sample will come to apply the result: the front end's state
      // is at this frame, where the result is.
      poll_results();
    }
  }
  // Results are applied in add_imu, where the propagated state and the
  // preintegration since the last window frame end at the same sample.
}

bool WindowEstimator::add_imu(const ImuSample& s) {
  bool changed = front_.add_imu(s);
  follow_front_end_restart();
  if (!imu_sample_usable(s) || (have_last_sample_ && s.t_ns <= last_sample_.t_ns)) {
    poll_results();
    return changed;
  }
  last_gyro_rps_ = Eigen::Vector3d(s.gyro_rps[0], s.gyro_rps[1], s.gyro_rps[2]);
  // The raw rate: the calibrator fits a constant bias itself, which keeps it
  // independent of the window's bias estimate (itself disturbed by a wrong t_d).
  if (calib_) calib_->add_gyro(s.t_ns, last_gyro_rps_);
  NavState still_state;
  if (still_.add(s, still_state)) still_t_ns_ = s.t_ns;
  if (have_last_sample_ && s.t_ns - last_sample_.t_ns > opt_.max_imu_gap_ns &&
      (pim_active_ || window_started_)) {
    // Preintegrating across the gap would invent motion. With
    // continue_without_imu the frames of the gap went in vision-only and the
    // chain restarts at the next frame; without it the window restarts
    // there, from the front end's (IMU-coasted) state.
    ++wc_.imu_gaps;
    if (!opt_.continue_without_imu) {
      ++wc_.window_resets;
      front_.count_reset();
    }
    pim_active_ = false;
    if (pending_slot_ >= 0) {
      free_slots_[n_free_++] = pending_slot_;
      pending_slot_ = -1;
    }
  }
  if (pim_active_ && have_last_sample_) {
    int64_t t0 = std::max(last_sample_.t_ns, t_last_frame_ns_);
    if (pending_slot_ >= 0 && s.t_ns >= jobs_[pending_slot_].t_ns) {
      const int64_t t_f = jobs_[pending_slot_].t_ns;
      if (t_f > t0) pim_.integrate_segment(last_sample_, s, t0, t_f);
      jobs_[pending_slot_].has_pim = true;
      submit_pending();
      t0 = t_f;
    }
    if (s.t_ns > t0) pim_.integrate_segment(last_sample_, s, t0, s.t_ns);
  }
  last_sample_ = s;
  have_last_sample_ = true;
  poll_results();
  return changed;
}

// Sends the pending job and starts the next preintegration at its time.
void WindowEstimator::submit_pending() {
  const int slot = pending_slot_;
  pending_slot_ = -1;
  Job& job = jobs_[slot];
  job.seq = next_seq_++;
  if (job.has_pim) job.pim = pim_;
  chain_[job.seq % kChain] = job.has_pim ? pim_ : Preintegrated(pim_params_);
  chain_seq_[job.seq % kChain] = job.seq;
  const NavState& x = front_.propagated();
  pim_.reset(x.bg_rps, x.ba_mps2, job.t_ns);
  pim_active_ = true;
  t_last_frame_ns_ = job.t_ns;
  ++wc_.jobs;
  if (threaded_) {
    // Cannot fail: the ring holds more than the pool.
    (void)todo_.try_push(static_cast<uint8_t>(slot));
  } else {
    process(slot);
    free_slots_[n_free_++] = slot;
  }
}

void WindowEstimator::poll_results() {
  WindowSolveResult r;
  if (threaded_) {
    uint64_t version = 0;
    if (results_.version() == last_result_version_) return;
    if (!results_.read(r, &version)) return;
    last_result_version_ = version;
  } else {
    if (!inline_result_new_) return;
    inline_result_new_ = false;
    r = inline_result_;
  }
  if (r.seq <= last_applied_seq_) return;
  last_applied_seq_ = r.seq;
  last_solve_ns_ = r.solve_ns;
  if (r.seq < first_seq_of_epoch_) {
    ++wc_.stale_results;
    return;
  }
  apply(r);
}

void WindowEstimator::fail_and_maybe_reset() {
  ++wc_.failures;
  if (++consecutive_failures_ >= opt_.max_consecutive_failures) {
    reset_requested_ = true;
    window_started_ = false;
    consecutive_failures_ = 0;
    ++wc_.window_resets;
    front_.count_reset();
  }
}

void WindowEstimator::apply(const WindowSolveResult& r) {
  if (!r.ok) {
    fail_and_maybe_reset();
    return;
  }
  NavState x = unpack(r.x);
  // Forward through the frames queued after this one, then the IMU since the
  // newest of them, to the propagated state's time.
  for (uint64_t k = r.seq + 1; k < next_seq_; ++k) {
    if (chain_seq_[k % kChain] != k) {
      ++wc_.stale_results;
      return;
    }
    x = predict(x, chain_[k % kChain]);
  }
  x = predict(x, pim_);
  const NavState& now = front_.propagated();
  if (std::llabs(x.t_ns - now.t_ns) > 1'000'000) {
    ++wc_.stale_results;  // the front end skipped samples we integrated (or the reverse)
    return;
  }
  x.t_ns = now.t_ns;
  if (!finite(x) || (x.p_WB - now.p_WB).norm() > opt_.max_correction_m) {
    fail_and_maybe_reset();
    return;
  }
  consecutive_failures_ = 0;
  td_s_ = r.td_s;
  x.q_WB.normalize();
  front_.correct_state(x);
  front_.set_pose_covariance(window_->newest_pose_covariance());  // the last solve's, kept until the next one
  ++wc_.applied;
  if (r.has_kf) {
    Eigen::Isometry3d T_WC = Eigen::Isometry3d::Identity();
    T_WC.linear() =
        Eigen::Quaterniond(r.kf_q[0], r.kf_q[1], r.kf_q[2], r.kf_q[3]).normalized().toRotationMatrix();
    T_WC.translation() = Eigen::Vector3d(r.kf_p[0], r.kf_p[1], r.kf_p[2]);
    front_.tracker().set_keyframe_pose(r.kf_t_ns, T_WC);
  }
}

// ---- optimizer side ------------------------------------------------------------

bool WindowEstimator::optimizer_step() {
  const uint8_t* s = todo_.front();
  if (s == nullptr) return false;
  const int slot = *s;
  todo_.pop();
  process(slot);
  (void)done_.try_push(static_cast<uint8_t>(slot));
  return true;
}

void WindowEstimator::process(int slot) {
  const int64_t t0 = rt::now_ns();
  const Job& job = jobs_[slot];
  WindowSolveResult out;
  out.seq = job.seq;
  out.x.t_ns = job.t_ns;
  WindowFrameInput in;
  in.t_ns = job.t_ns;
  in.guess = job.guess;
  in.imu_from_prev = job.has_pim ? &job.pim : nullptr;
  in.obs = obs_of(slot);
  in.n_obs = job.n_obs;
  in.uv_vel_pxps = opt_.window.estimate_time_offset ? vel_of(slot) : nullptr;
  in.depth_vel_mps = opt_.window.estimate_time_offset ? dvel_of(slot) : nullptr;
  in.td_meas_s = job.td_meas_s;
  in.td_meas_sigma_s = job.td_meas_sigma_s;
  in.keyframe = job.keyframe || window_->num_states() == 0;
  in.stationary = job.stationary;
  in.vision_only = job.vision_only;
  if (job.has_map_pose) {
    in.has_pose_prior = true;
    in.prior_p_WB = job.T_WB_map.translation();
    in.prior_q_WB = Eigen::Quaterniond(job.T_WB_map.linear());
    in.prior_sigma_p_m = job.map_sigma_p_m;
    in.prior_sigma_rad = job.map_sigma_rad;
  }
  if (job.reset || (!job.has_pim && !job.vision_only)) {
    window_->reset();
    in.imu_from_prev = nullptr;
    in.keyframe = true;
    out.reset_done = true;
  }
  bool ok = window_->add_frame(in);
  if (ok) {
    const WindowOptimizer::Result res = window_->optimize();
    ok = res.ok;
  }
  const NavState& x = window_->latest();
  ok = ok && finite(x) && x.v_WB.norm() < opt_.max_speed_mps && x.t_ns == job.t_ns;
  out.ok = ok;
  if (ok) {
    solves_ok_.fetch_add(1, std::memory_order_relaxed);
    out.x = pack(x);
    out.td_s = window_->problem().td_s;
    NavState kf;
    if (job.tracker_kf_t_ns >= 0 && window_->state_of(job.tracker_kf_t_ns, &kf) && finite(kf)) {
      Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();
      T_WB.linear() = kf.q_WB.normalized().toRotationMatrix();
      T_WB.translation() = kf.p_WB;
      const Eigen::Isometry3d T_WC = T_WB * T_BC_;
      const Eigen::Quaterniond q(T_WC.linear());
      out.has_kf = true;
      out.kf_t_ns = job.tracker_kf_t_ns;
      for (int i = 0; i < 3; ++i) out.kf_p[i] = T_WC.translation()[i];
      out.kf_q[0] = q.w();
      out.kf_q[1] = q.x();
      out.kf_q[2] = q.y();
      out.kf_q[3] = q.z();
    }
  }
  out.solve_ns = rt::now_ns() - t0;
  opt_latency_.record(out.solve_ns);
  if (threaded_) {
    results_.publish(out);
  } else {
    inline_result_ = out;
    inline_result_new_ = true;
  }
}

EstimatorWorkers WindowEstimator::workers() {
  EstimatorWorkers w;
  w.add(&optimizer_worker_);
  if (map_) {
    w.add(&map_->mapping_worker());
    w.add(&map_->loop_worker());
  }
  return w;
}

EstimatorView WindowEstimator::view() const {
  EstimatorView v;
  v.tracker = &front().tracker();
  v.has_optimizer = true;
  v.optimizer.jobs = wc_.jobs;
  v.optimizer.applied = wc_.applied;
  v.optimizer.failures = wc_.failures;
  v.optimizer.skipped_busy = wc_.skipped_busy;
  v.optimizer.resets = wc_.window_resets;
  v.optimizer.last_solve_ns = last_solve_ns_;
  return v;
}

}  // namespace kestrel::core

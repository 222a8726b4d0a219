// The EKF SLAM backend (ekf_slam.hpp, paper 003) as a pipeline estimator,
// `--estimator ekf` / `estimator: backend: ekf`: IMU-mode EKF (pose, velocity,
// biases and a bounded set of landmarks in one covariance) fed by the tracker's
// correspondences as virtual-stereo observations.
//
// Per IMU sample: one strapdown step of the filter (pose block only).
// Per frame: the filter is propagated to the frame time, its pose predicts the
// tracker's search, and the tracker's observations (keyframe points with
// persistent ids and the current frame's registered depth) update pose and
// landmarks together; a keyframe the tracker re-located on its local map
// adds that pose as a measurement. The tracker's chained pose is not used:
// the filter is the estimate. Start-up: the static initialiser of the dead-reckoning backend.
//
// Fixed memory: every buffer is sized in the constructor; add_imu and
// add_frame make no heap allocation in steady state (tests/ekf). The update
// needs ~300 KiB of stack (Eigen's GEMM panels, docs/ekf.md).
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/core/divergence.hpp"
#include "kestrel/core/ekf_slam.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/core/map_system.hpp"
#include "kestrel/core/tracker.hpp"
#include "kestrel/rt/latency_histogram.hpp"

namespace kestrel::core {

struct EkfEstimatorOptions {
  TrackerOptions tracker;
  // Active landmarks. The update costs ~ (15 + 3C)^2 * (observations) flops:
  // 64 keeps a frame at a few ms on a small board (docs/ekf.md, figures).
  int landmark_capacity = 64;
  // Pixel noise of every observation. The tracker's keypoints are 1 px at
  // level 0 and grow with the pyramid level; one value covers the mix.
  double pixel_sigma_px = 1.5;
  int max_missed_frames = 3;  // then a landmark leaves the filter into the map
  // With more new tracks than free slots, the slots go to the emptiest cells
  // of this grid over the image first (EkfSlamOptions::spread_grid_cols).
  // 0 columns: the tracker's order.
  int spread_grid_cols = 0;
  int spread_grid_rows = 0;
  double gate_chi2 = 13.28;  // 4 dof, 99 %
  // A tracked pixel without depth (its keyframe point now beyond the sensor's
  // range, or in a hole of the depth image) updates its landmark, if the
  // filter holds one, with its two pixel rows, and brings in a map point at
  // the map's position; off, it is thrown away and its landmark counted as
  // unseen. Off by default: the tracker only follows points a keyframe saw
  // with depth, so these are 2-3 % of its observations, and on the seven
  // whole-length EuRoC flights they left the error equal or up to 13 % worse
  // (docs/ekf.md, "Pixels without depth"); on the real 7-Scenes frames,
  // 3-9 % better.
  bool depthless_observations = false;
  double mono_gate_chi2 = 9.21;  // the gate for those: 2 dof, 99 %
  // Start-up covariance (the static initialiser fixes position and yaw by
  // definition; roll/pitch and gyro bias come from a short still window).
  double init_position_sigma_m = 1e-3;
  double init_attitude_sigma_rad = 0.01;
  double init_velocity_sigma_mps = 0.2;
  double init_gyro_bias_sigma_rps = 0.005;
  double init_acc_bias_sigma_mps2 = 0.1;
  // Without a still window by moving_start_after_ns the initialiser takes
  // gravity from a moving window (estimator.hpp): tilt and velocity are then
  // guesses, with these sigmas, which the filter corrects from vision.
  // 0.25 s, as vo and window (frontend_odometry.hpp).
  int64_t moving_start_after_ns = 250'000'000;
  double moving_init_attitude_sigma_rad = 0.1;
  double moving_init_velocity_sigma_mps = 1.0;
  // Position sigma after a re-initialisation. The first start defines W
  // (init_position_sigma_m, 1 mm); a restart keeps the coasted position,
  // which is a guess: at 1 mm the filter refused every map pose more than
  // ~8 cm away (the 99 % gate with a 2 cm map pose), so the tracker's local
  // map, which takes poses up to frontend.map_max_correction_m (0.15 m)
  // away, could never pull it back. At 5 cm such a pose passes the gate
  // (NIS 7.8 at 0.15 m against 16.81).
  double restart_position_sigma_m = 0.05;
  // IMU noise used when the rig gives none (EuRoC-class MEMS).
  double default_gyro_noise_density = 1.7e-4;
  double default_acc_noise_density = 2.0e-3;
  double default_gyro_random_walk = 2.0e-5;
  double default_acc_random_walk = 3.0e-3;
  // Every IMU noise density (the rig's or the defaults above) is multiplied
  // by this, as window.imu_noise_inflation: datasheet densities leave out an
  // airframe's vibration and any mismatch between the motion the IMU felt and
  // the one the camera saw. x30 is best on the hybrid EuRoC flights with their
  // real IMU (2-10x lower error); with the map poses below it costs little
  // on the simulator's datasheet IMU (docs/ekf.md, the sweep). The summary's
  // NIS figures say whether a rig's value fits.
  double imu_noise_inflation = 30.0;
  // Tracker search window: the prediction's pixel uncertainty grows with the
  // time since the last update that used observations.
  double pred_sigma_px_per_s = 60.0;
  double pred_sigma_min_px = 4.0;
  // A keyframe the tracker re-located on its local map (the depth-backed
  // points of past keyframes, docs/tracking.md) gives the filter that pose as
  // a measurement, as the window's map pose factor does: the filter forgets a
  // landmark 3 frames after it leaves the view, the local map remembers 8192,
  // so drift stops growing where the vehicle returns. Sigmas are lower bounds
  // on the PnP's own; the gate is chi2(6 dof, 99 %).
  bool use_map_pose = true;
  double map_pose_sigma_m = 0.02;
  double map_pose_sigma_rad = 0.01;
  double map_pose_gate_chi2 = 16.81;
  // The local map's points were placed at the filter's own earlier poses, so
  // a map pose is not independent of the state: taken at every keyframe it
  // counts the same information again and again, the filter turns
  // over-confident and gates its own landmarks (on `hard` at x1 IMU noise:
  // 232 gated instead of 7, 96 cm instead of 4.7). At most one per this
  // interval (docs/ekf.md: 0.25 s keeps most of the gain elsewhere).
  double map_pose_min_interval_s = 0.25;
  int max_lost_frames = 3;        // untracked frames before the tracker takes a new keyframe
  int min_used_for_tracking = 5;  // observations in the update for the frame to count as tracked
  // A frame closer than this to the last one the filter took is skipped (the
  // IMU carries the state across; the output keeps its rate). Feature
  // extraction is ~3/4 of the filter's CPU and costs the same on every frame,
  // so the camera rate is the lever. 50 ms takes every other frame of a 30 Hz
  // RGB-D camera (Kinect, OpenNI2) and every frame of a 20 Hz one; 0 takes
  // every frame. Negative (the default) is 50 with the map (mapping) and 0
  // without: with the map, its points hold the accuracy and its thread takes a
  // share of the CPU; without, each frame's observations are all the filter
  // has (docs/ekf.md, "Frame rate", the bench both ways). Only a frame after
  // a fix is skipped: after a frame that did not track, every frame is taken
  // until one does, so a loss is not stretched to twice its frames.
  double min_frame_interval_ms = -1.0;
  // The interval in effect (min_frame_interval_ms with the default resolved).
  double frame_interval_ms() const {
    return min_frame_interval_ms >= 0 ? min_frame_interval_ms : mapping ? 50.0 : 0.0;
  }
  // The window's map beside the filter (docs/ekf.md, "The map"): each
  // keyframe goes to the local mapping thread at the filter's pose, and the
  // refined points come back into the tracker's local map, so the map poses
  // above come from bundle-adjusted points. Off by default: the EKF is for
  // boards without the CPU for local bundle adjustment. Needs the caller's
  // map threads (Estimator::mapping_step / loop_step), as the window's.
  bool mapping = false;
  MapSystemOptions map;  // the config's map: section (EstimatorConfig::ekf_options)
  // With the map: a new landmark that is a map point starts at the map's
  // refined position and sigma, not at this frame's depth and pose (the
  // window's map-point prior, as a filter takes it).
  bool map_point_landmarks = true;
  // Divergence detection (the config's safety: section, docs/safety.md).
  DivergenceOptions divergence;

  // Empty when usable, else what is wrong (names the field).
  std::string validate() const;
};

// Counters beyond the generic ones (what the filter did with the tracker's output).
struct EkfEstimatorCounters {
  uint64_t observations_in = 0;        // from the tracker
  uint64_t observations_no_depth = 0;  // without depth (used only with depthless_observations)
  uint64_t observations_dropped = 0;   // beyond the per-frame buffer
  uint64_t frames_updated = 0;
  uint64_t frames_skipped = 0;  // closer than min_frame_interval_ms to the last frame taken
  uint64_t tracker_resets = 0;
  uint64_t filter_resets = 0;    // non-finite state: restarted from the IMU state
  uint64_t map_poses_used = 0;   // keyframe poses from the tracker's local map taken as a measurement
  uint64_t map_poses_gated = 0;  // ... refused by the gate
  uint64_t map_reanchors = 0;    // of the used, the first after a restart (a step, counted in reset_counter)
  double nis_sum = 0;            // first-chunk NIS and its degrees of freedom, summed
  double nis_dof_sum = 0;
  double pose_nis_sum = 0;  // EkfUpdateStats::pose_nis, summed over pose_nis_n updates
  uint64_t pose_nis_n = 0;
};

class EkfEstimator final : public Estimator {
 public:
  EkfEstimator(const Rig& rig, const EkfEstimatorOptions& opt = {});
  ~EkfEstimator() override;
  const char* name() const override { return "ekf"; }
  bool add_imu(const ImuSample& s) override;
  bool add_frame(const RgbdFrame& f) override;
  const EstimatorOutput& output() const override { return out_; }
  const EstimatorCounters& counters() const override {
    counters_.divergence = monitor_.counts();
    return counters_;
  }
  // Filter counters and the time of the EKF update alone (tracking excluded).
  std::string backend_summary() const override;

  // For consistency tests: the filter's marginal pose covariance, error
  // [rho, theta] with T_WB = T_hat exp([rho; theta]^) (docs/ekf.md).
  ekf::Mat6 pose_covariance() const { return ekf_.pose_covariance(); }
  bool started() const { return started_; }
  const EkfSlam& filter() const { return ekf_; }
  const EkfEstimatorCounters& ekf_counters() const { return ekf_counters_; }
  const TrackResult& last_track() const { return tracker_.last(); }
  const Tracker& tracker() const { return tracker_; }
  EstimatorView view() const override {
    EstimatorView v;
    v.tracker = &tracker_;
    return v;
  }
  const EkfEstimatorOptions& options() const { return opt_; }
  // Per frame with observations: ekf_.update() alone [ns].
  const rt::LatencyHistogram& update_latency() const { return update_latency_; }
  const DivergenceMonitor& divergence() const { return monitor_; }

  // With the map: its two workers.
  EstimatorWorkers workers() override {
    EstimatorWorkers w;
    if (map_) {
      w.add(&map_->mapping_worker());
      w.add(&map_->loop_worker());
    }
    return w;
  }
  MapSystem* map_system() const override { return map_.get(); }

 private:
  // moving: the velocity and tilt are guesses (a moving start, or a restart
  // after a divergence), with the wider start-up covariance.
  // restart: after a divergence or a numerical failure, whose position is a
  // coasted guess (restart_position_sigma_m), not the origin it defines.
  void start(const NavState& s0, bool moving, bool restart = false);
  void supervise();
  void set_quality(bool tracking);
  void propagate_to(int64_t t_ns);
  void publish(int64_t t_ns);
  void record_consistency(const EkfUpdateStats& st);
  void map_before_tracking();
  void map_after_update(const TrackResult& r, const RgbdFrame& f);

  EkfEstimatorOptions opt_;
  Eigen::Isometry3d T_BC_ = Eigen::Isometry3d::Identity();
  double fx_ = 1.0;
  double baseline_m_ = 0.25;
  int64_t max_gap_ns_ = 50'000'000;
  int64_t max_step_ns_ = 200'000'000;
  DeadReckoningEstimator init_;  // static initialisation only
  Tracker tracker_;
  EkfSlam ekf_;
  std::vector<StereoObservation> obs_;  // capacity fixed in the constructor
  bool started_ = false;
  int64_t t_state_ns_ = -1;  // time of the filter's mean
  int64_t last_imu_t_ns_ = -1;
  Eigen::Vector3d last_gyro_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d last_acc_ = Eigen::Vector3d::Zero();
  bool have_last_ = false;
  int64_t last_tracked_t_ns_ = -1;
  int64_t last_frame_t_ns_ = -1;   // the last frame taken (min_frame_interval_ms)
  bool last_frame_fixed_ = false;  // and whether it was a fix
  int lost_frames_ = 0;
  EstimatorOutput out_;
  mutable EstimatorCounters counters_;
  EkfEstimatorCounters ekf_counters_;
  rt::LatencyHistogram update_latency_;
  DivergenceMonitor monitor_;
  NavState last_fix_state_;
  bool have_fix_state_ = false;
  bool reanchor_pending_ = false;  // restarted, no map pose taken since
  int64_t last_map_pose_t_ns_ = -1;
  // The map (mapping on): the odometry's chain for it (KeyframePacket::chain)
  // steps on a loss of vision and on every restart.
  std::unique_ptr<MapSystem> map_;
  uint32_t map_chain_ = 0;
  bool map_chain_lost_ = false;
  uint64_t starts_ = 0;
  uint64_t map_chain_starts_ = 1;  // the first start opens chain 0
};

// The filter options the estimator derives from a rig: camera model and
// virtual baseline (so the virtual disparity's noise matches the depth
// sensor's sigma(z) = k z^2), depth range, IMU noise.
EkfSlamOptions ekf_slam_options_for(const Rig& rig, const EkfEstimatorOptions& opt, ekf::StereoCamera* cam,
                                    double* baseline_m);

}  // namespace kestrel::core

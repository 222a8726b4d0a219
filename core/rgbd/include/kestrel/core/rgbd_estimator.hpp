// The `rgbd` backend: RGB-D tracking without an IMU (ORB-SLAM3's RGB-D mode
// in Kestrel's pieces; docs/real-imagery.md).
//
// Per frame: a constant-velocity motion model predicts the camera pose (the
// search windows are placed with it, its rotation is not trusted); the
// tracker solves the motion against its keyframe in 6 DoF (rigid model on
// the pairs with depth, then RGB-D Gauss-Newton) and re-locates each new
// keyframe on its local map; the sliding window (window_optimizer.hpp) adds
// the frame as a vision-only state and refines the recent poses and their
// landmarks with reprojection + depth terms, the map pose factors anchoring
// it where old points are seen again. The window's newest pose is the output,
// and the tracker's keyframe takes the window's estimate of it.
//
// Frames: with no IMU and no gravity the world is the first body pose (W = B
// at the first frame): attitude is not levelled, so compare trajectories after
// an SE(3) alignment. The body is the rig's (T_BC); for an RGB-D camera alone
// it is the colour camera.
//
// Quality: kVisionOnly while frames are tracked; kLost when one is not (the
// pose then coasts on the motion model); after max_lost_frames the tracker and
// the window restart (reset counter), the pose holds still until a frame
// tracks again, and the local map may re-locate them.
//
// IMU samples are counted and ignored. Fixed memory: every buffer is sized at
// construction; add_frame() makes no heap allocation; the window is solved
// inline (bounded by its iteration limit).
#pragma once

#include <Eigen/Geometry>
#include <memory>
#include <string>

#include "kestrel/core/divergence.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/core/tracker.hpp"
#include "kestrel/core/window_optimizer.hpp"

namespace kestrel::core {

struct RgbdEstimatorOptions {
  TrackerOptions tracker;
  WindowOptions window;
  bool use_window = true;    // false: the tracker's poses alone (frame-to-keyframe + local map)
  int min_observations = 8;  // a frame with fewer stays out of the window
  // Search window: the motion model's pixel uncertainty at one frame, growing
  // with the time since the last tracked frame.
  double pred_sigma_px = 10.0;
  double pred_sigma_px_per_s = 150.0;
  int max_lost_frames = 3;   // untracked frames before the tracker and the window restart
  bool use_map_pose = true;  // keyframes re-located on the local map carry that pose into the window
  double map_pose_sigma_m = 0.02;
  double map_pose_sigma_rad = 0.01;
  double max_correction_m = 0.2;  // window vs tracked pose beyond this: the solve is not taken
  // Divergence detection (the config's safety: section, docs/safety.md): here
  // the speed and finiteness bounds and the coast timeout of the motion model.
  DivergenceOptions divergence;

  std::string validate() const;
};

struct RgbdCounters {
  uint64_t tracked = 0;
  uint64_t motion_model = 0;
  double refined_rms_px_sum = 0;  // tracked frames' inlier reprojection RMS at the final pose, summed      //
                                  // of those: posed by the motion-model fallback (TrackerOptions)
  uint64_t keyframes = 0;
  uint64_t lost = 0;
  uint64_t lost_few_matches = 0;  // of those: too few matches in the search windows
  uint64_t lost_no_motion = 0;    // of those: no consistent rigid motion among them
  uint64_t restarts = 0;
  uint64_t solves_ok = 0;
  uint64_t solves_rejected = 0;  // failed, non-finite or too far from the tracked pose
  uint64_t map_poses = 0;
  uint64_t model_estimates = 0;  // rigid fits over all tracked frames
};

class RgbdEstimator final : public Estimator {
 public:
  RgbdEstimator(const Rig& rig, const RgbdEstimatorOptions& opt = {});
  ~RgbdEstimator() override;
  const char* name() const override { return "rgbd"; }
  bool add_imu(const ImuSample& s) override;
  bool add_frame(const RgbdFrame& f) override;
  const EstimatorOutput& output() const override { return out_; }
  const EstimatorCounters& counters() const override { return counters_; }
  std::string backend_summary() const override;
  bool world_levelled() const override { return false; }

  const RgbdCounters& rgbd_counters() const { return rc_; }
  const TrackResult& last_track() const { return tracker_.last(); }
  const Tracker& tracker() const { return tracker_; }
  EstimatorView view() const override {
    EstimatorView v;
    v.tracker = &tracker_;
    return v;
  }
  const WindowOptimizer* window() const { return window_.get(); }

 private:
  Eigen::Isometry3d predict(int64_t t_ns) const;
  void restart();

  RgbdEstimatorOptions opt_;
  Eigen::Isometry3d T_BC_, T_CB_;
  Tracker tracker_;
  std::unique_ptr<WindowOptimizer> window_;
  EstimatorOutput out_;
  EstimatorCounters counters_;
  RgbdCounters rc_;
  // Motion model: the last two output camera poses.
  Eigen::Isometry3d T_WC_last_ = Eigen::Isometry3d::Identity(), T_WC_prev_ = Eigen::Isometry3d::Identity();
  int64_t t_last_ns_ = -1, t_prev_ns_ = -1;
  int64_t last_tracked_t_ns_ = -1;
  int lost_frames_ = 0;
  bool hold_ = false;  // lost past max_lost_frames: the pose stays put until a frame tracks
  bool window_started_ = false;
  DivergenceMonitor monitor_;
};

}  // namespace kestrel::core

// The tracking step of paper 000 ("IMU accelerated pose calculation"):
// ORB features of the current frame are matched against the current
// keyframe's features by projecting the keyframe's depth-backed 3D points with
// the IMU-predicted pose and searching a circle window around each
// prediction; LONSC with the IMU rotation rejects outliers and solves the
// translation (eq. 3, Algorithm 1); Gauss-Newton refines (R, t) on the inliers.
// A new keyframe is taken when the image area covered by matched points falls
// below a share of the area covered by all detected points (paper: 50-60 %).
//
// Tracking is frame-to-keyframe, not frame-to-frame: while the keyframe stays,
// errors do not accumulate from frame to frame (a hovering vehicle keeps one
// keyframe for seconds). Fixed memory: every buffer is sized in the
// constructor; track() makes no heap allocation.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <memory>
#include <string>

#include "kestrel/core/camera.hpp"
#include "kestrel/core/lonsc.hpp"
#include "kestrel/core/motion_estimation.hpp"
#include "kestrel/core/observation.hpp"
#include "kestrel/core/orb.hpp"
#include "kestrel/core/rigid_consensus.hpp"
#include "kestrel/core/stereo_matcher.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::core {

struct TrackerOptions {
  OrbOptions orb;
  // Circle window: radius = clamp(k_sigma * predicted pixel uncertainty, min, max).
  double search_radius_min_px = 20.0;
  double search_radius_max_px = 60.0;
  double search_k_sigma = 3.0;
  float match_ratio = 0.85f;     // best < ratio * second best within the window
  int match_max_hamming = 80;    // of 256 bits
  int match_max_level_diff = 1;  // pyramid levels between keyframe and current keypoint
  LonscOptions lonsc;
  CorrespondenceOrder order = CorrespondenceOrder::kByMatchCost;
  // Without an IMU rotation (track(..., rotation_known = false): the rgbd
  // backend, the window backend while its IMU is silent): a 3-point rigid
  // model on the pairs with a current depth, found by LONSC's ordered runs
  // or RANSAC (rigid_consensus.hpp), then RGB-D Gauss-Newton on its inliers.
  RigidMethod rigid_method = RigidMethod::kLonsc;
  RigidOptions rigid;
  PoseRefineOptions refine;
  double keypoint_sigma_px = 1.0;  // at level 0; scales with the level
  int min_inliers = 15;            // below: the frame is not tracked
  // Without an IMU rotation, a frame the rigid consensus cannot fix (too few
  // pairs with a current depth: a dropped or repeated depth image, depth
  // lost to range or glare) is tracked the way ORB-SLAM tracks with its
  // motion model: Huber Gauss-Newton on every match from the predicted pose,
  // three rounds dropping the matches beyond the consistency bound. With no
  // consensus behind it the pose needs more inliers than a consensus does.
  // 0: off (the frame is lost).
  int motion_model_min_inliers = 30;
  // Keyframes.
  double keyframe_area_ratio = 0.55;  // matched / detected area below this: new keyframe
  int keyframe_min_inliers = 60;      // fewer inliers than this: new keyframe
  double keyframe_max_interval_s = 5.0;
  int area_grid_cols = 16;  // the area measure (docs/tracking.md)
  int area_grid_rows = 12;
  // Depth: a 3x3 neighbourhood spread above this fraction of the depth marks
  // a depth edge, where the back-projection would mix two surfaces.
  double depth_edge_rel = 0.05;
  // Local map: the depth-backed points of past keyframes, kept in world
  // coordinates (ring of map_capacity, oldest overwritten). A new keyframe
  // searches it by projection, and when enough old points are found again it
  // takes the pose they give (PnP) instead of the chained one: drift then
  // stops growing wherever the vehicle returns to what it has seen.
  int map_capacity = 8192;  // 0: off
  double map_search_radius_px = 12.0;
  int map_match_max_hamming = 60;
  float map_match_ratio = 0.8f;
  double map_depth_tol_rel = 0.05;     // |z_feature - z_map| <= rel * z + 3 cm
  int map_min_inliers = 20;            // fewer: the keyframe keeps its chained pose
  double map_max_correction_m = 0.15;  // a larger jump is taken for a false match set
  double map_max_correction_rad = 0.05;
  double map_max_sigma_m = 0.03;  // a PnP less certain than this (clustered points) is not reported
  // Far tracks: keyframe features without depth (beyond the depth sensor's
  // range, mostly) are followed too, once the frame's motion is known, along
  // their epipolar segment between the sensor's max range and infinity. They
  // go out as observations without depth (the window triangulates them); the
  // motion itself still comes from the depth-backed points alone.
  bool far_tracks = false;
  double far_search_radius_px = 3.0;  // distance from the segment, at level 0 (scales with the level)
  double far_max_segment_px = 40.0;   // a longer segment is too ambiguous to search
  // Stereo rigs (a rectified Rig::stereo): each feature's depth from the row
  // search in the right image (stereo_matcher.hpp, docs/stereo.md).
  StereoMatchOptions stereo;

  [[nodiscard]] std::string validate() const;
};

enum class TrackStatus : uint8_t {
  kTracked = 0,
  kNewKeyframe,  // the first frame, or a re-initialisation: nothing to track against
  kNoImage,
  kFeatureError,  // the extractor refused the image (size/format)
  kTooFewMatches,
  kMotionFailed,  // LONSC / refinement found no consistent motion
};
const char* to_string(TrackStatus s);

struct TrackResult {
  TrackStatus status = TrackStatus::kNoImage;
  Eigen::Isometry3d T_WC = Eigen::Isometry3d::Identity();  // valid when tracked() or a keyframe was set
  bool keyframe = false;                                   // this frame became the keyframe
  int detected = 0;                                        // features in the current frame
  int with_depth = 0;                                      // of those, with a valid depth
  int stereo_searched = 0;       // stereo: features searched along their row of the right image
  bool stereo_no_right = false;  // stereo: the frame came without its right image (tracked without depth)
  int predicted = 0;             // keyframe points that projected into the image
  int matched = 0;               // correspondences handed to LONSC
  int inliers = 0;
  int far_predicted = 0;  // far tracks: keyframe features without depth searched
  int far_tracked = 0;    // ... and found again (observations without depth)
  double area_ratio = 0;  // matched / detected cells of the area grid
  double search_radius_px = 0;
  double inlier_rms_px = 0;
  // Reprojection RMS of the inliers at the final pose [px]: a calibration
  // that is off (intrinsics, distortion, registration) shows here first.
  double refined_rms_px = 0;
  // Local map search (keyframes only): points re-found, PnP inliers, and
  // the pose they give (camera in W, 1-sigma bounds: the largest axis) with
  // its distance from the chained pose. map_corrected: the keyframe took it
  // (only when it started without a keyframe to chain from).
  int map_matched = 0;
  int map_inliers = 0;
  bool map_pose_valid = false;
  Eigen::Isometry3d T_WC_map = Eigen::Isometry3d::Identity();
  double map_sigma_p_m = 0, map_sigma_rad = 0;
  double map_correction_m = 0;
  bool map_corrected = false;
  MotionStatus motion_status = MotionStatus::kOk;
  bool six_dof = false;       // tracked without a rotation prior (rigid model)
  bool motion_model = false;  // six_dof: the rigid consensus failed, the motion-model fallback fixed the pose
  int model_estimates = 0;    // six_dof: rigid fits the consensus search made
  bool tracked() const { return status == TrackStatus::kTracked; }
};

// One feature of the last frame as a display draws it (tools/viewer): where it
// was detected and what became of it. Flags combine.
struct FeatureMark {
  static constexpr uint8_t kDepth = 1;     // a valid depth at the keypoint
  static constexpr uint8_t kMatched = 2;   // matched to a keyframe point (handed to LONSC)
  static constexpr uint8_t kInlier = 4;    // a LONSC inlier: it moved the pose
  static constexpr uint8_t kMapPoint = 8;  // re-found in the local map (keyframes only)
  static constexpr uint8_t kFar = 16;      // a far track: a keyframe feature without depth, found again
  float x_px = 0, y_px = 0;                // as detected (distorted pixel, level 0)
  uint8_t flags = 0;
};

class Tracker {
 public:
  Tracker(const Rig& rig, const TrackerOptions& opt = {});
  ~Tracker();
  Tracker(const Tracker&) = delete;
  Tracker& operator=(const Tracker&) = delete;

  // One frame. T_WC_pred: the camera pose predicted by IMU propagation; its
  // rotation relative to the keyframe is LONSC's R. pred_sigma_px: the
  // prediction's uncertainty projected into the image (sets the window).
  // depth: registered to `image` (DepthU16), may be absent (then no new
  // keyframe can be made, only tracking against the existing one).
  // rotation_known = false: T_WC_pred is a motion-model guess (no gyro): its
  // rotation only places the search windows and the motion is solved in 6
  // DoF from the pairs with depth (TrackerOptions::rigid_method).
  const TrackResult& track(int64_t t_ns, const ImageView& image, const ImageView& depth,
                           const Eigen::Isometry3d& T_WC_pred, double pred_sigma_px,
                           bool rotation_known = true);
  // A stereo rig (Rig::stereo rectified): image and right are the rectified
  // pair and the features' depth comes from the row search; a frame without
  // its right image is tracked with depth-less features. Without a stereo
  // rig `right` is ignored.
  const TrackResult& track(int64_t t_ns, const ImageView& image, const ImageView& depth,
                           const ImageView& right, const Eigen::Isometry3d& T_WC_pred, double pred_sigma_px,
                           bool rotation_known = true);
  bool stereo() const;

  // Drops the keyframe: the next frame with depth starts a new one at its predicted pose.
  void reset();
  bool has_keyframe() const;
  int64_t keyframe_t_ns() const;
  // The last frame's observations of landmarks with persistent ids, for the
  // back ends: a tracked frame's inliers under the ids of the keyframe points
  // they matched, and on a new keyframe also each of its features with depth
  // (a feature that matched keeps the old id, so a landmark lives on across
  // keyframes while it is re-detected). uv undistorted [px].
  int num_observations() const;
  const WindowObservation* observations() const;
  // The back end refined the keyframe's pose: track against the refined one.
  // False (nothing changed) when t_ns is not the current keyframe's time.
  bool set_keyframe_pose(int64_t t_ns, const Eigen::Isometry3d& T_WC);
  // The current keyframe's pose (valid when has_keyframe()).
  Eigen::Isometry3d keyframe_pose() const;
  // The current keyframe's features for the map: at most `capacity`, returns
  // how many were written (0 without a keyframe). Allocation-free.
  int keyframe_features(KeyframeFeature* out, int capacity) const;
  // Points of the map (refined by local bundle adjustment, in W) enter the
  // local map: a point already there (same landmark id) takes the new
  // position, the others take ring slots (the oldest entries go). Tracked
  // observations of these points then carry their position to the window as
  // a prior (WindowObservation::map_sigma_m). Allocation-free.
  void apply_map_points(const MapPointUpdate* pts, int n);
  // Empties the local map (the map's frame moved against W: its points are
  // re-sent in the new alignment).
  void clear_map();
  const TrackResult& last() const { return result_; }
  const TrackerOptions& options() const { return opt_; }

  // Read-only views for a display, on the tracking thread between track()
  // calls; both copy into the caller's buffer (no allocation) and return how
  // many they wrote. The last frame's features (none when extraction failed):
  int copy_last_features(FeatureMark* out, int max_n) const;
  // The local map's points p_W [m] as x y z floats (xyz holds 3 * max_n); a
  // map larger than max_n is subsampled evenly.
  int copy_map_points(float* xyz, int max_n) const;

 private:
  struct Impl;
  TrackerOptions opt_;
  TrackResult result_;
  std::unique_ptr<Impl> impl_;
};

}  // namespace kestrel::core

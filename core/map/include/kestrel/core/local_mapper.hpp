// Paper 001's local mapping, for RGB-D: each new keyframe enters the map
// (features linked to the points the tracker already knew by id, new points
// from depth), points of the covisible keyframes are projected into it and
// fused, the new keyframe and its covisible neighbours are bundle-adjusted
// with their points (reprojection + depth, Huber; Ceres), and redundant
// keyframes and points seen too rarely are culled. Then the refined points
// around the new keyframe go back to the tracker (MapPointUpdate), which
// tracks against them and hands them to the window as landmark priors.
//
// Not real time: runs on the mapping thread and allocates (Ceres). docs/map.md.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <vector>

#include "kestrel/core/bundle_adjustment.hpp"
#include "kestrel/core/map.hpp"
#include "kestrel/core/motion_estimation.hpp"

namespace kestrel::core {

// The camera as the map sees it: undistorted pinhole pixels, the image size,
// the depth noise and the keypoint noise per pyramid level.
struct MapCamera {
  PinholeK K;
  int width = 0, height = 0;
  double depth_sigma_coeff_per_m = 0.0025;  // sigma_z = k z^2
  double keypoint_sigma_px = 1.0;           // at level 0
  double level_scale = 1.2;                 // per pyramid level
  double sigma_px(int level) const;
  double sigma_depth_m(double z) const;
  // A feature's point in the camera frame from its undistorted pixel and depth.
  Eigen::Vector3d point_C(const KeyframeFeature& f) const;
};

// A map point's 1-sigma [m]: the depth noise at its nearest measured depth
// (3 m without one) over the square root of its observations, at least
// floor_m. The window's prior and the loop's refit use the same model.
double point_sigma_m(const MapCamera& cam, const MapPoint& p, double floor_m);

struct LocalMapperStats {
  uint64_t keyframes = 0;     // inserted
  uint64_t refused_full = 0;  // not inserted: the map was full even after culling
  uint64_t points_created = 0;
  uint64_t points_fused = 0;        // duplicates merged
  uint64_t observations_added = 0;  // by projection (fusing), beyond the tracker's ids
  uint64_t points_culled = 0;
  uint64_t keyframes_culled = 0;
  uint64_t ba_runs = 0;
  uint64_t ba_failures = 0;
  uint64_t ba_outliers = 0;  // observations dropped by the bundle adjustment
};

class LocalMapper {
 public:
  LocalMapper(Map& map, const MapCamera& cam);

  // Inserts the keyframe at T_MC = T_MW * T_WC, fuses, bundle-adjusts and
  // culls. Returns its slot, -1 when the map refused it (full).
  int insert(const KeyframePacket& kf, const Eigen::Isometry3d& T_MW, int32_t parent);
  // The refined points around keyframe kf (its own, its covisible
  // neighbours', and those of keyframes near it that look the same way) in W
  // = T_WM * M, at most `capacity`. Returns how many were written.
  int export_points(int kf, const Eigen::Isometry3d& T_WM, MapPointUpdate* out, int capacity);
  // The neighbourhood of kf: covisible first, then near in space; at most max.
  int neighbourhood(int kf, int max, int32_t* out);

  // A point's 1-sigma as a prior [m].
  double point_sigma_m(const MapPoint& p) const;
  const LocalMapperStats& stats() const { return stats_; }
  const MapCamera& camera() const { return cam_; }
  // The bundle adjustment of keyframe kf's neighbourhood alone (tests).
  bool bundle_adjust(int kf);

 private:
  void link_features(int kf);
  void fuse(int kf);
  void cull_points(int kf);
  void cull_keyframes(int kf);

  Map& map_;
  MapCamera cam_;
  LocalMapperStats stats_;
  std::vector<int32_t> kf_scratch_, shared_scratch_, pt_scratch_;
  BaProblem ba_;  // reused: its vectors keep their capacity
  BaScratch ba_scratch_;
  std::vector<int32_t> ba_kf_;
  // The odometry path flown (MapKeyframe::path_m).
  double path_m_ = 0.0;
  bool have_last_ = false;
  Eigen::Vector3d last_p_W_ = Eigen::Vector3d::Zero();
};

}  // namespace kestrel::core

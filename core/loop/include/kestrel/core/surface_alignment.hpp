// Surface verification of a loop candidate: the query keyframe's depth grid
// aligned to the candidate's by a point-to-plane ICP in 4 DoF (yaw and
// translation: both keyframes see gravity), seeded by the map's poses. A
// loop's correction is drift, a few centimetres, so the map's own poses put
// the two surfaces close enough for projective association (KinectFusion's:
// a query point pairs with the candidate cell it projects into).
//
// It verifies where descriptors cannot: a revisit at two or three times the
// range, whose keypoints the 4-level pyramid does not repeat (docs/map.md,
// "Surface verification"). A look-alike elsewhere is never paired, since the
// seed is where the map already puts the place; a surface that leaves a
// direction free (one wall, a floor and a wall) is refused by the
// observability test instead of being closed along it.
// Not real time: the loop thread; its scratch keeps its capacity.
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <vector>

#include "kestrel/core/depth_grid.hpp"

namespace kestrel::core {

struct SurfaceAlignOptions {
  int iterations = 15;
  double max_pair_m = 0.2;            // association bound of the first iteration, shrinking to min_pair_m
  double min_pair_m = 0.03;           // ... at the last
  double max_normal_angle_rad = 0.5;  // paired normals agree within this
  // A cell has a normal when its four neighbours' depths are within this x z
  // (+ 2 cm) of its own: across a depth step there is no surface to pair with.
  double normal_max_step_rel = 0.1;
  double inlier_floor_m = 0.01;  // a pair is an inlier within this + 3 sigma of both depths
  // Query cells landing on a candidate cell with depth, of those with depth:
  // the view overlap (at the map's poses, and again at the solution).
  double min_overlap = 0.3;
  // Inliers among the landed cells: occlusion and cells without a normal keep
  // a true revisit below 1, a wrong alignment pairs few.
  double min_inlier_share = 0.5;
  // The weakest direction of (yaw x range, translation) carries at least
  // this share of the pairs' constraint (smallest eigenvalue of their mean
  // normalised information): 0 for one wall, about 0.04 for a room's corner
  // with two crates (one view a side). The gates' defaults: docs/map.md,
  // "Surface verification".
  double min_observability = 0.015;
  // Neighbouring cells share surface and depth bias, and a real sensor's
  // depth carries systematic error across the whole image: the covariance
  // counts this many independent pairs, not every cell (docs/map.md, "Real
  // frames": 50 closed loops 5-8 cm off the truth there).
  int independent_pairs = 20;
  // Views beside each side's own keyframe (LoopCloser picks covisible ones
  // looking most unlike it): one view may see only a floor and a wall, or
  // overlap the other too little, where its neighbours close the gap. 0: one
  // keyframe a side (docs/map.md, "Neighbouring views on both sides").
  int neighbours = 2;
};

// One keyframe's grid and where the map puts its camera.
struct SurfaceView {
  const uint16_t* z_mm = nullptr;
  Eigen::Isometry3d T_MC = Eigen::Isometry3d::Identity();
};

struct SurfaceFit {
  bool ok = false;
  // Why not: "no_grid", "overlap", "moved" (further than max_pair_m from the
  // seed: beyond the basin its pairing can see, it slid), "inliers",
  // "observability", "solve".
  const char* failed = "";
  // T_MC_true = correction * T_MC of the query (4 DoF, about M's origin), as PlaceFit.
  Eigen::Isometry3d correction = Eigen::Isometry3d::Identity();
  Eigen::Matrix4d cov = Eigen::Matrix4d::Zero();  // of (yaw [rad], t [m]), as PlaceFit
  int query_cells = 0, landed = 0, paired = 0, inliers = 0;
  double overlap = 0, inlier_share = 0, rms_m = 0, observability = 0;
};

class SurfaceAligner {
 public:
  // depth_sigma_coeff_per_m: sigma_z = k z^2 (MapCamera's depth model).
  void set_shape(const DepthGridShape& shape, double depth_sigma_coeff_per_m);
  bool enabled() const { return shape_.cells() > 0; }
  const DepthGridShape& shape() const { return shape_; }
  // Aligns grid z_q (seen from T_MC_q) to grid z_c (from T_MC_c).
  SurfaceFit align(const uint16_t* z_q, const Eigen::Isometry3d& T_MC_q, const uint16_t* z_c,
                   const Eigen::Isometry3d& T_MC_c, const SurfaceAlignOptions& opt);
  // The query's views (the first is the query keyframe, whose camera the
  // rotation is about) moved together onto the candidate's views: each query
  // point pairs in whichever candidate view it lands on closest. The gates
  // count the cells of every query view. At most kMaxViews a side.
  static constexpr int kMaxViews = 8;
  SurfaceFit align(const SurfaceView* query, int n_query, const SurfaceView* cand, int n_cand,
                   const SurfaceAlignOptions& opt);

 private:
  double sigma_m(double z) const { return std::max(1e-3, k_ * z * z); }
  DepthGridShape shape_;
  double k_ = 0.0025;
  // Candidate views: point and normal per cell in its camera frame (normal
  // zero: none), view after view.
  std::vector<Eigen::Vector3d> c_pt_, c_n_;
  // Query: per cell in its camera frame, then the cells with depth in M.
  std::vector<Eigen::Vector3d> q_pt_C_, q_n_C_;
  std::vector<Eigen::Vector3d> q_pt_, q_n_;
  std::vector<double> q_z_;
};

// Cell normals of a grid in its camera frame from the neighbouring cells'
// points (zero where a neighbour is missing or off the surface); pt gets the
// points (zero where no depth). Both hold shape.cells() entries.
void depth_grid_points_normals(const DepthGridShape& shape, const uint16_t* z_mm, double max_step_rel,
                               Eigen::Vector3d* pt, Eigen::Vector3d* n);

}  // namespace kestrel::core

// The map of paper 001's local-mapping and loop-closing threads, in memory
// sized once: keyframes (pose, ORB features with depth, the map point each
// feature observes, a bag-of-words vector) and map points (position,
// descriptor, the keyframes that observe them), with the covisibility graph
// read off the observations. Capacities come from MapOptions; nothing grows
// after construction, and when the map is full the caller culls (LocalMapper)
// or the keyframe is refused (counted). docs/map.md.
//
// Frames: M is the map frame (gravity along -z like W, the odometry frame);
// keyframes carry T_MC (camera in M). The map and the odometry agree until a
// loop closure, a relocalisation or a loaded map moves M against W: that
// offset is T_map_odom (MapState).
//
// Threading: one object, touched by the mapping and loop threads one at a
// time (the harness serialises them); never by a real-time thread.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/core/observation.hpp"
#include "kestrel/core/vocabulary.hpp"

namespace kestrel::core {

struct MapOptions {
  int max_keyframes = 2000;
  int max_points = 200000;
  // Local bundle adjustment (local_mapper.hpp).
  int ba_keyframes = 8;         // covisible keyframes optimised with the new one
  int ba_fixed_keyframes = 16;  // other keyframes seeing the same points, held fixed
  int ba_iterations = 5;        // per round; two rounds with outliers dropped in between
  enum class BaSolver { kOurs, kCeres } ba_solver = BaSolver::kOurs;  // bundle_adjustment.hpp
  double ba_huber = 2.8;           // Huber on the whitened error (sqrt of chi2 95 % for 3 dof: 2.80)
  double ba_outlier_chi2 = 7.815;  // an observation above this after round 1 is dropped (chi2 95 %, 3 dof)
  // The odometry's gravity direction holds each keyframe's roll and pitch:
  // vision alone lets a growing map tilt, the IMU sees gravity (1-sigma [rad]).
  double ba_gravity_sigma_rad = 0.01;
  // Fusing: points of the covisible keyframes projected into a new one.
  double fuse_radius_px = 4.0;  // at level 0, scaled with the level
  int fuse_max_hamming = 50;
  double fuse_depth_tol_rel = 0.05;  // measured depth vs projected within rel x z + 3 cm
  // Culling.
  double cull_keyframe_redundancy = 0.9;  // its points seen by >= 3 other keyframes: the keyframe goes
  int cull_point_min_keyframes = 2;       // a point seen by fewer keyframes once 3 keyframes passed: it goes
  double cull_point_min_found_ratio = 0.25;  // found / predicted visible below this: it goes
  // What the tracker gets back (MapPointUpdate): refined points of the local
  // keyframes and of keyframes near the new one.
  int update_max_points = 4096;
  double neighbour_radius_m = 3.0;        // keyframes this close (and looking the same way) count as near
  double neighbour_max_angle_rad = 1.05;  // 60 deg between optical axes
  double point_sigma_floor_m = 0.01;      // a map point's prior in the window: at least this
  int point_min_keyframes_for_prior = 2;  // a point seen by fewer keyframes is not handed back
  double min_keyframe_interval_s = 0.0;   // keyframes closer in time are not mapped (0: all)
  // Each keyframe's depth, coarse (depth_grid.hpp): cols of the grid (rows
  // keep the image's aspect), 2 bytes a cell per keyframe slot, for the loop's
  // surface verification (0: none; a stereo rig has no depth image to sample).
  int depth_grid_cols = 64;
  double depth_grid_edge_rel =
      0.05;  // a cell whose 3x3 pixels spread more than this x z is a depth edge: empty

  [[nodiscard]] std::string validate() const;
};

// A keyframe as it arrives from the tracking thread.
struct KeyframePacket {
  uint64_t seq = 0;
  int64_t t_ns = 0;
  Eigen::Isometry3d T_WC = Eigen::Isometry3d::Identity();  // camera in W (odometry), refined by the window
  // The odometry's chain: steps whenever the odometry lost continuity (vision
  // gone past safety.max_coast_s, a re-initialisation). A keyframe of another
  // chain than the map is localised in may sit anywhere in the map until a
  // relocalisation finds it (MapSystem).
  uint32_t chain = 0;
  int n = 0;
  KeyframeFeature* features = nullptr;  // capacity: the tracker's feature budget
  // Its depth grid (depth_grid.hpp): capacity MapSystem::depth_grid_shape().cells()
  // (nullptr: no grid); grid_n cells with depth, 0 when none was sampled.
  uint16_t* grid_z_mm = nullptr;
  int grid_n = 0;
};

constexpr int kMaxPointObservations = 12;

struct MapKeyframe {
  uint32_t id = 0;  // 0: free slot; otherwise unique and increasing in insertion order
  int64_t t_ns = 0;
  Eigen::Isometry3d T_MC = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d T_WC = Eigen::Isometry3d::Identity();  // odometry pose when it came
  Eigen::Vector3d g_C = Eigen::Vector3d(0, 0, -1);         // gravity direction in C, from the odometry
  int32_t parent = -1;                                     // spanning tree: the keyframe it was chained from
  uint32_t session = 0;                                    // 0: this flight; > 0: loaded from a map file
  uint32_t chain = 0;     // the odometry chain of T_WC (KeyframePacket::chain): T_WC compare within one
  int n = 0;              // features
  int first_feature = 0;  // into Map::features / Map::point_of
  int n_bow = 0;          // its BoW vector: Map::bow(kf), n_bow entries (with a vocabulary)
  int grid_n = 0;         // cells of its depth grid with depth (Map::depth_grid), 0: none
  double path_m = 0.0;    // odometry path flown before it, this session (bounds a loop's drift)
  uint64_t mark = 0;      // scratch stamps for set membership in one pass
  uint64_t mark2 = 0;
};

struct MapPoint {
  uint32_t landmark_id = 0;  // 0: free slot; the id the tracker knows it by
  Eigen::Vector3d p_M = Eigen::Vector3d::Zero();
  OrbDescriptor desc{};
  int16_t level = 0;
  int16_t n_obs = 0;
  int32_t obs_kf[kMaxPointObservations] = {};
  int16_t obs_feat[kMaxPointObservations] = {};
  uint32_t first_kf_id = 0;  // the keyframe that made it (culling by age)
  uint32_t visible = 0;      // predicted in view of a new keyframe
  uint32_t found = 0;        // ... and matched there
  float min_depth_m = 0.0f;  // nearest measured depth over its observations
  uint64_t mark = 0;
};

class Map {
 public:
  // With a vocabulary every keyframe gets a BoW vector and enters the
  // inverted index (place recognition); without one it does not.
  Map(const MapOptions& opt, int features_per_keyframe,
      std::shared_ptr<const Vocabulary> vocabulary = nullptr);
  ~Map();
  Map(const Map&) = delete;
  Map& operator=(const Map&) = delete;

  const MapOptions& options() const { return opt_; }
  int max_keyframes() const { return opt_.max_keyframes; }
  int max_points() const { return opt_.max_points; }
  int features_per_keyframe() const { return fpk_; }
  int num_keyframes() const { return n_kf_; }
  int num_points() const { return n_pt_; }

  // Keyframes. add_keyframe copies the features and returns the slot, -1 when full.
  int add_keyframe(int64_t t_ns, const Eigen::Isometry3d& T_MC, const Eigen::Isometry3d& T_WC,
                   const KeyframeFeature* f, int n, int32_t parent, uint32_t session = 0);
  // Removes a keyframe with its observations; points left without one go too;
  // its children in the spanning tree take its parent.
  void erase_keyframe(int kf);
  bool keyframe_used(int kf) const { return kf >= 0 && kf < opt_.max_keyframes && kfs_[kf].id != 0; }
  MapKeyframe& keyframe(int kf) { return kfs_[kf]; }
  const MapKeyframe& keyframe(int kf) const { return kfs_[kf]; }
  KeyframeFeature& feature(int kf, int j) { return features_[static_cast<size_t>(kf) * fpk_ + j]; }
  const KeyframeFeature& feature(int kf, int j) const {
    return features_[static_cast<size_t>(kf) * fpk_ + j];
  }
  // The point feature j of keyframe kf observes, -1: none.
  int32_t point_of(int kf, int j) const { return point_of_[static_cast<size_t>(kf) * fpk_ + j]; }
  // The newest keyframe (largest id), -1 when empty.
  int newest_keyframe() const { return newest_kf_; }
  // Place recognition (null without a vocabulary).
  const Vocabulary* vocabulary() const { return vocab_.get(); }
  const KeyframeDatabase* database() const { return db_.get(); }
  const BowEntry* bow(int kf) const { return bow_.get() + static_cast<size_t>(kf) * fpk_; }
  // Depth grids (depth_grid.hpp): cells per keyframe, set once before the
  // first keyframe (allocates); a keyframe's grid, nullptr without grids.
  void enable_depth_grids(int cells);
  int depth_grid_cells() const { return grid_cells_; }
  uint16_t* depth_grid(int kf) {
    return grid_cells_ > 0 ? grids_.get() + static_cast<size_t>(kf) * grid_cells_ : nullptr;
  }
  const uint16_t* depth_grid(int kf) const {
    return grid_cells_ > 0 ? grids_.get() + static_cast<size_t>(kf) * grid_cells_ : nullptr;
  }
  // The word of feature j of keyframe kf (with a vocabulary).
  uint32_t word(int kf, int j) const { return words_[static_cast<size_t>(kf) * fpk_ + j]; }

  // Points. add_point returns the slot, -1 when full (or the id is taken).
  int add_point(uint32_t landmark_id, const Eigen::Vector3d& p_M, const OrbDescriptor& d, int level, int kf,
                int feat);
  bool point_used(int p) const { return p >= 0 && p < opt_.max_points && pts_[p].landmark_id != 0; }
  MapPoint& point(int p) { return pts_[p]; }
  const MapPoint& point(int p) const { return pts_[p]; }
  int find_point(uint32_t landmark_id) const;
  // kf's feature j observes p; false when the point's observation list is
  // full, the feature observes a point already, or p is seen by kf already.
  bool add_observation(int p, int kf, int feat);
  void erase_observation(int p, int kf);
  void erase_point(int p);
  // `from` is the same point as `into`: its observations move over, it goes.
  void merge_point(int from, int into);
  // Ids for points that did not come from this flight's tracker (loaded maps):
  // above 2^31, where the tracker's own ids do not reach (docs/map.md).
  uint32_t fresh_landmark_id();

  // Covisibility: keyframes sharing at least min_shared points with kf, the
  // most shared first; at most max written. Returns how many.
  int covisible(int kf, int min_shared, int max, int32_t* kf_out, int32_t* shared_out) const;

  // Every used slot, for iteration.
  template <class F>
  void for_each_keyframe(F f) const {
    for (int k = 0; k < opt_.max_keyframes; ++k)
      if (kfs_[k].id != 0) f(k);
  }
  uint64_t next_mark() { return ++mark_; }
  uint32_t next_keyframe_id() const { return next_kf_id_; }
  void set_next_ids(uint32_t kf_id, uint32_t fresh_id);
  uint32_t fresh_id_state() const { return next_fresh_id_; }

 private:
  void index_insert(uint32_t id, int32_t p);
  void index_erase(uint32_t id);
  MapOptions opt_;
  int fpk_;
  std::unique_ptr<MapKeyframe[]> kfs_;
  std::unique_ptr<KeyframeFeature[]> features_;
  std::unique_ptr<int32_t[]> point_of_;
  std::unique_ptr<MapPoint[]> pts_;
  std::vector<int32_t> free_kf_, free_pt_;  // stacks, sized at construction
  // landmark id -> point slot: open addressing, linear probing, backward-shift deletion.
  std::unique_ptr<uint32_t[]> idx_key_;
  std::unique_ptr<int32_t[]> idx_val_;
  uint32_t idx_mask_ = 0;
  std::shared_ptr<const Vocabulary> vocab_;
  std::unique_ptr<KeyframeDatabase> db_;
  std::unique_ptr<BowEntry[]> bow_;
  std::unique_ptr<uint32_t[]> words_;
  std::unique_ptr<OrbDescriptor[]> desc_scratch_;
  std::unique_ptr<uint16_t[]> grids_;
  int grid_cells_ = 0;
  mutable std::unique_ptr<int32_t[]> covis_count_;  // scratch per keyframe slot
  mutable std::unique_ptr<int32_t[]> covis_list_;
  int n_kf_ = 0, n_pt_ = 0;
  int newest_kf_ = -1;
  uint32_t next_kf_id_ = 1;
  uint32_t next_fresh_id_ = 0x80000000u;
  uint64_t mark_ = 0;
};

}  // namespace kestrel::core

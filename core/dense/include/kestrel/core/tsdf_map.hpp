// A hashed TSDF volume in fixed memory: the dense map of issue 44.
// Voxel blocks (8^3 voxels) come from a pool sized once from the memory
// budget; an open-addressing hash table (sized with it) finds a block by its
// integer coordinates. Depth images are fused projectively: every voxel of
// every block in the camera's view is projected into the image and its signed
// distance along the ray updated with a weight from the depth noise model, so
// voxels in front of a surface are carved free. Blocks far behind the camera
// are evicted to make room. Pure computation: no threads, no I/O
// (docs/dense.md).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/msgs.hpp"

namespace kestrel::core {

struct TsdfOptions {
  double voxel_size_m = 0.05;
  // Blocks come from this budget, allocated at construction (voxels and the hash table).
  double memory_budget_mb = 64.0;
  // Half-width of the band around a surface where the signed distance is
  // kept, in voxels (below ~2 voxels the band has holes at grazing angles).
  double truncation_voxels = 3.0;
  // Depth beyond this is not fused: the noise (sigma ~ z^2) swamps the voxel.
  double max_depth_m = 3.5;
  // Every n-th pixel in u and v allocates blocks around its surface point.
  int pixel_stride = 2;
  // Every n-th pixel allocates the blocks its ray crosses, so free space is
  // known (for the planner) in space no surface was seen in.
  int carve_stride = 8;
  // The depth at which an observation has weight 1: w = (sigma(ref) / sigma(z))^2,
  // sigma(z) = DepthModel::sigma_coeff_per_m * z^2 (inverse-variance fusion).
  double weight_reference_depth_m = 2.0;
  // A voxel's weight saturates here: the map can still change when the world does.
  double max_weight = 100.0;
  // A voxel with less weight is unknown (queries, the surface): about two
  // observations at 2.8 m, one at 2.4 m.
  double min_weight = 0.5;
  // Blocks whose centre is farther than this from the newest camera position
  // are evicted when the pool is full (before that, nothing is evicted).
  double evict_distance_m = 6.0;

  // Throws std::invalid_argument naming the key ("dense.voxel_size_m ...").
  void validate() const;
};

enum class Occupancy : uint8_t { kUnknown = 0, kFree = 1, kOccupied = 2 };
const char* to_string(Occupancy o);

struct TsdfCounters {
  uint64_t frames = 0;
  uint64_t blocks_allocated = 0;  // ever
  uint64_t blocks_evicted = 0;    // far behind, to make room
  uint64_t blocks_refused = 0;    // pool full and nothing far enough to evict: observation lost, counted
  uint64_t voxels_updated = 0;
  uint64_t pixels_invalid = 0;  // zero, non-finite, out of range
};

// One point of the extracted surface, in the map's frame.
struct SurfacePoint {
  Eigen::Vector3f p;
  uint8_t rgb[3] = {0, 0, 0};
};

class TsdfMap {
 public:
  static constexpr int kBlockSide = 8;
  static constexpr int kBlockVoxels = kBlockSide * kBlockSide * kBlockSide;

  explicit TsdfMap(const TsdfOptions& opt);

  // Fuses a depth image registered to `cam` (and its colour, optional: data
  // == nullptr) seen from T_MC (camera -> the map's frame M). Depth in
  // `depth_model` units; its sigma_coeff_per_m weights each observation.
  // Allocation-free after construction.
  void integrate(const ImageView& depth, const ImageView& rgb, const CameraIntrinsics& cam,
                 const DepthModel& depth_model, const Eigen::Isometry3d& T_MC);

  // Takes back what integrate() with the same arguments added (re-anchoring a
  // keyframe whose pose moved: remove it where it was, fuse it where it is).
  // Exact while no voxel's weight saturated at max_weight and its block was not
  // evicted in between; a voxel left without weight becomes unknown. Never
  // allocates a block. Allocation-free.
  void deintegrate(const ImageView& depth, const ImageView& rgb, const CameraIntrinsics& cam,
                   const DepthModel& depth_model, const Eigen::Isometry3d& T_MC);

  // The planner's queries. Unknown (never seen, weight too low, evicted) is
  // neither free nor occupied: a planner decides what it dares.
  Occupancy occupancy(const Eigen::Vector3d& p_M) const;
  // Walks the segment at half-voxel steps: kOccupied if any point is,
  // else kUnknown if any is, else kFree.
  Occupancy segment(const Eigen::Vector3d& a_M, const Eigen::Vector3d& b_M) const;
  // The signed distance at p [m] (trilinear within a voxel is not done: the
  // voxel's value), false where unknown.
  bool distance(const Eigen::Vector3d& p_M, float& sdf_m) const;

  // The zero crossings between neighbouring voxels (interpolated), with
  // colour: the surface as points. Allocates (`out`), not for real-time use.
  void extract_surface(std::vector<SurfacePoint>& out) const;
  // Centres of the voxels whose signed distance says occupied (|sdf| <
  // half a voxel or inside the band behind the surface): the OctoMap export.
  void occupied_voxels(std::vector<Eigen::Vector3f>& out) const;
  void free_voxels(std::vector<Eigen::Vector3f>& out) const;

  // Block by block, for a stream that sends only what changed (the viewer):
  // slots 0..block_capacity()-1; a slot's key changes when it is evicted and
  // reused. block_updated: counters().frames after the frame that last listed it (>= 1).
  bool block_used(int b) const { return blocks_[static_cast<std::size_t>(b)].used; }
  uint32_t block_updated(int b) const { return blocks_[static_cast<std::size_t>(b)].last_seen; }
  const Eigen::Vector3i& block_key_of(int b) const { return blocks_[static_cast<std::size_t>(b)].key; }
  double block_size_m() const { return block_size_m_; }
  // The surface points of one block (extract_surface's, block b's share):
  // at most `max` into `out`, returns how many. Allocation-free.
  int extract_block_surface(int b, SurfacePoint* out, int max) const;

  void clear();
  const TsdfOptions& options() const { return opt_; }
  const TsdfCounters& counters() const { return counters_; }
  int block_capacity() const { return capacity_; }
  int blocks_in_use() const { return in_use_; }
  std::size_t memory_bytes() const;

 private:
  struct Voxel {
    float sdf_m = 0;
    float weight = 0;
    uint8_t rgb[3] = {0, 0, 0};
    uint8_t pad = 0;
  };
  struct Block {
    Eigen::Vector3i key = Eigen::Vector3i::Zero();
    bool used = false;
    uint32_t last_seen = 0;  // frame counter
  };

  int find(const Eigen::Vector3i& key) const;  // block index or -1
  int find_or_allocate(const Eigen::Vector3i& key, const Eigen::Vector3d& cam_M);
  int list_existing(const Eigen::Vector3i& key);
  template <bool kRemove>
  void fuse(const ImageView& depth, const ImageView& rgb, const CameraIntrinsics& cam,
            const DepthModel& depth_model, const Eigen::Isometry3d& T_MC);
  bool evict_one_far(const Eigen::Vector3d& cam_M);
  void erase(int block);
  uint32_t slot_of(const Eigen::Vector3i& key) const;
  Eigen::Vector3i block_key(const Eigen::Vector3d& p_M) const;
  const Voxel* voxel_at(const Eigen::Vector3d& p_M) const;
  Occupancy classify(const Voxel& v) const;
  Eigen::Vector3f voxel_centre(int block, int i) const;
  // Calls emit(SurfacePoint) for each surface point of block b until it returns false.
  template <class Emit>
  void block_surface(int b, Emit&& emit) const;

  TsdfOptions opt_;
  double block_size_m_ = 0.4;
  double trunc_m_ = 0.15;
  int capacity_ = 0;
  int in_use_ = 0;
  uint32_t table_mask_ = 0;
  std::vector<int32_t> table_;  // block index, -1 = empty (linear probing)
  std::vector<Block> blocks_;
  std::vector<Voxel> voxels_;  // capacity_ * kBlockVoxels
  std::vector<int32_t> free_list_;
  std::vector<int32_t> in_view_;      // per integrate: blocks to update (capacity_)
  std::vector<uint32_t> view_stamp_;  // per block: the frame it was listed in
  TsdfCounters counters_;
  uint64_t evicted_in_frame_ = ~0ull;  // the frame whose eviction sweep ran (one per frame)
};

}  // namespace kestrel::core

// Global bundle adjustment after a loop (paper 001's loop-closing thread,
// ORB-SLAM's full BA): the 4-DoF pose graph moves the keyframes by drift, but
// leaves the points where their first observer took them and the keyframes'
// own errors in place; a bundle adjustment of the whole map over every
// observation takes those out. It runs in three steps so that the mapping
// thread is held only while the map is copied and written back:
//   snapshot()  under the map's lock: keyframe poses, points, observations;
//   solve()     without it, on the snapshot only (our solver, sparse);
//   apply()     under the lock again: the snapshot's keyframes and points take
//               the solution; keyframes mapped meanwhile take their spanning-
//               tree parent's correction and points their first observer's
//               (ORB-SLAM's write-back), so the map stays in one piece.
// Not real time (the loop thread): it allocates. docs/map.md.
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/core/bundle_adjustment.hpp"
#include "kestrel/core/local_mapper.hpp"
#include "kestrel/core/map.hpp"

namespace kestrel::core {

struct GlobalBaOptions {
  bool enabled = true;  // after each closed loop (map.global_ba)
  // Bounds on one run, so its cost is bounded by construction: the newest
  // keyframes are free (older ones that see the same points are held), the
  // points seen most often are kept.
  int max_keyframes = 1000;
  int max_points = 40000;
  int iterations = 10;  // per round; two rounds with outliers left out of the second
  // Each keyframe is held to its spanning-tree parent by the odometry's
  // relative pose between them (same chain), with these sigmas (0: none).
  // Loose, so the points decide wherever keyframes share them; where they
  // share few, the odometry keeps the map from bending.
  double odometry_sigma_m = 0.01;
  double odometry_sigma_rad = 0.01;

  [[nodiscard]] std::string validate() const;
};

struct GlobalBaStats {
  uint64_t runs = 0;
  uint64_t failures = 0;   // the solver found no usable step
  uint64_t keyframes = 0;  // free keyframes, last run
  uint64_t fixed_keyframes = 0;
  uint64_t points = 0;
  uint64_t observations = 0;
  uint64_t odometry_factors = 0;    // last run
  uint64_t loop_factors = 0;        // last run
  uint64_t outliers = 0;            // left out of the second round, last run
  uint64_t followed_keyframes = 0;  // mapped during the solve: took their parent's correction (all runs)
  uint64_t followed_points = 0;
  uint64_t lost_keyframes = 0;              // culled during the solve
  double initial_cost = 0, final_cost = 0;  // last run
  double max_keyframe_move_m = 0;           // last run, at write-back
};

// A closed loop for the adjustment: keyframe id_b seen from id_a (camera frames).
struct GlobalBaLoop {
  uint32_t id_a = 0, id_b = 0;
  Eigen::Matrix3d R_ab = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t_ab = Eigen::Vector3d::Zero();
  double sigma_m = 0.01, sigma_rad = 0.01;
};

class GlobalBundleAdjustment {
 public:
  GlobalBundleAdjustment(const MapCamera& cam, const GlobalBaOptions& opt) : cam_(cam), opt_(opt) {}

  // Copies the map's keyframes (this flight's: a loaded map's are held) and
  // points; false when there is nothing to adjust. Under the map's lock.
  // loops: the closed loops' relative poses (LoopCloser::loop_edges), held as
  // factors too: a loop verified by surfaces alone shares no point between
  // its two places, and without its edge the adjustment would reopen it.
  bool snapshot(const Map& map, const std::vector<GlobalBaLoop>& loops = {});
  // The solve, touching nothing but the snapshot. False: no usable solution.
  bool solve();
  // Writes the solution into the map (under the lock), returns true when it
  // moved it. A snapshot that was not solved is dropped.
  bool apply(Map& map);
  // A snapshot waits for solve() / a solution waits for apply().
  bool snapshotted() const { return state_ == State::kSnapshot; }
  bool solved() const { return state_ == State::kSolved; }
  const GlobalBaStats& stats() const { return stats_; }
  const GlobalBaOptions& options() const { return opt_; }

 private:
  enum class State { kIdle, kSnapshot, kSolved };
  struct KfRef {
    int32_t slot = -1;
    uint32_t id = 0;
    Eigen::Isometry3d T_MC;  // at the snapshot
  };
  struct PointRef {
    int32_t slot;
    uint32_t landmark_id;
    Eigen::Vector3d p_M;  // at the snapshot
  };
  MapCamera cam_;
  GlobalBaOptions opt_;
  double huber_ = 2.8, outlier_chi2_ = 7.815;
  State state_ = State::kIdle;
  bool ok_ = false;  // the solve gave a usable solution
  BaProblem pb_;
  BaScratch scratch_;
  std::vector<KfRef> kfs_;     // pb_.poses' order
  std::vector<PointRef> pts_;  // pb_.points_M's order
  // Per keyframe slot: its pose in the problem (-1: none); at write-back its
  // correction and whether it moved (1: solved or held, 2: followed its parent).
  std::vector<int32_t> slot_pose_;
  std::vector<Eigen::Isometry3d> delta_;
  std::vector<uint8_t> moved_, point_done_;
  GlobalBaStats stats_;
};

}  // namespace kestrel::core

// Relocalisation: after the odometry lost its chain (vision gone past
// safety.max_coast_s, a re-initialisation) or on a map loaded from a file,
// where is the camera in the map? A lost keyframe's BoW vector queries the
// inverted index over the whole map; the best candidates are verified by the
// same 3D-3D 4-DoF RANSAC as a loop (PlaceMatcher), with stronger evidence
// than a loop needs, since there is no drift bound to keep aliases out:
//  - more inliers and a larger inlier share (reloc_min_inliers, _share);
//  - unambiguous: if two candidates verify with poses that disagree, the place
//    looks like two places (a repeated texture) and nothing is concluded;
//  - consistent: reloc_consistent_keyframes consecutive lost keyframes must
//    give the same T_map_odom (within loop_consistency_m / _rad).
// Not real time: the mapping thread, on the keyframe packets it is handed
// while the map is not localised. docs/map.md.
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <memory>

#include "kestrel/core/loop_closer.hpp"

namespace kestrel::core {

struct RelocStats {
  uint64_t queries = 0;
  uint64_t candidates = 0;
  uint64_t verified = 0;            // keyframes with a verified, unambiguous place
  uint64_t rejected_ambiguous = 0;  // two places fit: refused
  uint64_t rejected_consistency = 0;
  uint64_t relocalisations = 0;
};

class Relocaliser {
 public:
  Relocaliser(Map& map, const MapCamera& cam, const LoopOptions& opt);

  // A lost keyframe: its features and where the current alignment puts it
  // (T_MC_guess = T_map_odom * T_WC). True when this keyframe completes the
  // evidence: *correction is then the 4-DoF T with T_MC_true = T * T_MC_guess,
  // so the new alignment is project_4dof(T * T_map_odom).
  bool relocalise(const KeyframeFeature* f, int n, const Eigen::Isometry3d& T_MC_guess, uint64_t seed,
                  Eigen::Isometry3d* correction);
  // Forget the pending evidence (a keyframe in between was not lost, or a new loss began).
  void reset() { pending_count_ = 0; }
  const RelocStats& stats() const { return stats_; }

 private:
  bool agree(const Eigen::Isometry3d& a, const Eigen::Isometry3d& b, const Eigen::Vector3d& at) const;
  Map& map_;
  LoopOptions opt_;  // the loop's matching thresholds with the relocalisation's evidence
  PlaceMatcher matcher_;
  RelocStats stats_;
  std::unique_ptr<BowEntry[]> bow_;
  std::unique_ptr<OrbDescriptor[]> desc_;
  int capacity_ = 0;
  Eigen::Isometry3d pending_ = Eigen::Isometry3d::Identity();
  int pending_count_ = 0;
};

}  // namespace kestrel::core

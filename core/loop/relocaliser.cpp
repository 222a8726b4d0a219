#include "kestrel/core/relocaliser.hpp"

#include <algorithm>
#include <cmath>

namespace kestrel::core {

Relocaliser::Relocaliser(Map& map, const MapCamera& cam, const LoopOptions& opt)
    : map_(map), opt_(opt), matcher_(map, cam) {
  opt_.min_inliers = opt.reloc_min_inliers;
  opt_.min_inlier_share = opt.reloc_min_inlier_share;
  // Lost: the odometry's pose is no seed for where the place is.
  opt_.prior_seed_radius_px = 0;
  capacity_ = map.features_per_keyframe();
  bow_.reset(new BowEntry[static_cast<size_t>(capacity_)]);
  desc_.reset(new OrbDescriptor[static_cast<size_t>(capacity_)]);
}

bool Relocaliser::agree(const Eigen::Isometry3d& a, const Eigen::Isometry3d& b,
                        const Eigen::Vector3d& at) const {
  return (a * at - b * at).norm() < opt_.consistency_m &&
         std::abs(yaw_of(a.linear().transpose() * b.linear())) < opt_.consistency_rad;
}

bool Relocaliser::relocalise(const KeyframeFeature* f, int n, const Eigen::Isometry3d& T_MC_guess,
                             uint64_t seed, Eigen::Isometry3d* correction) {
  const Vocabulary* voc = map_.vocabulary();
  const KeyframeDatabase* db = map_.database();
  if (voc == nullptr || db == nullptr || n <= 0) return false;
  ++stats_.queries;
  n = std::min(n, capacity_);
  for (int j = 0; j < n; ++j) desc_[j] = f[j].desc;
  const int nb = voc->transform(desc_.get(), n, bow_.get());
  KeyframeDatabase::Match cands[32];
  const int nc = db->query(
      bow_.get(), nb, [](int) { return false; }, static_cast<float>(opt_.min_score), 0.8,
      std::min(opt_.reloc_max_candidates, 32), cands);
  stats_.candidates += static_cast<uint64_t>(nc);
  // Every candidate is verified: one that fits another pose than the best
  // makes the place ambiguous.
  const Eigen::Vector3d at = T_MC_guess.translation();
  PlaceFit best, fit;
  Eigen::Isometry3d fits[32];
  int n_fits = 0;
  for (int c = 0; c < nc; ++c) {
    if (matcher_.match(f, n, T_MC_guess, cands[c].keyframe, opt_, seed * 1000003u + static_cast<uint64_t>(c),
                       &fit) != PlaceMatcher::kOk)
      continue;
    if (n_fits == 0 || fit.inliers > best.inliers) best = fit;
    fits[n_fits++] = fit.correction;
  }
  bool ambiguous = false;
  for (int i = 0; i < n_fits; ++i) ambiguous = ambiguous || !agree(fits[i], best.correction, at);
  if (n_fits == 0) {
    pending_count_ = 0;
    return false;
  }
  if (ambiguous) {
    ++stats_.rejected_ambiguous;
    pending_count_ = 0;
    return false;
  }
  ++stats_.verified;
  // The odometry between consecutive lost keyframes is good: the same
  // alignment must explain both.
  if (pending_count_ > 0 && !agree(pending_, best.correction, at)) {
    ++stats_.rejected_consistency;
    pending_count_ = 0;
  }
  pending_ = best.correction;
  if (++pending_count_ < opt_.reloc_consistent_keyframes) return false;
  pending_count_ = 0;
  *correction = best.correction;
  ++stats_.relocalisations;
  return true;
}

}  // namespace kestrel::core

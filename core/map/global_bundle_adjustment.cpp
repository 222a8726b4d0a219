#include "kestrel/core/global_bundle_adjustment.hpp"

#include <algorithm>
#include <sstream>

#include "ba_observation.hpp"

namespace kestrel::core {

std::string GlobalBaOptions::validate() const {
  std::ostringstream e;
  if (max_keyframes < 1) e << "  global_ba_max_keyframes must be >= 1\n";
  if (max_points < 1) e << "  global_ba_max_points must be >= 1\n";
  if (iterations < 1) e << "  global_ba_iterations must be >= 1\n";
  if (!(odometry_sigma_m >= 0) || !(odometry_sigma_rad >= 0))
    e << "  global_ba_odometry_sigma_m and global_ba_odometry_sigma_rad must be >= 0\n";
  if ((odometry_sigma_m > 0) != (odometry_sigma_rad > 0))
    e << "  global_ba_odometry_sigma_m and global_ba_odometry_sigma_rad are both 0 (off) or both > 0\n";
  return e.str();
}

bool GlobalBundleAdjustment::snapshot(const Map& map, const std::vector<GlobalBaLoop>& loops) {
  state_ = State::kIdle;
  ok_ = false;
  const MapOptions& mo = map.options();
  huber_ = mo.ba_huber;
  outlier_chi2_ = mo.ba_outlier_chi2;
  // This flight's keyframes, oldest first; a loaded map's are another
  // flight's frame and stay as they are (held where they observe points).
  std::vector<std::pair<uint32_t, int32_t>> own;
  map.for_each_keyframe([&](int k) {
    if (map.keyframe(k).session == 0) own.emplace_back(map.keyframe(k).id, k);
  });
  if (own.size() < 2) return false;
  std::sort(own.begin(), own.end());
  // The gauge: the oldest keyframe of the flight is held (ORB-SLAM holds its
  // first); gravity holds roll and pitch. Beyond the cap the oldest are held too.
  const size_t n_free = std::min(own.size() - 1, static_cast<size_t>(opt_.max_keyframes));
  slot_pose_.assign(static_cast<size_t>(map.max_keyframes()), -1);
  kfs_.clear();
  pb_.poses.clear();
  auto add_pose = [&](int32_t k, bool fixed) {
    const MapKeyframe& K = map.keyframe(k);
    slot_pose_[static_cast<size_t>(k)] = static_cast<int32_t>(pb_.poses.size());
    kfs_.push_back({k, K.id, K.T_MC});
    const Eigen::Isometry3d T_CM = K.T_MC.inverse();
    BaPose P;
    P.R_CM = T_CM.linear();
    P.t_CM = T_CM.translation();
    P.fixed = fixed;
    P.has_gravity = !fixed;
    P.g_C = K.g_C;
    pb_.poses.push_back(P);
  };
  for (size_t i = own.size() - n_free; i < own.size(); ++i) add_pose(own[i].second, false);

  // Points seen twice or more, one of them by a free keyframe; beyond the cap
  // the most observed (ties: slot order, so a replay gives the same set).
  std::vector<std::pair<int, int32_t>> cand;  // (-observations, slot)
  for (int p = 0; p < map.max_points(); ++p) {
    if (!map.point_used(p)) continue;
    const MapPoint& P = map.point(p);
    if (P.n_obs < 2) continue;
    bool seen_free = false;
    for (int i = 0; i < P.n_obs && !seen_free; ++i)
      seen_free = slot_pose_[static_cast<size_t>(P.obs_kf[i])] >= 0;
    if (seen_free) cand.emplace_back(-P.n_obs, p);
  }
  if (cand.size() > static_cast<size_t>(opt_.max_points)) {
    std::nth_element(cand.begin(), cand.begin() + opt_.max_points, cand.end());
    cand.resize(static_cast<size_t>(opt_.max_points));
    std::sort(cand.begin(), cand.end(), [](const auto& a, const auto& b) { return a.second < b.second; });
  }
  if (cand.empty()) return false;
  pb_.K = cam_.K;
  pb_.huber = huber_;
  pb_.gravity_inv_sigma = mo.ba_gravity_sigma_rad > 0 ? 1.0 / mo.ba_gravity_sigma_rad : 0.0;
  pb_.points_M.clear();
  pb_.obs.clear();
  pts_.clear();
  for (const auto& c : cand) {
    const MapPoint& P = map.point(c.second);
    const int32_t a = static_cast<int32_t>(pb_.points_M.size());
    pb_.points_M.push_back(P.p_M);
    pts_.push_back({c.second, P.landmark_id, P.p_M});
    for (int i = 0; i < P.n_obs; ++i) {
      const int32_t k = P.obs_kf[i];
      if (slot_pose_[static_cast<size_t>(k)] < 0) add_pose(k, true);
      const KeyframeFeature& f = map.feature(k, P.obs_feat[i]);
      pb_.obs.push_back(ba_observation(cam_, f, slot_pose_[static_cast<size_t>(k)], a));
    }
  }
  // The odometry between each keyframe and its parent, where both are in the
  // problem, one is free and T_WC of both comes from one odometry chain.
  pb_.relative.clear();
  if (opt_.odometry_sigma_m > 0) {
    for (size_t i = 0; i < kfs_.size(); ++i) {
      const MapKeyframe& K = map.keyframe(kfs_[i].slot);
      if (K.parent < 0 || slot_pose_[static_cast<size_t>(K.parent)] < 0) continue;
      const MapKeyframe& P = map.keyframe(K.parent);
      const int32_t a = slot_pose_[static_cast<size_t>(K.parent)];
      const int32_t b = static_cast<int32_t>(i);
      if (P.chain != K.chain || P.session != 0 ||
          (pb_.poses[static_cast<size_t>(a)].fixed && pb_.poses[i].fixed))
        continue;
      const Eigen::Isometry3d T_ab = P.T_WC.inverse() * K.T_WC;
      BaRelativePose e;
      e.a = a;
      e.b = b;
      e.R_ab = T_ab.linear();
      e.t_ab = T_ab.translation();
      e.inv_sigma_m = 1.0 / opt_.odometry_sigma_m;
      e.inv_sigma_rad = 1.0 / opt_.odometry_sigma_rad;
      pb_.relative.push_back(e);
    }
  }
  stats_.odometry_factors = pb_.relative.size();
  // The closed loops, where both keyframes are in the problem and one is free.
  size_t n_loop = 0;
  for (const GlobalBaLoop& l : loops) {
    int32_t a = -1, b = -1;
    for (size_t i = 0; i < kfs_.size() && (a < 0 || b < 0); ++i) {
      if (kfs_[i].id == l.id_a) a = static_cast<int32_t>(i);
      if (kfs_[i].id == l.id_b) b = static_cast<int32_t>(i);
    }
    if (a < 0 || b < 0 ||
        (pb_.poses[static_cast<size_t>(a)].fixed && pb_.poses[static_cast<size_t>(b)].fixed))
      continue;
    BaRelativePose e;
    e.a = a;
    e.b = b;
    e.R_ab = l.R_ab;
    e.t_ab = l.t_ab;
    e.inv_sigma_m = 1.0 / std::max(l.sigma_m, 1e-4);
    e.inv_sigma_rad = 1.0 / std::max(l.sigma_rad, 1e-5);
    pb_.relative.push_back(e);
    ++n_loop;
  }
  stats_.loop_factors = n_loop;
  stats_.keyframes = n_free;
  stats_.fixed_keyframes = pb_.poses.size() - n_free;
  stats_.points = pb_.points_M.size();
  stats_.observations = pb_.obs.size();
  state_ = State::kSnapshot;
  return true;
}

bool GlobalBundleAdjustment::solve() {
  if (state_ != State::kSnapshot) return false;
  state_ = State::kSolved;
  ++stats_.runs;
  // Two rounds, as the local BA: what is still far off after the first
  // (a wrong association the loop's merge or the fusing made) is left out.
  const BaResult r1 = solve_bundle_adjustment(pb_, opt_.iterations, scratch_);
  if (!r1.usable) {
    ++stats_.failures;
    return false;
  }
  uint64_t outliers = 0;
  for (BaObservation& ob : pb_.obs) {
    if (ba_chi2(pb_, ob) > outlier_chi2_) {
      ob.enabled = false;
      ++outliers;
    }
  }
  const BaResult r2 = solve_bundle_adjustment(pb_, opt_.iterations, scratch_);
  if (!r2.usable || !(r2.final_cost <= r1.initial_cost)) {
    ++stats_.failures;
    return false;
  }
  stats_.outliers = outliers;
  stats_.initial_cost = r1.initial_cost;
  stats_.final_cost = r2.final_cost;
  ok_ = true;
  return true;
}

bool GlobalBundleAdjustment::apply(Map& map) {
  const bool ok = state_ == State::kSolved && ok_;
  state_ = State::kIdle;
  ok_ = false;
  if (!ok) return false;
  const size_t nk = static_cast<size_t>(map.max_keyframes());
  delta_.assign(nk, Eigen::Isometry3d::Identity());
  moved_.assign(nk, 0);
  double max_move = 0;
  // The snapshot's keyframes: the solve's correction on top of whatever the
  // local BA did meanwhile (T <- delta T, delta = T_solved T_snapshot^-1).
  for (size_t i = 0; i < kfs_.size(); ++i) {
    const KfRef& r = kfs_[i];
    if (!map.keyframe_used(r.slot) || map.keyframe(r.slot).id != r.id) {
      ++stats_.lost_keyframes;
      continue;
    }
    moved_[static_cast<size_t>(r.slot)] = 1;
    if (pb_.poses[i].fixed) continue;
    Eigen::Isometry3d T_CM = Eigen::Isometry3d::Identity();
    T_CM.linear() = Eigen::Quaterniond(pb_.poses[i].R_CM).normalized().toRotationMatrix();
    T_CM.translation() = pb_.poses[i].t_CM;
    const Eigen::Isometry3d T_MC = T_CM.inverse();
    delta_[static_cast<size_t>(r.slot)] = T_MC * r.T_MC.inverse();
    max_move = std::max(max_move, (T_MC.translation() - r.T_MC.translation()).norm());
    MapKeyframe& K = map.keyframe(r.slot);
    K.T_MC = delta_[static_cast<size_t>(r.slot)] * K.T_MC;
  }
  // Keyframes mapped during the solve: their spanning-tree parent's correction.
  map.for_each_keyframe([&](int k) {
    if (moved_[static_cast<size_t>(k)] != 0 || map.keyframe(k).session != 0) return;
    int32_t p = map.keyframe(k).parent;
    for (size_t steps = 0; p >= 0 && moved_[static_cast<size_t>(p)] == 0 && steps < nk; ++steps)
      p = map.keyframe(p).parent;
    if (p < 0 || moved_[static_cast<size_t>(p)] == 0) return;
    delta_[static_cast<size_t>(k)] = delta_[static_cast<size_t>(p)];
    moved_[static_cast<size_t>(k)] = 2;
    MapKeyframe& K = map.keyframe(k);
    K.T_MC = delta_[static_cast<size_t>(k)] * K.T_MC;
    ++stats_.followed_keyframes;
  });
  // Points: the solution where nothing touched them since the snapshot;
  // otherwise, and for points made meanwhile, their first observer's correction.
  point_done_.assign(static_cast<size_t>(map.max_points()), 0);
  for (size_t a = 0; a < pts_.size(); ++a) {
    const PointRef& r = pts_[a];
    if (!map.point_used(r.slot) || map.point(r.slot).landmark_id != r.landmark_id) continue;
    MapPoint& P = map.point(r.slot);
    point_done_[static_cast<size_t>(r.slot)] = 1;
    if (P.p_M == r.p_M) {
      P.p_M = pb_.points_M[a];
    } else if (P.n_obs > 0) {
      P.p_M = delta_[static_cast<size_t>(P.obs_kf[0])] * P.p_M;
    }
  }
  for (int p = 0; p < map.max_points(); ++p) {
    if (!map.point_used(p) || point_done_[static_cast<size_t>(p)] != 0) continue;
    MapPoint& P = map.point(p);
    if (P.n_obs == 0 || moved_[static_cast<size_t>(P.obs_kf[0])] == 0) continue;
    P.p_M = delta_[static_cast<size_t>(P.obs_kf[0])] * P.p_M;
    if (moved_[static_cast<size_t>(P.obs_kf[0])] == 2) ++stats_.followed_points;
  }
  stats_.max_keyframe_move_m = max_move;
  return true;
}

}  // namespace kestrel::core

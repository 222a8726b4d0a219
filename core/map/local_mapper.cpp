#include "kestrel/core/local_mapper.hpp"

#include <algorithm>
#include <cmath>

#include "ba_observation.hpp"

namespace kestrel::core {

double MapCamera::sigma_px(int level) const { return keypoint_sigma_px * std::pow(level_scale, level); }
double MapCamera::sigma_depth_m(double z) const { return std::max(1e-3, depth_sigma_coeff_per_m * z * z); }
Eigen::Vector3d MapCamera::point_C(const KeyframeFeature& f) const {
  return Eigen::Vector3d((f.u_px - K.cx) / K.fx * f.depth_m, (f.v_px - K.cy) / K.fy * f.depth_m, f.depth_m);
}

LocalMapper::LocalMapper(Map& map, const MapCamera& cam) : map_(map), cam_(cam) {
  kf_scratch_.resize(static_cast<size_t>(map.max_keyframes()));
  shared_scratch_.resize(static_cast<size_t>(map.max_keyframes()));
}

double point_sigma_m(const MapCamera& cam, const MapPoint& p, double floor_m) {
  const double z = p.min_depth_m > 0 ? p.min_depth_m : 3.0;
  return std::max(floor_m, cam.sigma_depth_m(z) / std::sqrt(std::max<double>(1, p.n_obs)));
}

double LocalMapper::point_sigma_m(const MapPoint& p) const {
  return core::point_sigma_m(cam_, p, map_.options().point_sigma_floor_m);
}

int LocalMapper::insert(const KeyframePacket& pk, const Eigen::Isometry3d& T_MW, int32_t parent) {
  int kf = map_.add_keyframe(pk.t_ns, T_MW * pk.T_WC, pk.T_WC, pk.features, pk.n, parent);
  if (kf < 0) {
    // Full: cull what the newest keyframe makes redundant, then try once more.
    if (map_.newest_keyframe() >= 0) cull_keyframes(map_.newest_keyframe());
    kf = map_.add_keyframe(pk.t_ns, T_MW * pk.T_WC, pk.T_WC, pk.features, pk.n, parent);
    if (kf < 0) {
      ++stats_.refused_full;
      return -1;
    }
  }
  ++stats_.keyframes;
  map_.keyframe(kf).chain = pk.chain;
  if (uint16_t* grid = map_.depth_grid(kf); grid != nullptr && pk.grid_z_mm != nullptr && pk.grid_n > 0) {
    std::copy(pk.grid_z_mm, pk.grid_z_mm + map_.depth_grid_cells(), grid);
    map_.keyframe(kf).grid_n = pk.grid_n;
  }
  if (have_last_) path_m_ += (pk.T_WC.translation() - last_p_W_).norm();
  have_last_ = true;
  last_p_W_ = pk.T_WC.translation();
  map_.keyframe(kf).path_m = path_m_;
  link_features(kf);
  fuse(kf);
  bundle_adjust(kf);
  cull_points(kf);
  cull_keyframes(kf);
  return kf;
}

void LocalMapper::link_features(int kf) {
  MapKeyframe& K = map_.keyframe(kf);
  for (int j = 0; j < K.n; ++j) {
    const KeyframeFeature& f = map_.feature(kf, j);
    if (f.landmark_id == 0) continue;
    const int p = map_.find_point(f.landmark_id);
    if (p >= 0) {
      if (map_.add_observation(p, kf, j)) {
        ++map_.point(p).visible;
        ++map_.point(p).found;
      }
      continue;
    }
    if (f.depth_m <= 0) continue;
    const Eigen::Vector3d p_C = cam_.point_C(f);
    const int q = map_.add_point(f.landmark_id, K.T_MC * p_C, f.desc, f.level, kf, j);
    if (q >= 0) {
      ++stats_.points_created;
      map_.point(q).visible = map_.point(q).found = 1;
    }
  }
}

void LocalMapper::fuse(int kf) {
  // The neighbourhood: covisible keyframes and those near in space looking
  // the same way (a place seen again after the tracker lost its ids).
  std::vector<int32_t>& set = pt_scratch_;
  set.resize(static_cast<size_t>(3 * map_.options().ba_keyframes + 8));
  set.resize(static_cast<size_t>(neighbourhood(kf, static_cast<int>(set.size()), set.data())));
  if (!set.empty()) set.erase(set.begin());  // kf itself
  int n = 0;
  const MapKeyframe& K = map_.keyframe(kf);
  const Eigen::Isometry3d T_CM = K.T_MC.inverse();
  const uint64_t pt_mark = map_.next_mark();
  for (int j = 0; j < K.n; ++j) {
    const int32_t p = map_.point_of(kf, j);
    if (p >= 0) map_.point(p).mark = pt_mark;
  }
  // The search radius per pyramid level, once: pow() in the inner loop was
  // a tenth of the mapping thread.
  constexpr int kLevels = 32;
  double radius_px[kLevels];
  for (int l = 0; l < kLevels; ++l)
    radius_px[l] = map_.options().fuse_radius_px * std::pow(cam_.level_scale, l);
  for (const int32_t k : set) {
    const MapKeyframe& N = map_.keyframe(k);
    for (int jj = 0; jj < N.n; ++jj) {
      const int32_t p = map_.point_of(k, jj);
      if (p < 0 || map_.point(p).mark == pt_mark) continue;
      MapPoint& P = map_.point(p);
      P.mark = pt_mark;
      const Eigen::Vector3d c = T_CM * P.p_M;
      if (c.z() < 0.1) continue;
      const double u = cam_.K.fx * c.x() / c.z() + cam_.K.cx, v = cam_.K.fy * c.y() / c.z() + cam_.K.cy;
      if (u < 0 || v < 0 || u >= cam_.width || v >= cam_.height) continue;
      ++P.visible;
      int best = 1 << 30, best_j = -1;
      for (int j = 0; j < K.n; ++j) {
        const KeyframeFeature& f = map_.feature(kf, j);
        if (std::abs(f.level - P.level) > 1) continue;
        const double r = radius_px[std::clamp<int>(f.level, 0, kLevels - 1)];
        const double du = f.u_px - u, dv = f.v_px - v;
        if (du * du + dv * dv > r * r) continue;
        if (f.depth_m > 0 && std::abs(f.depth_m - c.z()) > map_.options().fuse_depth_tol_rel * c.z() + 0.03)
          continue;
        const int d = hamming_distance(P.desc, f.desc);
        if (d < best) {
          best = d;
          best_j = j;
        }
      }
      if (best_j < 0 || best > map_.options().fuse_max_hamming) continue;
      const int32_t q = map_.point_of(kf, best_j);
      if (q < 0) {
        if (map_.add_observation(p, kf, best_j)) {
          ++P.found;
          ++stats_.observations_added;
          ++n;
        }
      } else if (q != p) {
        // Two points for one feature: the better observed one stays.
        const bool keep_q = map_.point(q).n_obs >= P.n_obs;
        map_.merge_point(keep_q ? p : q, keep_q ? q : p);
        (keep_q ? map_.point(q) : map_.point(p)).mark = pt_mark;
        ++stats_.points_fused;
      }
    }
  }
  (void)n;
}

bool LocalMapper::bundle_adjust(int kf) {
  if (!map_.keyframe_used(kf)) return false;
  const MapOptions& o = map_.options();
  // Local keyframes: the new one and its most covisible neighbours.
  std::vector<int32_t> local(1, kf);
  {
    const int m = map_.covisible(kf, 1, o.ba_keyframes, kf_scratch_.data(), nullptr);
    local.insert(local.end(), kf_scratch_.begin(), kf_scratch_.begin() + m);
  }
  const uint64_t local_mark = map_.next_mark();
  for (const int32_t k : local) map_.keyframe(k).mark = local_mark;
  // Their points, and the other keyframes that see them (held fixed).
  std::vector<int32_t> points;
  const uint64_t pt_mark = map_.next_mark();
  const uint64_t fixed_mark = map_.next_mark();
  std::vector<int32_t> fixed_cand;
  for (const int32_t k : local) {
    const MapKeyframe& K = map_.keyframe(k);
    for (int j = 0; j < K.n; ++j) {
      const int32_t p = map_.point_of(k, j);
      if (p < 0 || map_.point(p).mark == pt_mark) continue;
      map_.point(p).mark = pt_mark;
      points.push_back(p);
      const MapPoint& P = map_.point(p);
      for (int i = 0; i < P.n_obs; ++i) {
        MapKeyframe& F = map_.keyframe(P.obs_kf[i]);
        if (F.mark == local_mark) continue;
        if (F.mark2 != fixed_mark) {
          F.mark2 = fixed_mark;
          shared_scratch_[P.obs_kf[i]] = 0;
          fixed_cand.push_back(P.obs_kf[i]);
        }
        ++shared_scratch_[P.obs_kf[i]];
      }
    }
  }
  std::sort(fixed_cand.begin(), fixed_cand.end(),
            [&](int32_t a, int32_t b) { return shared_scratch_[a] > shared_scratch_[b]; });
  if (static_cast<int>(fixed_cand.size()) > o.ba_fixed_keyframes) fixed_cand.resize(o.ba_fixed_keyframes);
  const uint64_t in_mark = map_.next_mark();
  for (const int32_t k : local) map_.keyframe(k).mark2 = in_mark;
  for (const int32_t k : fixed_cand) map_.keyframe(k).mark2 = in_mark;
  if (points.empty()) return false;

  // The problem: local keyframes free (the gravity prior on each), the others
  // fixed, every observation of the points by any of them.
  BaProblem& pb = ba_;
  pb.K = cam_.K;
  pb.huber = o.ba_huber;
  pb.gravity_inv_sigma = o.ba_gravity_sigma_rad > 0 ? 1.0 / o.ba_gravity_sigma_rad : 0.0;
  const size_t nk = local.size() + fixed_cand.size();
  pb.poses.resize(nk);
  ba_kf_.resize(nk);
  for (size_t i = 0; i < nk; ++i) {
    const int32_t k = i < local.size() ? local[i] : fixed_cand[i - local.size()];
    ba_kf_[i] = k;
    shared_scratch_[static_cast<size_t>(k)] = static_cast<int32_t>(i);  // the counts are spent
    const Eigen::Isometry3d T_CM = map_.keyframe(k).T_MC.inverse();
    BaPose& P = pb.poses[i];
    P.R_CM = T_CM.linear();
    P.t_CM = T_CM.translation();
    P.fixed = i >= local.size();
    P.has_gravity = !P.fixed;
    P.g_C = map_.keyframe(k).g_C;
  }
  // Gauge: without fixed keyframes the oldest local one holds the frame.
  if (fixed_cand.empty()) {
    if (local.size() < 2) return false;
    size_t oldest = 0;
    for (size_t i = 1; i < local.size(); ++i)
      if (map_.keyframe(local[i]).id < map_.keyframe(local[oldest]).id) oldest = i;
    pb.poses[oldest].fixed = true;
  }
  pb.points_M.resize(points.size());
  pb.obs.clear();
  for (size_t a = 0; a < points.size(); ++a) {
    const MapPoint& P = map_.point(points[a]);
    pb.points_M[a] = P.p_M;
    for (int i = 0; i < P.n_obs; ++i) {
      if (map_.keyframe(P.obs_kf[i]).mark2 != in_mark) continue;
      const KeyframeFeature& f = map_.feature(P.obs_kf[i], P.obs_feat[i]);
      pb.obs.push_back(ba_observation(cam_, f, shared_scratch_[static_cast<size_t>(P.obs_kf[i])],
                                      static_cast<int32_t>(a)));
    }
  }
  ++stats_.ba_runs;
  // Two rounds: observations still far off after the first are left out of the second.
  for (int round = 0; round < 2; ++round) {
    const BaResult r = o.ba_solver == MapOptions::BaSolver::kCeres
                           ? solve_bundle_adjustment_ceres(pb, o.ba_iterations)
                           : solve_bundle_adjustment(pb, o.ba_iterations, ba_scratch_);
    if (!r.usable) {
      ++stats_.ba_failures;
      return false;
    }
    if (round == 0) {
      for (BaObservation& ob : pb.obs)
        if (ba_chi2(pb, ob) > o.ba_outlier_chi2) ob.enabled = false;
    }
  }
  for (size_t i = 0; i < local.size(); ++i) {
    Eigen::Isometry3d T_CM = Eigen::Isometry3d::Identity();
    T_CM.linear() = Eigen::Quaterniond(pb.poses[i].R_CM).normalized().toRotationMatrix();
    T_CM.translation() = pb.poses[i].t_CM;
    map_.keyframe(local[i]).T_MC = T_CM.inverse();
  }
  for (size_t a = 0; a < points.size(); ++a) map_.point(points[a]).p_M = pb.points_M[a];
  for (size_t r = 0; r < pb.obs.size(); ++r) {
    const BaObservation& ob = pb.obs[r];
    if (ob.enabled && ba_chi2(pb, ob) <= o.ba_outlier_chi2) continue;
    const int32_t p = points[static_cast<size_t>(ob.point)];
    if (!map_.point_used(p)) continue;
    map_.erase_observation(p, ba_kf_[static_cast<size_t>(ob.pose)]);
    ++stats_.ba_outliers;
  }
  return true;
}

void LocalMapper::cull_points(int kf) {
  const MapOptions& o = map_.options();
  const uint32_t now = map_.keyframe(kf).id;
  // Points made by the last few keyframes are judged once they are 3 keyframes old.
  const int n = map_.covisible(kf, 1, o.ba_keyframes, kf_scratch_.data(), nullptr);
  kf_scratch_[n] = kf;
  const uint64_t mark = map_.next_mark();
  for (int i = 0; i <= n; ++i) {
    const int k = kf_scratch_[i];
    const MapKeyframe& K = map_.keyframe(k);
    for (int j = 0; j < K.n; ++j) {
      const int32_t p = map_.point_of(k, j);
      if (p < 0) continue;
      MapPoint& P = map_.point(p);
      if (P.mark == mark) continue;
      P.mark = mark;
      const uint32_t age = now - P.first_kf_id;
      if (age < 3) continue;
      const bool rare = P.n_obs < o.cull_point_min_keyframes;
      const bool missed =
          P.visible >= 4 && static_cast<double>(P.found) < o.cull_point_min_found_ratio * P.visible;
      if (rare || missed) {
        map_.erase_point(p);
        ++stats_.points_culled;
      }
    }
  }
}

void LocalMapper::cull_keyframes(int kf) {
  // ORB-SLAM's rule: a keyframe whose points are, for the given share, seen
  // by at least three other keyframes adds nothing. The newest keyframe and
  // the map's first stay.
  const MapOptions& o = map_.options();
  const int n = map_.covisible(kf, 1, 2 * o.ba_keyframes, kf_scratch_.data(), nullptr);
  std::vector<int32_t> cand(kf_scratch_.begin(), kf_scratch_.begin() + n);
  for (const int32_t k : cand) {
    if (!map_.keyframe_used(k) || k == kf || map_.keyframe(k).parent < 0) continue;
    const MapKeyframe& K = map_.keyframe(k);
    int n_pts = 0, n_redundant = 0;
    for (int j = 0; j < K.n; ++j) {
      const int32_t p = map_.point_of(k, j);
      if (p < 0) continue;
      ++n_pts;
      const MapPoint& P = map_.point(p);
      const int level = K.n > 0 ? map_.feature(k, j).level : 0;
      int seen = 0;
      for (int i = 0; i < P.n_obs && seen < 3; ++i) {
        if (P.obs_kf[i] == k) continue;
        // Seen at the same or a finer scale there.
        if (map_.feature(P.obs_kf[i], P.obs_feat[i]).level <= level + 1) ++seen;
      }
      if (seen >= 3) ++n_redundant;
    }
    if (n_pts > 0 && n_redundant > o.cull_keyframe_redundancy * n_pts) {
      map_.erase_keyframe(k);
      ++stats_.keyframes_culled;
    }
  }
}

int LocalMapper::neighbourhood(int kf, int max, int32_t* out) {
  const MapOptions& o = map_.options();
  if (!map_.keyframe_used(kf) || max <= 0) return 0;
  int n = 0;
  out[n++] = kf;
  const uint64_t mark = map_.next_mark();
  map_.keyframe(kf).mark = mark;
  const int m = map_.covisible(kf, 1, std::min(max - 1, 2 * o.ba_keyframes), kf_scratch_.data(), nullptr);
  for (int i = 0; i < m && n < max; ++i) {
    out[n++] = kf_scratch_[i];
    map_.keyframe(kf_scratch_[i]).mark = mark;
  }
  // Near in space and looking the same way: what the vehicle sees again
  // after a while away (not covisible yet: nothing links them).
  const MapKeyframe& K = map_.keyframe(kf);
  const Eigen::Vector3d c = K.T_MC.translation(), axis = K.T_MC.linear().col(2);
  const double cos_max = std::cos(o.neighbour_max_angle_rad);
  struct Near {
    double d;
    int32_t k;
  };
  std::vector<Near> near;
  map_.for_each_keyframe([&](int k) {
    const MapKeyframe& N = map_.keyframe(k);
    if (N.mark == mark) return;
    const double d = (N.T_MC.translation() - c).norm();
    if (d > o.neighbour_radius_m || N.T_MC.linear().col(2).dot(axis) < cos_max) return;
    near.push_back({d, k});
  });
  std::sort(near.begin(), near.end(), [](const Near& a, const Near& b) { return a.d < b.d; });
  for (const Near& x : near) {
    if (n >= max) break;
    out[n++] = x.k;
  }
  return n;
}

int LocalMapper::export_points(int kf, const Eigen::Isometry3d& T_WM, MapPointUpdate* out, int capacity) {
  const MapOptions& o = map_.options();
  std::vector<int32_t> nb(static_cast<size_t>(std::max(1, 3 * o.ba_keyframes + 8)));
  const int m = neighbourhood(kf, static_cast<int>(nb.size()), nb.data());
  const uint64_t mark = map_.next_mark();
  int n = 0;
  for (int i = 0; i < m && n < capacity; ++i) {
    const MapKeyframe& K = map_.keyframe(nb[i]);
    for (int j = 0; j < K.n && n < capacity; ++j) {
      const int32_t p = map_.point_of(nb[i], j);
      if (p < 0) continue;
      MapPoint& P = map_.point(p);
      if (P.mark == mark || P.n_obs < o.point_min_keyframes_for_prior) continue;
      P.mark = mark;
      MapPointUpdate& u = out[n++];
      u.landmark_id = P.landmark_id;
      u.level = P.level;
      u.desc = P.desc;
      u.p_W = T_WM * P.p_M;
      u.sigma_m = static_cast<float>(point_sigma_m(P));
    }
  }
  return n;
}

}  // namespace kestrel::core

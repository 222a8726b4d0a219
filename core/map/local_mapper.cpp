#include "kestrel/core/local_mapper.hpp"

#include <ceres/ceres.h>

#include <algorithm>
#include <cmath>

namespace kestrel::core {

double MapCamera::sigma_px(int level) const { return keypoint_sigma_px * std::pow(level_scale, level); }
double MapCamera::sigma_depth_m(double z) const { return std::max(1e-3, depth_sigma_coeff_per_m * z * z); }
Eigen::Vector3d MapCamera::point_C(const KeyframeFeature& f) const {
  return Eigen::Vector3d((f.u_px - K.cx) / K.fx * f.depth_m, (f.v_px - K.cy) / K.fy * f.depth_m, f.depth_m);
}

namespace {

// One observation: reprojection (undistorted pixels) and, with a depth, the
// camera-frame z; whitened. Pose block: q_CM (x, y, z, w) and t_CM, so that
// p_C = R_CM p_M + t_CM.
template <int kRows>
struct ObservationCost {
  ObservationCost(const PinholeK& K, double u, double v, double z, double inv_sigma_px, double inv_sigma_z)
      : K_(K), u_(u), v_(v), z_(z), isp_(inv_sigma_px), isz_(inv_sigma_z) {}
  template <typename T>
  bool operator()(const T* q, const T* t, const T* p, T* r) const {
    const Eigen::Quaternion<T> Q(q[3], q[0], q[1], q[2]);
    const Eigen::Matrix<T, 3, 1> P(p[0], p[1], p[2]);
    const Eigen::Matrix<T, 3, 1> c = Q * P + Eigen::Matrix<T, 3, 1>(t[0], t[1], t[2]);
    const T z = c.z() < T(1e-3) ? T(1e-3) : c.z();
    r[0] = (T(K_.fx) * c.x() / z + T(K_.cx) - T(u_)) * T(isp_);
    r[1] = (T(K_.fy) * c.y() / z + T(K_.cy) - T(v_)) * T(isp_);
    if (kRows == 3) r[2] = (c.z() - T(z_)) * T(isz_);
    return true;
  }
  PinholeK K_;
  double u_, v_, z_, isp_, isz_;
};

// Roll and pitch from the odometry: R_CM's view of M's down axis against the
// gravity direction the odometry had in C, whitened.
struct GravityCost {
  GravityCost(const Eigen::Vector3d& g_C, double inv_sigma) : g_(g_C), is_(inv_sigma) {}
  template <typename T>
  bool operator()(const T* q, T* r) const {
    const Eigen::Quaternion<T> Q(q[3], q[0], q[1], q[2]);
    const Eigen::Matrix<T, 3, 1> d = Q * Eigen::Matrix<T, 3, 1>(T(0), T(0), T(-1));
    for (int i = 0; i < 3; ++i) r[i] = (d[i] - T(g_[i])) * T(is_);
    return true;
  }
  Eigen::Vector3d g_;
  double is_;
};

// Whitened squared error of an observation at the current estimates.
double observation_chi2(const MapCamera& cam, const Eigen::Isometry3d& T_CM, const Eigen::Vector3d& p_M,
                        const KeyframeFeature& f) {
  const Eigen::Vector3d c = T_CM * p_M;
  if (c.z() < 1e-3) return 1e30;
  const double isp = 1.0 / cam.sigma_px(f.level);
  const double eu = (cam.K.fx * c.x() / c.z() + cam.K.cx - f.u_px) * isp;
  const double ev = (cam.K.fy * c.y() / c.z() + cam.K.cy - f.v_px) * isp;
  double e = eu * eu + ev * ev;
  if (f.depth_m > 0) {
    const double ez = (c.z() - f.depth_m) / cam.sigma_depth_m(f.depth_m);
    e += ez * ez;
  }
  return e;
}

}  // namespace

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
        const double r = map_.options().fuse_radius_px * std::pow(cam_.level_scale, f.level);
        const double du = f.u_px - u, dv = f.v_px - v;
        if (du * du + dv * dv > r * r) continue;
        if (f.depth_m > 0 && std::abs(f.depth_m - c.z()) > map_.options().fuse_depth_tol_rel * c.z() + 0.03) continue;
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

  // Parameters: T_CM per keyframe as (q x y z w, t), points in M.
  const size_t nk = local.size() + fixed_cand.size();
  std::vector<std::array<double, 7>> pose(nk);
  std::vector<int32_t> kf_of(nk);
  auto slot_pose = [&](int32_t k) -> double* {
    for (size_t i = 0; i < nk; ++i)
      if (kf_of[i] == k) return pose[i].data();
    return nullptr;
  };
  ceres::Problem::Options po;
  po.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  po.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(po);
  ceres::EigenQuaternionManifold qm;
  ceres::HuberLoss huber(o.ba_huber);
  for (size_t i = 0; i < nk; ++i) {
    kf_of[i] = i < local.size() ? local[i] : fixed_cand[i - local.size()];
    const Eigen::Isometry3d T_CM = map_.keyframe(kf_of[i]).T_MC.inverse();
    const Eigen::Quaterniond q(T_CM.linear());
    pose[i] = {q.x(), q.y(), q.z(), q.w(), T_CM.translation().x(), T_CM.translation().y(), T_CM.translation().z()};
    problem.AddParameterBlock(pose[i].data(), 4, &qm);
    problem.AddParameterBlock(pose[i].data() + 4, 3);
  }
  // Gauge: without fixed keyframes the oldest local one holds the frame.
  if (fixed_cand.empty()) {
    if (local.size() < 2) return false;
    size_t oldest = 0;
    for (size_t i = 1; i < local.size(); ++i)
      if (map_.keyframe(local[i]).id < map_.keyframe(local[oldest]).id) oldest = i;
    problem.SetParameterBlockConstant(pose[oldest].data());
    problem.SetParameterBlockConstant(pose[oldest].data() + 4);
  }
  if (o.ba_gravity_sigma_rad > 0)
    for (size_t i = 0; i < local.size(); ++i)
      problem.AddResidualBlock(new ceres::AutoDiffCostFunction<GravityCost, 3, 4>(
                                   new GravityCost(map_.keyframe(local[i]).g_C, 1.0 / o.ba_gravity_sigma_rad)),
                               nullptr, pose[i].data());
  for (size_t i = local.size(); i < nk; ++i) {
    problem.SetParameterBlockConstant(pose[i].data());
    problem.SetParameterBlockConstant(pose[i].data() + 4);
  }
  std::vector<std::array<double, 3>> pt(points.size());
  struct Res {
    ceres::ResidualBlockId id;
    int32_t p, kf;
    int16_t feat;
    size_t a;  // index into points / pt
  };
  std::vector<Res> res;
  for (size_t a = 0; a < points.size(); ++a) {
    const MapPoint& P = map_.point(points[a]);
    pt[a] = {P.p_M.x(), P.p_M.y(), P.p_M.z()};
    for (int i = 0; i < P.n_obs; ++i) {
      const int32_t k = P.obs_kf[i];
      if (map_.keyframe(k).mark2 != in_mark) continue;
      double* q = slot_pose(k);
      const KeyframeFeature& f = map_.feature(k, P.obs_feat[i]);
      const double isp = 1.0 / cam_.sigma_px(f.level);
      ceres::CostFunction* cf;
      if (f.depth_m > 0) {
        cf = new ceres::AutoDiffCostFunction<ObservationCost<3>, 3, 4, 3, 3>(new ObservationCost<3>(
            cam_.K, f.u_px, f.v_px, f.depth_m, isp, 1.0 / cam_.sigma_depth_m(f.depth_m)));
      } else {
        cf = new ceres::AutoDiffCostFunction<ObservationCost<2>, 2, 4, 3, 3>(
            new ObservationCost<2>(cam_.K, f.u_px, f.v_px, 0.0, isp, 0.0));
      }
      res.push_back({problem.AddResidualBlock(cf, &huber, q, q + 4, pt[a].data()), points[a], k, P.obs_feat[i], a});
    }
  }
  ceres::Solver::Options so;
  so.linear_solver_type = ceres::DENSE_SCHUR;
  so.max_num_iterations = o.ba_iterations;
  so.num_threads = 1;
  so.logging_type = ceres::SILENT;
  ceres::Solver::Summary sum;
  ++stats_.ba_runs;
  auto chi2_of = [&](const Res& r) {
    const double* q = slot_pose(r.kf);
    Eigen::Isometry3d T_CM = Eigen::Isometry3d::Identity();
    T_CM.linear() = Eigen::Quaterniond(q[3], q[0], q[1], q[2]).normalized().toRotationMatrix();
    T_CM.translation() = Eigen::Vector3d(q[4], q[5], q[6]);
    return observation_chi2(cam_, T_CM, Eigen::Vector3d(pt[r.a].data()), map_.feature(r.kf, r.feat));
  };
  for (int round = 0; round < 2; ++round) {
    ceres::Solve(so, &problem, &sum);
    if (!sum.IsSolutionUsable()) {
      ++stats_.ba_failures;
      return false;
    }
    if (round == 0) {
      for (size_t r = 0; r < res.size(); ++r) {
        if (res[r].id != nullptr && chi2_of(res[r]) > o.ba_outlier_chi2) {
          problem.RemoveResidualBlock(res[r].id);
          res[r].id = nullptr;
        }
      }
    }
  }
  for (size_t i = 0; i < local.size(); ++i) {
    Eigen::Isometry3d T_CM = Eigen::Isometry3d::Identity();
    T_CM.linear() = Eigen::Quaterniond(pose[i][3], pose[i][0], pose[i][1], pose[i][2]).normalized().toRotationMatrix();
    T_CM.translation() = Eigen::Vector3d(pose[i][4], pose[i][5], pose[i][6]);
    map_.keyframe(local[i]).T_MC = T_CM.inverse();
  }
  for (size_t a = 0; a < points.size(); ++a) map_.point(points[a]).p_M = Eigen::Vector3d(pt[a].data());
  for (size_t r = 0; r < res.size(); ++r) {
    if (res[r].id != nullptr && chi2_of(res[r]) <= o.ba_outlier_chi2) continue;
    if (!map_.point_used(res[r].p)) continue;
    map_.erase_observation(res[r].p, res[r].kf);
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
      const bool missed = P.visible >= 4 && static_cast<double>(P.found) < o.cull_point_min_found_ratio * P.visible;
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

#include "kestrel/core/loop_closer.hpp"

#include <ceres/ceres.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <random>
#include <sstream>
#include <unordered_map>

#include "kestrel/core/pose_graph.hpp"
#include "kestrel/core/vocabulary.hpp"

namespace kestrel::core {

std::string LoopOptions::validate() const {
  std::ostringstream e;
  if (min_age_s < 0) e << "  loop_min_age_s must be >= 0\n";
  if (connected_min_shared < 1) e << "  loop_connected_min_shared must be >= 1\n";
  if (max_candidates < 1) e << "  loop_max_candidates must be >= 1\n";
  if (min_inliers < 3) e << "  loop_min_inliers must be >= 3\n";
  if (!(min_inlier_share >= 0 && min_inlier_share <= 1)) e << "  loop_min_inlier_share must be in [0, 1]\n";
  if (ransac_iterations < 1) e << "  loop_ransac_iterations must be >= 1\n";
  if (min_seed_inliers < 3) e << "  loop_min_seed_inliers must be >= 3\n";
  if (!(prior_seed_radius_px >= 0)) e << "  loop_prior_seed_radius_px must be >= 0\n";
  if (geometric_candidates < 0) e << "  loop_geometric_candidates must be >= 0\n";
  if (!(geometric_min_overlap > 0 && geometric_min_overlap <= 1))
    e << "  loop_geometric_min_overlap must be in (0, 1]\n";
  if (!(geometric_max_range_m > 0)) e << "  loop_geometric_max_range_m must be > 0\n";
  if (!(guided_radius_px >= 0)) e << "  loop_guided_radius_px must be >= 0\n";
  if (!(min_out_of_plane_m >= 0)) e << "  loop_min_out_of_plane_m must be >= 0\n";
  if (!(min_correction_chi2 >= 0)) e << "  loop_min_correction_chi2 must be >= 0\n";
  if (!(inlier_m > 0)) e << "  loop_inlier_m must be > 0\n";
  if (!(refine_chi2 >= 0)) e << "  loop_refine_chi2 must be >= 0\n";
  if (consistent_keyframes < 1) e << "  loop_consistent_keyframes must be >= 1\n";
  if (!(max_correction_m >= 0)) e << "  loop_max_correction_m must be >= 0\n";
  if (!(max_correction_per_m >= 0)) e << "  loop_max_correction_per_m must be >= 0\n";
  if (!(max_yaw_rad >= 0)) e << "  loop_max_yaw_rad must be >= 0\n";
  if (!(max_yaw_per_m >= 0)) e << "  loop_max_yaw_per_m must be >= 0\n";
  if (pose_graph_iterations < 1) e << "  loop_pose_graph_iterations must be >= 1\n";
  const SurfaceAlignOptions& so = surface;
  if (so.iterations < 1) e << "  loop_surface_iterations must be >= 1\n";
  if (!(so.min_pair_m > 0 && so.max_pair_m >= so.min_pair_m))
    e << "  loop_surface_min_pair_m must be > 0 and <= loop_surface_max_pair_m\n";
  if (!(so.max_normal_angle_rad > 0 && so.max_normal_angle_rad <= 3.15))
    e << "  loop_surface_max_normal_angle_rad must be in (0, pi]\n";
  if (!(so.normal_max_step_rel > 0)) e << "  loop_surface_normal_max_step_rel must be > 0\n";
  if (!(so.inlier_floor_m >= 0)) e << "  loop_surface_inlier_floor_m must be >= 0\n";
  if (!(so.min_overlap > 0 && so.min_overlap <= 1)) e << "  loop_surface_min_overlap must be in (0, 1]\n";
  if (!(so.min_inlier_share >= 0 && so.min_inlier_share <= 1))
    e << "  loop_surface_min_inlier_share must be in [0, 1]\n";
  if (!(so.min_observability >= 0)) e << "  loop_surface_min_observability must be >= 0\n";
  if (so.independent_pairs < 1) e << "  loop_surface_independent_pairs must be >= 1\n";
  if (so.neighbours < 0 || so.neighbours >= SurfaceAligner::kMaxViews)
    e << "  loop_surface_neighbours must be in [0, " << SurfaceAligner::kMaxViews - 1 << "]\n";
  if (reloc_max_candidates < 1) e << "  reloc_max_candidates must be >= 1\n";
  if (reloc_min_inliers < 3) e << "  reloc_min_inliers must be >= 3\n";
  if (!(reloc_min_inlier_share >= 0 && reloc_min_inlier_share <= 1))
    e << "  reloc_min_inlier_share must be in [0, 1]\n";
  if (reloc_consistent_keyframes < 1) e << "  reloc_consistent_keyframes must be >= 1\n";
  if (!(reloc_timeout_s >= 0)) e << "  reloc_timeout_s must be >= 0\n";
  return e.str();
}

double yaw_of(const Eigen::Matrix3d& R) { return std::atan2(R(1, 0), R(0, 0)); }

namespace {

// A verified loop edge is stiffer than the odometry's chain: the chain's
// edges carry the drift the loop corrects, and over tens of keyframes their
// sum would otherwise hold the loop back (a 1 cm chain edge x 36 keyframes is
// 6 cm of slack against the loop's 2 mm). A floor under the refit's own
// covariance, which sees the pixels' and depths' noise but not the error the
// candidate place's keyframes share.
constexpr double kLoopSigma_m = 0.002, kLoopSigma_rad = 0.0005;

// 4-DoF least squares of p = Rz(yaw) q + t over the index set (closed form:
// centroids, then the yaw of the centred xy cross-covariance).
Eigen::Isometry3d fit_4dof(const std::vector<Eigen::Vector3d>& q, const std::vector<Eigen::Vector3d>& p,
                           const std::vector<int>& idx) {
  Eigen::Vector3d qm = Eigen::Vector3d::Zero(), pm = Eigen::Vector3d::Zero();
  for (int i : idx) {
    qm += q[i];
    pm += p[i];
  }
  qm /= static_cast<double>(idx.size());
  pm /= static_cast<double>(idx.size());
  double s_cross = 0, s_dot = 0;
  for (int i : idx) {
    const Eigen::Vector3d a = q[i] - qm, b = p[i] - pm;
    s_cross += a.x() * b.y() - a.y() * b.x();
    s_dot += a.x() * b.x() + a.y() * b.y();
  }
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = rot_z(std::atan2(s_cross, s_dot));
  T.translation() = pm - T.linear() * qm;
  return T;
}

}  // namespace

LoopCloser::LoopCloser(Map& map, const MapCamera& cam, const LoopOptions& opt)
    : map_(map), cam_(cam), opt_(opt), matcher_(map, cam) {
  const std::string err = opt.validate();
  if (!err.empty()) throw std::invalid_argument("LoopOptions:\n" + err);
  kf_scratch_.resize(static_cast<size_t>(map.max_keyframes()));
  shared_scratch_.resize(static_cast<size_t>(map.max_keyframes()));
}

void LoopCloser::set_depth_grid(const DepthGridShape& shape) {
  aligner_.set_shape(shape, cam_.depth_sigma_coeff_per_m);
}

bool LoopCloser::detect(int kf, LoopMatch* out) {
  const KeyframeDatabase* db = map_.database();
  if (db == nullptr || !map_.keyframe_used(kf)) return false;
  MapKeyframe& K = map_.keyframe(kf);
  if (K.n_bow == 0) return false;
  // The keyframe's connected neighbours are not loops; the lowest score among
  // its closest neighbours sharing at least 15 points (ORB-SLAM's
  // covisibility edge) says how alike "the same place" looks here.
  // connected_min_shared > 1 keeps a revisit that fusing linked by a point or
  // two per keyframe a candidate (docs/map.md, "Weakly linked revisits": it
  // closes such loops, and on two Vicon flights also bad ones, so it is off).
  const int nc = map_.covisible(kf, opt_.connected_min_shared, map_.max_keyframes(), kf_scratch_.data(),
                                shared_scratch_.data());
  const uint64_t mark = map_.next_mark();
  K.mark = mark;
  double min_covis = 1.0;
  int n_scored = 0;
  for (int i = 0; i < nc; ++i) {
    MapKeyframe& N = map_.keyframe(kf_scratch_[i]);
    N.mark = mark;
    if (n_scored < 10 && shared_scratch_[i] >= 15) {
      min_covis = std::min(min_covis, bow_score(map_.bow(kf), K.n_bow, map_.bow(kf_scratch_[i]), N.n_bow));
      ++n_scored;
    }
  }
  const double min_score = std::max(opt_.min_score, n_scored > 0 ? 0.7 * min_covis : opt_.min_score);
  const int64_t min_age_ns = static_cast<int64_t>(opt_.min_age_s * 1e9);
  const auto skip = [&](int k) {
    const MapKeyframe& C = map_.keyframe(k);
    return C.mark == mark || K.t_ns - C.t_ns < min_age_ns;
  };
  KeyframeDatabase::Match cands[32];
  int n = db->query(map_.bow(kf), K.n_bow, skip, static_cast<float>(min_score), 0.8,
                    std::min(opt_.max_candidates, 16), cands);
  const int n_bow = n;
  if (opt_.geometric_candidates > 0) {
    int32_t geo[16];
    float share[16];
    const auto skip_geo = [&](int k) {
      if (skip(k)) return true;
      for (int c = 0; c < n_bow; ++c)
        if (cands[c].keyframe == k) return true;
      return false;
    };
    const int ng = geometric_candidates(kf, skip_geo, std::min(opt_.geometric_candidates, 16), geo, share);
    for (int g = 0; g < ng; ++g) {
      const MapKeyframe& C = map_.keyframe(geo[g]);
      cands[n].keyframe = geo[g];
      cands[n].score = static_cast<float>(bow_score(map_.bow(kf), K.n_bow, map_.bow(geo[g]), C.n_bow));
      ++n;
    }
    stats_.geometric_candidates += static_cast<uint64_t>(ng);
  }
  stats_.candidates += static_cast<uint64_t>(n);
  bool found = false;
  chosen_record_ = -1;
  for (int c = 0; c < n; ++c) {
    LoopMatch m;
    if (!verify(kf, cands[c].keyframe, cands[c].score, c >= n_bow, &m)) continue;
    if (!found || m.inliers > out->inliers) {
      *out = std::move(m);
      if (logging_) chosen_record_ = static_cast<int64_t>(log_.candidates.size()) - 1;
    }
    found = true;
  }
  if (chosen_record_ >= 0) log_.candidates[static_cast<size_t>(chosen_record_)].chosen = true;
  if (found) ++stats_.verified;
  return found;
}

PlaceMatcher::PlaceMatcher(Map& map, const MapCamera& cam) : map_(map), cam_(cam) {
  kf_scratch_.resize(static_cast<size_t>(map.max_keyframes()));
  shared_scratch_.resize(static_cast<size_t>(map.max_keyframes()));
}

PlaceMatcher::Result PlaceMatcher::match(const KeyframeFeature* f, int n, const Eigen::Isometry3d& T_MC,
                                         int cand, const LoopOptions& opt, uint64_t seed, PlaceFit* out) {
  out->place_points = out->matches = out->ransac_inliers = out->guided_matches = out->inliers = 0;
  out->failed = LoopVerdict::kFewPoints;
  // The candidate's place: its points and those of its closest connected
  // keyframes. With connected_min_shared > 1 not any covisible one: fusing
  // links the place to the keyframes flown since by a point or two, and their
  // own points - the same texture, placed by the drifted odometry - would take
  // the matches (or fail the ratio test against the old copies).
  const int nn = map_.covisible(cand, opt.connected_min_shared, opt.candidate_neighbours, kf_scratch_.data(),
                                shared_scratch_.data());
  const uint64_t mark = map_.next_mark();
  const double floor_m = map_.options().point_sigma_floor_m;
  targets_.clear();
  for (int i = -1; i < nn; ++i) {
    const int k = i < 0 ? cand : kf_scratch_[i];
    const MapKeyframe& N = map_.keyframe(k);
    for (int j = 0; j < N.n; ++j) {
      const int32_t p = map_.point_of(k, j);
      if (p < 0 || map_.point(p).mark == mark) continue;
      map_.point(p).mark = mark;
      const MapPoint& P = map_.point(p);
      targets_.push_back({P.p_M, &P.desc, p, point_sigma_m(cam_, P, floor_m), P.level});
    }
  }
  // The candidate's own depth-backed features that the map keeps no point
  // for (culled, or never seen twice): RGB-D measured them, and most of a
  // keyframe is such features (the map keeps the points seen again, a small
  // share of what a view holds), so without them a revisit from another
  // angle rarely finds enough matches.
  if (opt.place_features) {
    for (int i = -1; i < nn; ++i) {
      const int k = i < 0 ? cand : kf_scratch_[i];
      const MapKeyframe& C = map_.keyframe(k);
      for (int j = 0; j < C.n; ++j) {
        const KeyframeFeature& g = map_.feature(k, j);
        if (map_.point_of(k, j) >= 0 || g.depth_m <= 0) continue;
        targets_.push_back({C.T_MC * cam_.point_C(g), &g.desc, -1,
                            std::max(floor_m, cam_.sigma_depth_m(g.depth_m)), g.level});
      }
    }
  }
  out->place_points = static_cast<int>(targets_.size());
  const int seed_min = std::min(opt.min_seed_inliers, opt.min_inliers);
  if (out->place_points < seed_min) return kFewInliers;
  // Descriptor matches of the depth-backed features, best two with the ratio
  // test; a second best within a few cm of the best is the same place seen
  // twice (a point and the feature it came from), not an ambiguity.
  std::vector<Eigen::Vector3d> q, p;
  std::vector<double> thr;
  Pairs pairs;
  const auto add_pair = [&](int j, int t) {
    q.push_back(T_MC * cam_.point_C(f[j]));
    p.push_back(targets_[static_cast<size_t>(t)].p_M);
    thr.push_back(opt.inlier_m + 3.0 * cam_.sigma_depth_m(f[j].depth_m));
    pairs.emplace_back(j, t);
  };
  const int nt = static_cast<int>(targets_.size());
  dist_.resize(static_cast<size_t>(nt));
  for (int j = 0; j < n; ++j) {
    if (f[j].depth_m <= 0) continue;
    int best = BestTwoMatches::kNone, arg = -1;
    for (int t = 0; t < nt; ++t) {
      dist_[static_cast<size_t>(t)] = hamming_distance(f[j].desc, *targets_[static_cast<size_t>(t)].desc);
      if (dist_[static_cast<size_t>(t)] < best) {
        best = dist_[static_cast<size_t>(t)];
        arg = t;
      }
    }
    if (arg < 0 || best > opt.match_max_hamming) continue;
    int second = BestTwoMatches::kNone;
    const Eigen::Vector3d& pb = targets_[static_cast<size_t>(arg)].p_M;
    for (int t = 0; t < nt; ++t) {
      if (t != arg && dist_[static_cast<size_t>(t)] < second &&
          (targets_[static_cast<size_t>(t)].p_M - pb).squaredNorm() > kSamePlace_m * kSamePlace_m)
        second = dist_[static_cast<size_t>(t)];
    }
    if (second != BestTwoMatches::kNone && !(best < opt.match_ratio * second)) continue;
    add_pair(j, arg);
  }
  out->matches = static_cast<int>(q.size());
  out->failed = LoopVerdict::kFewMatches;
  if (out->matches < seed_min) return kFewInliers;
  // 4-DoF RANSAC: two matches fix yaw and translation. Seeded by the caller
  // (keyframe ids), so a replay finds the same places.
  std::mt19937_64 rng(seed);
  std::vector<int> best_in, in;
  auto inliers_of = [&](const Eigen::Isometry3d& T, std::vector<int>& set) {
    set.clear();
    for (size_t i = 0; i < q.size(); ++i)
      if ((T * q[i] - p[i]).norm() < thr[i]) set.push_back(static_cast<int>(i));
  };
  // The best correction RANSAC finds on the pairs, refitted on its inliers
  // (left in `in`); false below seed_min inliers or the share.
  const auto ransac = [&](Eigen::Isometry3d* T) {
    const int m0 = static_cast<int>(q.size());
    best_in.clear();
    for (int it = 0; it < opt.ransac_iterations && m0 >= 2; ++it) {
      const int a = static_cast<int>(rng() % static_cast<uint64_t>(m0));
      const int b = static_cast<int>(rng() % static_cast<uint64_t>(m0));
      if (a == b || (q[a] - q[b]).head<2>().norm() < 0.1 || (p[a] - p[b]).head<2>().norm() < 0.1) continue;
      inliers_of(fit_4dof(q, p, {a, b}), in);
      if (in.size() > best_in.size()) best_in.swap(in);
    }
    out->ransac_inliers = static_cast<int>(best_in.size());
    if (out->ransac_inliers < seed_min) return false;
    *T = fit_4dof(q, p, best_in);
    for (int round = 0; round < 2; ++round) {
      inliers_of(*T, in);
      if (static_cast<int>(in.size()) < seed_min) break;
      *T = fit_4dof(q, p, in);
    }
    inliers_of(*T, in);
    out->ransac_inliers = static_cast<int>(in.size());
    return out->ransac_inliers >= seed_min && in.size() >= opt.min_inlier_share * m0;
  };
  // Guided search: a correction puts the place's targets in the query image;
  // each is matched to the features around where it lands, at a consistent
  // depth. The descriptors alone match few targets of a place seen from
  // another angle (every target competes with every other); where the
  // geometry already says where to look, most of them are found. The pairs
  // become `kept` and what the search adds.
  const auto guided = [&](const Eigen::Isometry3d& T, double radius_px, const Pairs& kept) {
    std::vector<char> taken(static_cast<size_t>(n), 0), target_taken(static_cast<size_t>(nt), 0);
    for (const auto& [j, t] : kept) {
      taken[static_cast<size_t>(j)] = 1;
      target_taken[static_cast<size_t>(t)] = 1;
    }
    const Eigen::Isometry3d T_CM = (T * T_MC).inverse();
    // Per feature: the best target found for it and its distance.
    std::vector<int> claim(static_cast<size_t>(n), -1),
        claim_dist(static_cast<size_t>(n), BestTwoMatches::kNone);
    for (int t = 0; t < nt; ++t) {
      if (target_taken[static_cast<size_t>(t)]) continue;
      const Target& tg = targets_[static_cast<size_t>(t)];
      const Eigen::Vector3d c = T_CM * tg.p_M;
      if (c.z() < 0.1) continue;
      const double u = cam_.K.fx * c.x() / c.z() + cam_.K.cx, v = cam_.K.fy * c.y() / c.z() + cam_.K.cy;
      if (u < 0 || v < 0 || u >= cam_.width || v >= cam_.height) continue;
      BestTwoMatches bt;
      for (int j = 0; j < n; ++j) {
        if (taken[static_cast<size_t>(j)] || f[j].depth_m <= 0) continue;
        const double r = radius_px * std::pow(cam_.level_scale, f[j].level);
        if (std::abs(f[j].u_px - u) > r || std::abs(f[j].v_px - v) > r) continue;
        if (std::abs(c.z() - f[j].depth_m) > opt.inlier_m + 3.0 * cam_.sigma_depth_m(f[j].depth_m)) continue;
        bt.offer(hamming_distance(f[j].desc, *tg.desc), j);
      }
      if (bt.best_index < 0 || bt.best > opt.match_max_hamming ||
          !bt.passes_ratio(static_cast<float>(opt.match_ratio)))
        continue;
      const size_t j = static_cast<size_t>(bt.best_index);
      if (bt.best < claim_dist[j]) {
        claim_dist[j] = bt.best;
        claim[j] = t;
      }
    }
    q.clear();
    p.clear();
    thr.clear();
    pairs.clear();
    for (const auto& [j, t] : kept) add_pair(j, t);
    for (int j = 0; j < n; ++j)
      if (claim[static_cast<size_t>(j)] >= 0) add_pair(j, claim[static_cast<size_t>(j)]);
    return static_cast<int>(pairs.size() - kept.size());
  };
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  out->failed = out->matches < seed_min ? LoopVerdict::kFewMatches : LoopVerdict::kFewInliers;
  if (out->matches < seed_min || !ransac(&T)) {
    // No seed from the descriptors: the odometry's own pose is one (a loop
    // corrects drift, a few cm). Its guided matches must then agree on a
    // correction as descriptor matches would.
    if (opt.prior_seed_radius_px <= 0) return kFewInliers;
    out->prior_seeded = true;
    out->guided_matches = guided(Eigen::Isometry3d::Identity(), opt.prior_seed_radius_px, Pairs{});
    out->matches = static_cast<int>(q.size());
    if (out->matches < seed_min || !ransac(&T)) return kFewInliers;
  }
  if (opt.guided_radius_px > 0) {
    Pairs kept;
    for (int i : in) kept.push_back(pairs[static_cast<size_t>(i)]);
    out->guided_matches = guided(T, opt.guided_radius_px, kept);
    inliers_of(T, in);
    if (!in.empty()) T = fit_4dof(q, p, in);
    inliers_of(T, in);
  }
  const int m = static_cast<int>(q.size());
  out->inliers = static_cast<int>(in.size());
  out->failed = LoopVerdict::kFewRefitInliers;
  if (static_cast<int>(in.size()) < opt.min_inliers || in.size() < opt.min_inlier_share * m)
    return kFewInliers;
  if (opt.refine_chi2 > 0) {
    // The 3D fit weighs every point alike and its gate admits several cm at
    // range, where the depth is poor: refit on what the camera measures well
    // (pixels) and what it measures poorly (depth), each with its noise, and
    // keep the matches the refit explains.
    std::vector<int> cand_in = in;
    for (int round = 0; round < 2; ++round) {
      T = refine_4dof(T, T_MC, f, pairs, cand_in, opt.refine_chi2);
      chi2_inliers(T, T_MC, f, pairs, opt.refine_chi2, in);
      out->inliers = static_cast<int>(in.size());
      if (static_cast<int>(in.size()) < opt.min_inliers) return kFewInliers;
      cand_in = in;
    }
    if (in.size() < opt.min_inlier_share * m) return kFewInliers;
    out->cov = refit_covariance(T, T_MC, f, pairs, in);
  } else {
    out->cov.setZero();
  }
  out->failed = LoopVerdict::kVerified;
  out->correction = T;
  out->matches = m;
  out->inliers = static_cast<int>(in.size());
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (int i : in) mean += p[static_cast<size_t>(i)];
  mean /= static_cast<double>(in.size());
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (int i : in) {
    const Eigen::Vector3d d = p[static_cast<size_t>(i)] - mean;
    scatter += d * d.transpose();
  }
  scatter /= static_cast<double>(in.size());
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(scatter, Eigen::EigenvaluesOnly);
  out->out_of_plane_m = std::sqrt(std::max(0.0, eig.eigenvalues()(0)));
  // The matches to map points join them on closing; a feature-only target
  // has no point to join.
  out->inlier_pairs.clear();
  for (int i : in) {
    const int32_t pt = targets_[static_cast<size_t>(pairs[static_cast<size_t>(i)].second)].point;
    if (pt >= 0) out->inlier_pairs.emplace_back(pairs[static_cast<size_t>(i)].first, pt);
  }
  return kOk;
}

namespace {

// A map point seen from the corrected query camera: p_C = T_CM (T^-1 p_M),
// T = (yaw, t) in M. Pixel and depth residuals, whitened.
struct PlaceCost {
  PlaceCost(const Eigen::Isometry3d& T_CM, const Eigen::Vector3d& p_M, const PinholeK& K, double u, double v,
            double z, double inv_sigma_px, double inv_sigma_z)
      : R_(T_CM.linear()),
        t_(T_CM.translation()),
        p_(p_M),
        K_(K),
        u_(u),
        v_(v),
        z_(z),
        isp_(inv_sigma_px),
        isz_(inv_sigma_z) {}
  template <typename T>
  bool operator()(const T* x, T* r) const {
    const T c = ceres::cos(x[0]), s = ceres::sin(x[0]);
    const T dx = T(p_.x()) - x[1], dy = T(p_.y()) - x[2], dz = T(p_.z()) - x[3];
    const Eigen::Matrix<T, 3, 1> q(c * dx + s * dy, -s * dx + c * dy, dz);
    const Eigen::Matrix<T, 3, 1> pc = R_.cast<T>() * q + t_.cast<T>();
    const T zc = pc.z() < T(1e-3) ? T(1e-3) : pc.z();
    r[0] = (T(K_.fx) * pc.x() / zc + T(K_.cx) - T(u_)) * T(isp_);
    r[1] = (T(K_.fy) * pc.y() / zc + T(K_.cy) - T(v_)) * T(isp_);
    r[2] = (pc.z() - T(z_)) * T(isz_);
    return true;
  }
  Eigen::Matrix3d R_;
  Eigen::Vector3d t_, p_;
  PinholeK K_;
  double u_, v_, z_, isp_, isz_;
};

}  // namespace

void PlaceMatcher::pair_sigmas(const KeyframeFeature& f, int t, double* sigma_px, double* sigma_z_m) const {
  const double sp = targets_[static_cast<size_t>(t)].sigma_m;
  const double spx = cam_.sigma_px(f.level), sz = cam_.sigma_depth_m(f.depth_m);
  const double lever = cam_.K.fx * sp / std::max(0.1, static_cast<double>(f.depth_m));
  *sigma_px = std::sqrt(spx * spx + lever * lever);
  *sigma_z_m = std::sqrt(sz * sz + sp * sp);
}

Eigen::Isometry3d PlaceMatcher::refine_4dof(const Eigen::Isometry3d& T, const Eigen::Isometry3d& T_MC,
                                            const KeyframeFeature* f, const Pairs& pairs,
                                            const std::vector<int>& idx, double chi2) const {
  double x[4] = {yaw_of(T.linear()), T.translation().x(), T.translation().y(), T.translation().z()};
  ceres::Problem::Options po;
  po.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(po);
  // Robust from where the inlier gate ends: beyond it a match counts less.
  ceres::HuberLoss huber(std::sqrt(chi2));
  const Eigen::Isometry3d T_CM = T_MC.inverse();
  for (int i : idx) {
    const auto& [j, pt] = pairs[static_cast<size_t>(i)];
    double spx = 1, sz = 1;
    pair_sigmas(f[j], pt, &spx, &sz);
    problem.AddResidualBlock(new ceres::AutoDiffCostFunction<PlaceCost, 3, 4>(
                                 new PlaceCost(T_CM, targets_[static_cast<size_t>(pt)].p_M, cam_.K, f[j].u_px,
                                               f[j].v_px, f[j].depth_m, 1.0 / spx, 1.0 / sz)),
                             &huber, x);
  }
  ceres::Solver::Options so;
  so.linear_solver_type = ceres::DENSE_QR;
  so.max_num_iterations = 10;
  so.num_threads = 1;
  ceres::Solver::Summary sum;
  ceres::Solve(so, &problem, &sum);
  if (!sum.IsSolutionUsable()) return T;
  Eigen::Isometry3d R = Eigen::Isometry3d::Identity();
  R.linear() = rot_z(x[0]);
  R.translation() = Eigen::Vector3d(x[1], x[2], x[3]);
  return R;
}

Eigen::Matrix4d PlaceMatcher::refit_covariance(const Eigen::Isometry3d& T, const Eigen::Isometry3d& T_MC,
                                               const KeyframeFeature* f, const Pairs& pairs,
                                               const std::vector<int>& idx) const {
  const double x[4] = {yaw_of(T.linear()), T.translation().x(), T.translation().y(), T.translation().z()};
  const double* params[1] = {x};
  const Eigen::Isometry3d T_CM = T_MC.inverse();
  Eigen::Matrix4d info = Eigen::Matrix4d::Zero();
  for (int i : idx) {
    const auto& [j, pt] = pairs[static_cast<size_t>(i)];
    double spx = 1, sz = 1;
    pair_sigmas(f[j], pt, &spx, &sz);
    const ceres::AutoDiffCostFunction<PlaceCost, 3, 4> cost(
        new PlaceCost(T_CM, targets_[static_cast<size_t>(pt)].p_M, cam_.K, f[j].u_px, f[j].v_px, f[j].depth_m,
                      1.0 / spx, 1.0 / sz));
    double r[3];
    Eigen::Matrix<double, 3, 4, Eigen::RowMajor> J;
    double* jac[1] = {J.data()};
    if (!cost.Evaluate(params, r, jac) || !J.allFinite()) continue;
    info += J.transpose() * J;
  }
  const Eigen::LDLT<Eigen::Matrix4d> ldlt(info);
  if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().minCoeff() > 0)) return Eigen::Matrix4d::Zero();
  return ldlt.solve(Eigen::Matrix4d::Identity());
}

void PlaceMatcher::chi2_inliers(const Eigen::Isometry3d& T, const Eigen::Isometry3d& T_MC,
                                const KeyframeFeature* f, const Pairs& pairs, double chi2,
                                std::vector<int>& out) const {
  out.clear();
  const Eigen::Isometry3d T_CM = (T * T_MC).inverse();
  for (size_t i = 0; i < pairs.size(); ++i) {
    const auto& [j, pt] = pairs[i];
    const Eigen::Vector3d c = T_CM * targets_[static_cast<size_t>(pt)].p_M;
    if (c.z() < 1e-3) continue;
    double spx = 1, sz = 1;
    pair_sigmas(f[j], pt, &spx, &sz);
    const double eu = (cam_.K.fx * c.x() / c.z() + cam_.K.cx - f[j].u_px) / spx;
    const double ev = (cam_.K.fy * c.y() / c.z() + cam_.K.cy - f[j].v_px) / spx;
    const double ez = (c.z() - f[j].depth_m) / sz;
    if (eu * eu + ev * ev + ez * ez < chi2) out.push_back(static_cast<int>(i));
  }
}

template <class Skip>
int LoopCloser::geometric_candidates(int kf, const Skip& skip, int max, int32_t* out_kf, float* out_share) {
  const MapKeyframe& K = map_.keyframe(kf);
  // A sample of the query's depth points, in M.
  Eigen::Vector3d pts[48];
  int np = 0;
  const int stride = std::max(1, K.n / 48);
  for (int j = 0; j < K.n && np < 48; j += stride) {
    const KeyframeFeature& g = map_.feature(kf, j);
    if (g.depth_m > 0) pts[np++] = K.T_MC * cam_.point_C(g);
  }
  if (np < 8) return 0;
  const Eigen::Vector3d axis_K = K.T_MC.linear().col(2);
  int n = 0;
  map_.for_each_keyframe([&](int k) {
    if (k == kf || skip(k)) return;
    const MapKeyframe& C = map_.keyframe(k);
    if ((C.T_MC.translation() - K.T_MC.translation()).norm() > opt_.geometric_max_range_m) return;
    if (C.T_MC.linear().col(2).dot(axis_K) < 0) return;  // looking away: a view beside, not a revisit
    const Eigen::Isometry3d T_CM = C.T_MC.inverse();
    int seen = 0;
    for (int i = 0; i < np; ++i) {
      const Eigen::Vector3d c = T_CM * pts[i];
      if (c.z() < 0.1 || c.z() > opt_.geometric_max_range_m) continue;
      const double u = cam_.K.fx * c.x() / c.z() + cam_.K.cx, v = cam_.K.fy * c.y() / c.z() + cam_.K.cy;
      if (u >= 0 && v >= 0 && u < cam_.width && v < cam_.height) ++seen;
    }
    const float share = static_cast<float>(seen) / static_cast<float>(np);
    if (share < opt_.geometric_min_overlap) return;
    // Insertion into the best `max`, best first.
    int at = n < max ? n : max;
    while (at > 0 && out_share[at - 1] < share) --at;
    if (at >= max) return;
    const int last = std::min(n, max - 1);
    for (int i = last; i > at; --i) {
      out_kf[i] = out_kf[i - 1];
      out_share[i] = out_share[i - 1];
    }
    out_kf[at] = k;
    out_share[at] = share;
    n = std::min(n + 1, max);
  });
  return n;
}

int LoopCloser::surface_views(int kf, int other, SurfaceView* out) {
  out[0].z_mm = map_.depth_grid(kf);
  out[0].T_MC = map_.keyframe(kf).T_MC;
  int n = 1;
  const int want = std::min(opt_.surface.neighbours, SurfaceAligner::kMaxViews - 1);
  if (want <= 0) return n;
  // Of the covisible keyframes flown within min_age_s of it (so the odometry
  // between them is local, not an older pass the map has linked), those
  // looking most unlike the views already chosen: the most covisible ones
  // repeat the keyframe's own view, and with it the direction it leaves free.
  const int64_t t_ns = map_.keyframe(kf).t_ns, local_ns = static_cast<int64_t>(opt_.min_age_s * 1e9);
  const int nn = map_.covisible(kf, opt_.connected_min_shared, kMaxSurfaceNeighbourPool, kf_scratch_.data(),
                                shared_scratch_.data());
  Eigen::Vector3d axis[SurfaceAligner::kMaxViews];
  axis[0] = out[0].T_MC.linear().col(2);
  while (n <= want) {
    int best = -1;
    double best_cos = 2.0;
    for (int i = 0; i < nn; ++i) {
      const int k = kf_scratch_[static_cast<size_t>(i)];
      if (k < 0 || k == other || map_.keyframe(k).grid_n <= 0) continue;
      if (std::abs(map_.keyframe(k).t_ns - t_ns) >= local_ns) continue;
      const Eigen::Vector3d a = map_.keyframe(k).T_MC.linear().col(2);
      double cos_max = -1.0;
      for (int j = 0; j < n; ++j) cos_max = std::max(cos_max, a.dot(axis[j]));
      if (cos_max < best_cos) {
        best_cos = cos_max;
        best = i;
      }
    }
    if (best < 0) break;
    const int k = kf_scratch_[static_cast<size_t>(best)];
    kf_scratch_[static_cast<size_t>(best)] = -1;
    out[n].z_mm = map_.depth_grid(k);
    out[n].T_MC = map_.keyframe(k).T_MC;
    axis[n] = out[n].T_MC.linear().col(2);
    ++n;
  }
  return n;
}

bool LoopCloser::verify(int kf, int cand, double score, bool geometric, LoopMatch* out) {
  const MapKeyframe& K = map_.keyframe(kf);
  const MapKeyframe& C = map_.keyframe(cand);
  PlaceFit fit;
  const PlaceMatcher::Result r = matcher_.match(&map_.feature(kf, 0), K.n, K.T_MC, cand, opt_,
                                                static_cast<uint64_t>(K.id) * 1000003u + C.id, &fit);
  const double path_m = std::max(0.0, K.path_m - C.path_m);
  const Eigen::Vector3d pos = K.T_MC.translation();
  LoopCandidateRecord* rec = log_candidate();
  if (rec != nullptr) {
    rec->query_id = K.id;
    rec->candidate_id = C.id;
    rec->query_t_ns = K.t_ns;
    rec->candidate_t_ns = C.t_ns;
    rec->score = score;
    rec->geometric = geometric;
    rec->prior_seeded = fit.prior_seeded;
    rec->place_points = fit.place_points;
    rec->matches = fit.matches;
    rec->ransac_inliers = fit.ransac_inliers;
    rec->guided_matches = fit.guided_matches;
    rec->inliers = fit.inliers;
    rec->path_m = path_m;
    rec->T_MC_query = K.T_MC;
    rec->T_MC_candidate = C.T_MC;
  }
  const auto verdict = [&](LoopVerdict v) {
    if (rec != nullptr) rec->verdict = v;
  };
  // The descriptors refused it: the depth grids may still agree where the
  // keypoints do not (another range, another angle). The observability test
  // stands in for the plane check: it refuses any direction the surface
  // leaves free, which is what the plane check guards against.
  bool surface = false;
  if (r != PlaceMatcher::kOk && opt_.surface_verify && aligner_.enabled() && K.grid_n > 0 && C.grid_n > 0) {
    ++stats_.surface_tried;
    SurfaceView qv[SurfaceAligner::kMaxViews], cv[SurfaceAligner::kMaxViews];
    const int nq = surface_views(kf, cand, qv);
    const int nc = surface_views(cand, kf, cv);
    const SurfaceFit sf = aligner_.align(qv, nq, cv, nc, opt_.surface);
    if (rec != nullptr) {
      rec->surface_tried = true;
      rec->surface_ok = sf.ok;
      rec->surface_failed = sf.failed;
      rec->surface_overlap = sf.overlap;
      rec->surface_inlier_share = sf.inlier_share;
      rec->surface_rms_m = sf.rms_m;
      rec->surface_observability = sf.observability;
      rec->surface_correction = sf.correction;
    }
    if (sf.ok) {
      ++stats_.surface_aligned;
      surface = true;
      fit.correction = sf.correction;
      fit.cov = sf.cov;
      fit.inlier_pairs.clear();
    }
  }
  const Eigen::Isometry3d& T = fit.correction;
  const double yaw = yaw_of(T.linear());
  const double dp = (T * pos - pos).norm(), dyaw = std::abs(yaw);
  if (rec != nullptr && (r == PlaceMatcher::kOk || surface)) {
    rec->out_of_plane_m = fit.out_of_plane_m;
    rec->correction = T;
    rec->correction_m = dp;
    rec->correction_rad = dyaw;
  }
  if (r != PlaceMatcher::kOk && !surface) {
    ++stats_.rejected_inliers;
    verdict(fit.failed);
    return false;
  }
  if (!surface && fit.out_of_plane_m < opt_.min_out_of_plane_m) {
    ++stats_.rejected_planar;
    verdict(LoopVerdict::kPlanar);
    return false;
  }
  // Drift, or an alias? The odometry drifts by a few percent of the path at
  // most; a correction beyond that means another place that looks the same.
  if (dp > opt_.max_correction_m + opt_.max_correction_per_m * path_m ||
      dyaw > opt_.max_yaw_rad + opt_.max_yaw_per_m * path_m) {
    ++stats_.rejected_drift;
    verdict(LoopVerdict::kDrift);
    return false;
  }
  // The correction's uncertainty where it acts, at the query: p' = Rz(yaw) p + t.
  const double c = std::cos(yaw), s = std::sin(yaw);
  Eigen::Matrix4d A = Eigen::Matrix4d::Identity();
  A.block<3, 1>(1, 0) = Eigen::Vector3d(-s * pos.x() - c * pos.y(), c * pos.x() - s * pos.y(), 0.0);
  Eigen::Matrix4d S = A * fit.cov * A.transpose();
  S(0, 0) += kLoopSigma_rad * kLoopSigma_rad;
  S.block<3, 3>(1, 1) += kLoopSigma_m * kLoopSigma_m * Eigen::Matrix3d::Identity();
  if (opt_.min_correction_chi2 > 0) {
    Eigen::Vector4d d;
    d << yaw, T * pos - pos;
    if (d.dot(S.ldlt().solve(d)) < opt_.min_correction_chi2) {
      ++stats_.skipped_insignificant;
      verdict(LoopVerdict::kInsignificant);
      return false;
    }
  }
  verdict(LoopVerdict::kVerified);
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(S.block<3, 3>(1, 1), Eigen::EigenvaluesOnly);
  out->sigma_m = std::sqrt(std::max(0.0, eig.eigenvalues()(2)));
  out->sigma_rad = std::sqrt(S(0, 0));
  out->query = kf;
  out->candidate = cand;
  out->query_id = K.id;
  out->candidate_id = C.id;
  out->correction = T;
  out->matches = fit.matches;
  out->inliers = surface ? 0 : fit.inliers;  // a descriptor-verified candidate is preferred (detect)
  out->surface = surface;
  out->score = score;
  out->inlier_pairs = std::move(fit.inlier_pairs);
  return true;
}

bool LoopCloser::close(const LoopMatch& lm, LoopClosure* out) {
  if (!map_.keyframe_used(lm.query) || !map_.keyframe_used(lm.candidate) ||
      map_.keyframe(lm.query).id != lm.query_id || map_.keyframe(lm.candidate).id != lm.candidate_id)
    return false;
  // Nodes: every keyframe; held: the candidate's place and the map's first keyframe.
  PoseGraph4 g;
  std::vector<int> node_of(static_cast<size_t>(map_.max_keyframes()), -1);
  std::vector<int> slot_of;
  std::unordered_map<uint32_t, int> node_by_id;
  int first = -1;
  map_.for_each_keyframe([&](int k) {
    if (first < 0 || map_.keyframe(k).id < map_.keyframe(first).id) first = k;
  });
  const uint32_t query_id = lm.query_id;
  map_.for_each_keyframe([&](int k) {
    const MapKeyframe& K = map_.keyframe(k);
    node_of[static_cast<size_t>(k)] = g.add_node(K.T_MC, k == lm.candidate || k == first);
    slot_of.push_back(k);
    node_by_id[K.id] = node_of[static_cast<size_t>(k)];
  });
  const size_t n_nodes = g.T.size();
  const std::vector<Eigen::Isometry3d> T_old = g.T;
  // Edges from the current poses: the spanning tree and strong covisibility.
  for (size_t a = 0; a < n_nodes; ++a) {
    const int k = slot_of[a];
    const MapKeyframe& K = map_.keyframe(k);
    if (map_.keyframe_used(K.parent))
      g.add_edge_from_current(node_of[static_cast<size_t>(K.parent)], static_cast<int>(a), 0.01, 0.002);
    const int nc =
        map_.covisible(k, opt_.covis_edge_min_shared, 5, kf_scratch_.data(), shared_scratch_.data());
    for (int i = 0; i < nc; ++i) {
      const int o = kf_scratch_[i];
      if (map_.keyframe(o).id < K.id && o != K.parent)
        g.add_edge_from_current(node_of[static_cast<size_t>(o)], static_cast<int>(a), 0.02, 0.005);
    }
  }
  // Earlier loops stay closed.
  for (const LoopEdge& e : loop_edges_) {
    const auto ia = node_by_id.find(e.id_a), ib = node_by_id.find(e.id_b);
    if (ia == node_by_id.end() || ib == node_by_id.end()) continue;
    // Its yaw on top of the rotations the two keyframes have now.
    const Eigen::Matrix3d R = g.T[static_cast<size_t>(ia->second)].linear() * e.R_ab *
                              g.T[static_cast<size_t>(ib->second)].linear().transpose();
    g.add_edge(ia->second, ib->second, e.t_ab, yaw_of(R), e.sigma_m, e.sigma_rad);
  }
  // The new loop: where the query keyframe really is, seen from the candidate.
  const int ic = node_of[static_cast<size_t>(lm.candidate)], iq = node_of[static_cast<size_t>(lm.query)];
  const Eigen::Isometry3d T_q_true = lm.correction * g.T[static_cast<size_t>(iq)];
  const Eigen::Isometry3d& T_c = g.T[static_cast<size_t>(ic)];
  LoopEdge le{lm.candidate_id,
              lm.query_id,
              T_c.linear().transpose() * (T_q_true.translation() - T_c.translation()),
              T_c.linear().transpose() * T_q_true.linear(),
              std::max(lm.sigma_m, kLoopSigma_m),
              std::max(lm.sigma_rad, kLoopSigma_rad)};
  g.add_edge(ic, iq, le.t_ab, yaw_of(lm.correction.linear()), le.sigma_m, le.sigma_rad);
  // Start the keyframes flown since the query where the loop says they are.
  for (size_t a = 0; a < n_nodes; ++a) {
    if (!g.fixed[a] && map_.keyframe(slot_of[a]).id >= query_id)
      g.move_node(static_cast<int>(a), lm.correction);
  }
  if (!g.solve(opt_.pose_graph_iterations)) {
    ++stats_.pose_graph_failures;
    return false;
  }
  loop_edges_.push_back(le);
  // Keyframes take their corrected poses, points move with their first observer.
  std::vector<Eigen::Isometry3d> delta(n_nodes);
  for (size_t a = 0; a < n_nodes; ++a) delta[a] = g.T[a] * T_old[a].inverse();
  for (int pt = 0; pt < map_.max_points(); ++pt) {
    if (!map_.point_used(pt)) continue;
    MapPoint& P = map_.point(pt);
    if (P.n_obs == 0) continue;
    const int ref = node_of[static_cast<size_t>(P.obs_kf[0])];
    if (ref >= 0) P.p_M = delta[static_cast<size_t>(ref)] * P.p_M;
  }
  for (size_t a = 0; a < n_nodes; ++a) map_.keyframe(slot_of[a]).T_MC = g.T[a];
  // The matched points are one: the query's observations join the old place's points.
  for (const auto& [j, pt] : lm.inlier_pairs) {
    if (!map_.point_used(pt)) continue;
    const int32_t pa = map_.point_of(lm.query, j);
    if (pa == pt) continue;
    if (pa >= 0) {
      map_.merge_point(pa, pt);
      ++stats_.points_merged;
    } else if (map_.add_observation(pt, lm.query, j)) {
      ++stats_.points_merged;
    }
  }
  out->closed = true;
  out->match = lm;
  out->newest = map_.newest_keyframe();
  if (out->newest >= 0)
    out->newest_delta = delta[static_cast<size_t>(node_of[static_cast<size_t>(out->newest)])];
  ++stats_.closures;
  return true;
}

LoopCandidateRecord* LoopCloser::log_candidate() {
  if (!logging_) return nullptr;
  log_.candidates.emplace_back();
  return &log_.candidates.back();
}

const char* loop_verdict_name(LoopVerdict v) {
  switch (v) {
    case LoopVerdict::kFewPoints:
      return "few_points";
    case LoopVerdict::kFewMatches:
      return "few_matches";
    case LoopVerdict::kFewInliers:
      return "few_inliers";
    case LoopVerdict::kFewRefitInliers:
      return "few_refit_inliers";
    case LoopVerdict::kPlanar:
      return "planar";
    case LoopVerdict::kDrift:
      return "drift";
    case LoopVerdict::kInsignificant:
      return "within_uncertainty";
    case LoopVerdict::kVerified:
      return "verified";
  }
  return "?";
}

LoopClosure LoopCloser::process(int kf) {
  LoopClosure r;
  if (!map_.keyframe_used(kf)) return r;
  ++stats_.queries;
  const uint32_t id = map_.keyframe(kf).id;
  const bool cooldown =
      last_closure_kf_id_ != 0 && id < last_closure_kf_id_ + static_cast<uint32_t>(opt_.cooldown_keyframes);
  if (logging_) {
    LoopQueryRecord q;
    q.id = id;
    q.t_ns = map_.keyframe(kf).t_ns;
    q.cooldown = cooldown;
    q.T_MC = map_.keyframe(kf).T_MC;
    const int nc = map_.covisible(kf, 1, map_.max_keyframes(), kf_scratch_.data(), shared_scratch_.data());
    const int64_t min_age_ns = static_cast<int64_t>(opt_.min_age_s * 1e9);
    for (int i = 0; i < nc && q.old_links.size() < 8; ++i) {
      const MapKeyframe& O = map_.keyframe(kf_scratch_[i]);
      if (q.t_ns - O.t_ns >= min_age_ns) q.old_links.emplace_back(O.id, shared_scratch_[i]);
    }
    log_.queries.push_back(std::move(q));
  }
  chosen_record_ = -1;
  if (cooldown) {
    pending_count_ = 0;
    return r;
  }
  LoopMatch m;
  if (!detect(kf, &m)) {
    pending_count_ = 0;
    return r;
  }
  bool consistent = false;
  if (pending_count_ > 0 && map_.keyframe_used(m.query)) {
    // Both corrections at this keyframe's position: the same drift, seen twice.
    const Eigen::Vector3d pos = map_.keyframe(m.query).T_MC.translation();
    const double dp = (pending_.correction * pos - m.correction * pos).norm();
    const double dyaw = std::abs(yaw_of((pending_.correction.linear().transpose() * m.correction.linear())));
    consistent = dp < opt_.consistency_m && dyaw < opt_.consistency_rad;
    if (!consistent) {
      ++stats_.rejected_consistency;
      if (chosen_record_ >= 0) log_.candidates[static_cast<size_t>(chosen_record_)].inconsistent = true;
    }
  }
  pending_count_ = consistent ? pending_count_ + 1 : 1;
  pending_ = m;
  if (pending_count_ < opt_.consistent_keyframes) return r;
  pending_count_ = 0;
  if (close(m, &r)) {
    last_closure_kf_id_ = map_.keyframe(map_.newest_keyframe()).id;
    if (chosen_record_ >= 0) log_.candidates[static_cast<size_t>(chosen_record_)].closed = true;
  }
  return r;
}

}  // namespace kestrel::core

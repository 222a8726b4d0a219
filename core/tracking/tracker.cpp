#include "kestrel/core/tracker.hpp"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include "kestrel/core/so3.hpp"

namespace kestrel::core {

const char* to_string(TrackStatus s) {
  switch (s) {
    case TrackStatus::kTracked:
      return "tracked";
    case TrackStatus::kNewKeyframe:
      return "new-keyframe";
    case TrackStatus::kNoImage:
      return "no-image";
    case TrackStatus::kFeatureError:
      return "feature-error";
    case TrackStatus::kTooFewMatches:
      return "too-few-matches";
    case TrackStatus::kMotionFailed:
      return "motion-failed";
  }
  return "?";
}

std::string TrackerOptions::validate() const {
  std::ostringstream e;
  const std::string orb_err = orb.validate();
  if (!orb_err.empty()) e << orb_err;
  if (!(search_radius_min_px > 0 && search_radius_max_px >= search_radius_min_px))
    e << "search_radius_min_px/max_px: need 0 < min <= max\n";
  if (!(match_ratio > 0 && match_ratio <= 1)) e << "match_ratio: in (0, 1]\n";
  if (min_inliers < 3) e << "min_inliers: at least 3\n";
  if (motion_model_min_inliers != 0 && motion_model_min_inliers < 6)
    e << "motion_model_min_inliers: 0 (off) or at least 6\n";
  if (!(keyframe_area_ratio > 0 && keyframe_area_ratio < 1)) e << "keyframe_area_ratio: in (0, 1)\n";
  if (area_grid_cols < 2 || area_grid_rows < 2) e << "area_grid_cols/rows: at least 2\n";
  if (map_capacity < 0) e << "map_capacity: >= 0 (0: no local map)\n";
  if (!(rigid.consistency.threshold_px > 0 && rigid.depth_tol_rel >= 0 && rigid.depth_tol_m >= 0 &&
        rigid.min_run_length >= 3 && rigid.candidate_runs >= 1 && rigid.candidate_runs <= 8 &&
        rigid.confidence > 0 && rigid.confidence < 1 && rigid.max_iterations >= 1)) {
    e << "rigid.*: threshold_px > 0, tolerances >= 0, min_run_length >= 3, candidate_runs in [1, 8], "
         "confidence "
         "in (0, 1), max_iterations >= 1\n";
  }
  if (map_capacity > 0 && !(map_search_radius_px > 0 && map_min_inliers >= 6 && map_match_ratio > 0 &&
                            map_match_ratio <= 1 && map_max_correction_m > 0 && map_max_correction_rad > 0))
    e << "map_*: radius > 0, min_inliers >= 6, ratio in (0, 1], max corrections > 0\n";
  if (far_tracks && !(far_search_radius_px > 0 && far_max_segment_px > 0))
    e << "far_search_radius_px, far_max_segment_px: > 0\n";
  e << stereo.validate();
  return e.str();
}

namespace {

constexpr int kSearchCellPx = 32;

struct FrameData {
  OrbFeatures feats;
  std::unique_ptr<Eigen::Vector3d[]> p_C;  // back-projected keypoints, camera frame [m]
  std::unique_ptr<uint8_t[]> has_depth;
  std::unique_ptr<uint32_t[]> lm_id;   // persistent landmark id per feature, 0: none yet
  std::unique_ptr<int32_t[]> map_idx;  // its local-map entry, -1: none
  std::unique_ptr<uint8_t[]> owned;    // 1: this frame created that entry (as a keyframe)
  Eigen::Isometry3d T_WC = Eigen::Isometry3d::Identity();
  int64_t t_ns = 0;
  int with_depth = 0;
  bool valid = false;

  explicit FrameData(int capacity)
      : feats(capacity),
        p_C(new Eigen::Vector3d[capacity]),
        has_depth(new uint8_t[capacity]),
        lm_id(new uint32_t[capacity]),
        map_idx(new int32_t[capacity]),
        owned(new uint8_t[capacity]) {}

  void swap(FrameData& o) noexcept {
    std::swap(feats, o.feats);
    std::swap(p_C, o.p_C);
    std::swap(has_depth, o.has_depth);
    std::swap(lm_id, o.lm_id);
    std::swap(map_idx, o.map_idx);
    std::swap(owned, o.owned);
    std::swap(T_WC, o.T_WC);
    std::swap(t_ns, o.t_ns);
    std::swap(with_depth, o.with_depth);
    std::swap(valid, o.valid);
  }
};

// A local-map point: where a keyframe's depth put it, and what it looked like.
struct MapPoint {
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
  OrbDescriptor desc{};
  uint32_t id = 0;  // 0: empty
  int level = 0;
  uint32_t stamp = 0;  // == the search's stamp: already matched in this frame
  // > 0: the point came from the map (local bundle adjustment), with this
  // 1-sigma [m]; 0: the tracker's own, placed by its keyframe's depth.
  float sigma_m = 0.0f;
};

// Pose from 2D-3D matches with a measured depth each (RGB-D PnP): p' = R p + t
// must reproject onto u (sigma_px) and lie at depth z (sigma_z). Image-only
// PnP with a few dozen points leaves the distance along the optical axis
// uncertain by about a centimetre; the depth rows pin it. Gauss-Newton with
// Huber weights on the whitened 3-row error, left perturbation; true when the
// system stayed solvable.
// cov: the [t, w] covariance of the last linearisation (whitened errors, so
// in m and rad).
bool refine_pose_rgbd(Eigen::Matrix3d* R, Eigen::Vector3d* t, const PinholeK& K, const Correspondence2D3D* c,
                      const double* z, const double* sigma_z, const uint32_t* idx, std::size_t n,
                      double huber, Eigen::Matrix<double, 6, 6>* cov) {
  if (n < 3) return false;
  for (int it = 0; it < 6; ++it) {
    Eigen::Matrix<double, 6, 6> H = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> g = Eigen::Matrix<double, 6, 1>::Zero();
    for (std::size_t k = 0; k < n; ++k) {
      const uint32_t i = idx[k];
      const Eigen::Vector3d q = *R * c[i].p_prev + *t;
      if (q.z() < 0.05) continue;
      const double iz = 1.0 / q.z(), s = 1.0 / std::max(1e-3, static_cast<double>(c[i].sigma_px));
      Eigen::Vector3d r(s * (K.fx * q.x() * iz + K.cx - c[i].u_cur.x()),
                        s * (K.fy * q.y() * iz + K.cy - c[i].u_cur.y()), (q.z() - z[i]) / sigma_z[i]);
      Eigen::Matrix3d Jq;
      Jq << s * K.fx * iz, 0, -s * K.fx * q.x() * iz * iz, 0, s * K.fy * iz, -s * K.fy * q.y() * iz * iz, 0,
          0, 1.0 / sigma_z[i];
      Eigen::Matrix<double, 3, 6> J;
      J.leftCols<3>() = Jq;                  // d q / d t = I
      J.rightCols<3>() = -Jq * so3::hat(q);  // d q / d w = -[q]x
      const double e = r.norm();
      const double w = e <= huber ? 1.0 : huber / e;
      H.noalias() += w * J.transpose() * J;
      g.noalias() += w * J.transpose() * r;
    }
    const Eigen::LDLT<Eigen::Matrix<double, 6, 6>> ldlt(H);
    if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().array() > 0.0).all()) return false;
    *cov = ldlt.solve(Eigen::Matrix<double, 6, 6>::Identity());
    const Eigen::Matrix<double, 6, 1> d = -ldlt.solve(g);
    if (!d.allFinite()) return false;
    const Eigen::Matrix3d dR = so3::Exp(d.tail<3>());
    *R = dR * *R;
    *t = dR * *t + d.head<3>();
    if (d.norm() < 1e-8) break;
  }
  return true;
}

}  // namespace

// The stage methods below are kept out of line ([[gnu::noinline]]): one call
// per frame costs nothing, and `kestrel bench --cpu-budget` can then charge
// each stage its own instructions instead of folding them into track().
struct Tracker::Impl {
  Impl(const Rig& rig, const TrackerOptions& opt)
      : cam(rig.rgb),
        depth(rig.depth),
        extractor(opt.orb, std::max(rig.rgb.width, 1), std::max(rig.rgb.height, 1)),
        capacity(opt.orb.n_features),
        cur(capacity),
        kf(capacity),
        grid_cols((std::max(rig.rgb.width, 1) + kSearchCellPx - 1) / kSearchCellPx),
        grid_rows((std::max(rig.rgb.height, 1) + kSearchCellPx - 1) / kSearchCellPx),
        cell_start(new int[static_cast<size_t>(grid_cols * grid_rows + 1)]),
        cell_fill(new int[static_cast<size_t>(grid_cols * grid_rows)]),
        cell_items(new int[static_cast<size_t>(capacity)]),
        best_kf(new int[static_cast<size_t>(capacity)]),
        best_dist(new int[static_cast<size_t>(capacity)]),
        corr(new Correspondence2D3D[static_cast<size_t>(capacity)]),
        corr_cur(new int[static_cast<size_t>(capacity)]),
        order(new uint32_t[static_cast<size_t>(capacity)]),
        model_inl(new uint32_t[static_cast<size_t>(capacity)]),
        area_detected(new uint8_t[static_cast<size_t>(opt.area_grid_cols * opt.area_grid_rows)]),
        area_matched(new uint8_t[static_cast<size_t>(opt.area_grid_cols * opt.area_grid_rows)]),
        obs(new WindowObservation[static_cast<size_t>(capacity)]),
        mark(new uint8_t[static_cast<size_t>(capacity)]),
        map_capacity(opt.map_capacity),
        map(new MapPoint[static_cast<size_t>(std::max(opt.map_capacity, 1))]),
        map_z(new double[static_cast<size_t>(capacity)]),
        map_sz(new double[static_cast<size_t>(capacity)]),
        id_slot(new int32_t[id_table_size(opt.map_capacity)]),
        id_mask(static_cast<uint32_t>(id_table_size(opt.map_capacity) - 1)),
        lonsc(static_cast<size_t>(capacity), opt.lonsc),
        rigid(static_cast<size_t>(capacity), opt.rigid),
        corr_q(new Eigen::Vector3d[static_cast<size_t>(capacity)]),
        corr_has_q(new uint8_t[static_cast<size_t>(capacity)]),
        corr_z(new double[static_cast<size_t>(capacity)]),
        corr_sz(new double[static_cast<size_t>(capacity)]),
        orderer(static_cast<size_t>(capacity)),
        stereo_on(rig.stereo.present && rig.stereo.rectified && rig.stereo.baseline_m > 0),
        stereo_fb_px_m(rig.rgb.fx * rig.stereo.baseline_m),
        stereo(opt.stereo),
        kp_x(new float[static_cast<size_t>(capacity)]),
        kp_y(new float[static_cast<size_t>(capacity)]),
        disparity(new float[static_cast<size_t>(capacity)]) {
    K.fx = cam.fx();
    K.fy = cam.fy();
    K.cx = cam.cx();
    K.cy = cam.cy();
    std::fill(id_slot.get(), id_slot.get() + id_mask + 1, -1);
  }

  static size_t id_table_size(int ring) {
    size_t n = 1;
    while (n < 4 * static_cast<size_t>(std::max(ring, 1))) n <<= 1;
    return n;
  }

  // Metric depth at a keypoint, or 0 when missing, out of range or on a depth edge.
  double depth_at(const ImageView& d, float x, float y, double edge_rel) const {
    const int cx = static_cast<int>(std::lround(x));
    const int cy = static_cast<int>(std::lround(y));
    if (cx < 1 || cy < 1 || cx >= d.width - 1 || cy >= d.height - 1) return 0.0;
    double zmin = std::numeric_limits<double>::infinity(), zmax = 0.0, zc = 0.0;
    for (int dy = -1; dy <= 1; ++dy) {
      const auto* row =
          reinterpret_cast<const uint16_t*>(d.data + static_cast<size_t>(cy + dy) * d.stride_bytes);
      for (int dx = -1; dx <= 1; ++dx) {
        const uint16_t raw = row[cx + dx];
        if (raw == 0) return 0.0;
        const double z = raw * depth.scale_m_per_unit;
        zmin = std::min(zmin, z);
        zmax = std::max(zmax, z);
        if (dx == 0 && dy == 0) zc = z;
      }
    }
    if (zc < depth.min_range_m || zc > depth.max_range_m) return 0.0;
    if (zmax - zmin > edge_rel * zc) return 0.0;
    return zc;
  }

  // Stereo: depth z = f b / d from the row search; a feature without a match has none.
  [[gnu::noinline]] int stereo_depth(FrameData& f, const ImageView& left, const ImageView& right) {
    f.with_depth = 0;
    const int n = f.feats.size();
    for (int i = 0; i < n; ++i) {
      kp_x[i] = f.feats.keypoint(i).x;
      kp_y[i] = f.feats.keypoint(i).y;
    }
    StereoMatchStats st;
    stereo.match(left, right, kp_x.get(), kp_y.get(), n, disparity.get(), &st);
    for (int i = 0; i < n; ++i) {
      const double z = disparity[i] > 0 ? stereo_fb_px_m / disparity[i] : 0.0;
      f.has_depth[i] = z > 0 ? 1 : 0;
      if (z > 0) {
        f.p_C[i] = cam.back_project(Eigen::Vector2d(kp_x[i], kp_y[i]), z);
        ++f.with_depth;
      }
    }
    return st.searched;
  }

  [[gnu::noinline]] void back_project(FrameData& f, const ImageView& d, double edge_rel) {
    f.with_depth = 0;
    const bool have = d.data != nullptr && d.format == PixelFormat::kDepthU16;
    for (int i = 0; i < f.feats.size(); ++i) {
      const OrbKeypoint& kp = f.feats.keypoint(i);
      const double z = have ? depth_at(d, kp.x, kp.y, edge_rel) : 0.0;
      f.has_depth[i] = z > 0 ? 1 : 0;
      if (z > 0) {
        f.p_C[i] = cam.back_project(Eigen::Vector2d(kp.x, kp.y), z);
        ++f.with_depth;
      }
    }
  }

  void build_grid(const FrameData& f) {
    const int cells = grid_cols * grid_rows;
    std::fill(cell_fill.get(), cell_fill.get() + cells, 0);
    for (int i = 0; i < f.feats.size(); ++i) ++cell_fill[cell_of(f.feats.keypoint(i))];
    cell_start[0] = 0;
    for (int c = 0; c < cells; ++c) cell_start[c + 1] = cell_start[c] + cell_fill[c];
    std::fill(cell_fill.get(), cell_fill.get() + cells, 0);
    for (int i = 0; i < f.feats.size(); ++i) {
      const int c = cell_of(f.feats.keypoint(i));
      cell_items[cell_start[c] + cell_fill[c]++] = i;
    }
  }

  int cell_of(const OrbKeypoint& kp) const {
    const int gx = std::clamp(static_cast<int>(kp.x) / kSearchCellPx, 0, grid_cols - 1);
    const int gy = std::clamp(static_cast<int>(kp.y) / kSearchCellPx, 0, grid_rows - 1);
    return gy * grid_cols + gx;
  }

  double area_ratio(const TrackerOptions& opt, const uint32_t* inlier_idx, size_t n_inliers) {
    const int cols = opt.area_grid_cols, rows = opt.area_grid_rows;
    std::fill(area_detected.get(), area_detected.get() + cols * rows, 0);
    std::fill(area_matched.get(), area_matched.get() + cols * rows, 0);
    const double sx = static_cast<double>(cols) / cam.width(), sy = static_cast<double>(rows) / cam.height();
    auto cell = [&](const OrbKeypoint& kp) {
      const int gx = std::clamp(static_cast<int>(kp.x * sx), 0, cols - 1);
      const int gy = std::clamp(static_cast<int>(kp.y * sy), 0, rows - 1);
      return gy * cols + gx;
    };
    for (int i = 0; i < cur.feats.size(); ++i) area_detected[cell(cur.feats.keypoint(i))] = 1;
    for (size_t k = 0; k < n_inliers; ++k)
      area_matched[cell(cur.feats.keypoint(corr_cur[inlier_idx[k]]))] = 1;
    int det = 0, mat = 0;
    for (int c = 0; c < cols * rows; ++c) {
      det += area_detected[c];
      mat += area_matched[c];
    }
    return det > 0 ? static_cast<double>(mat) / det : 0.0;
  }

  // The best current feature within `radius` of uv for a descriptor, over the
  // search grid of cur (build_grid), among the features `accept` lets through.
  template <typename Accept>
  BestTwoMatches search_circle(const Eigen::Vector2d& uv, double radius, const OrbDescriptor& desc,
                               Accept accept) const {
    const double r2 = radius * radius;
    const int gx0 = std::max(0, static_cast<int>((uv.x() - radius) / kSearchCellPx));
    const int gx1 = std::min(grid_cols - 1, static_cast<int>((uv.x() + radius) / kSearchCellPx));
    const int gy0 = std::max(0, static_cast<int>((uv.y() - radius) / kSearchCellPx));
    const int gy1 = std::min(grid_rows - 1, static_cast<int>((uv.y() + radius) / kSearchCellPx));
    BestTwoMatches bt;
    for (int gy = gy0; gy <= gy1; ++gy) {
      for (int gx = gx0; gx <= gx1; ++gx) {
        const int c = gy * grid_cols + gx;
        for (int k = cell_start[c]; k < cell_start[c + 1]; ++k) {
          const int j = cell_items[k];
          const OrbKeypoint& ckp = cur.feats.keypoint(j);
          const double dx = ckp.x - uv.x(), dy = ckp.y - uv.y();
          if (dx * dx + dy * dy > r2) continue;
          if (!accept(j, ckp)) continue;
          bt.offer(hamming_distance(desc, cur.feats.descriptor(j)), j);
        }
      }
    }
    return bt;
  }

  // One candidate per current feature: the closest descriptor wins.
  void keep_best(const BestTwoMatches& bt, int candidate) {
    if (bt.best < best_dist[bt.best_index]) {
      best_dist[bt.best_index] = bt.best;
      best_kf[bt.best_index] = candidate;
    }
  }

  void reset_best(int n_cur) {
    std::fill(best_kf.get(), best_kf.get() + n_cur, -1);
    std::fill(best_dist.get(), best_dist.get() + n_cur, std::numeric_limits<int>::max());
  }

  // ---- The local map ----------------------------------------------------------
  // Searches the local map from T_WC (a new keyframe's chained pose) for
  // points of older keyframes that cur does not see through the keyframe it
  // tracked; with enough RGB-D PnP inliers those features take the points'
  // ids and res carries the map's pose with its uncertainty. A few dozen
  // matches give a pose good to a centimetre or two, noisier than tracking's
  // chained one, so it only replaces *T_WC when apply (a restart with no
  // chain); otherwise the window weighs it against the chain. Allocation-free.
  [[gnu::noinline]] void search_map(const TrackerOptions& opt, Eigen::Isometry3d* T_WC, bool apply,
                                    TrackResult& res) {
    if (map_size == 0) return;
    const int n = match_map_points(opt, T_WC->inverse());
    res.map_matched = n;
    if (n < opt.map_min_inliers) return;
    Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
    Eigen::Vector3d t = Eigen::Vector3d::Zero();
    Eigen::Matrix<double, 6, 6> cov;
    size_t n_in = 0;
    if (!solve_map_pose(opt, n, &R, &t, &cov, &n_in)) return;
    // p_new = R p_guess + t: the guess camera seen from the corrected one.
    Eigen::Isometry3d T_CnewCguess = Eigen::Isometry3d::Identity();
    T_CnewCguess.linear() = R;
    T_CnewCguess.translation() = t;
    const Eigen::Isometry3d T_WC_new = *T_WC * T_CnewCguess.inverse();
    const double dp = (T_WC_new.translation() - T_WC->translation()).norm();
    const double dr = Eigen::AngleAxisd(R).angle();
    const double sigma_p = std::sqrt(cov.topLeftCorner<3, 3>().diagonal().maxCoeff());
    if (dp > opt.map_max_correction_m || dr > opt.map_max_correction_rad || !(sigma_p <= opt.map_max_sigma_m))
      return;
    res.map_inliers = static_cast<int>(n_in);
    res.map_pose_valid = true;
    res.T_WC_map = T_WC_new;
    res.map_sigma_p_m = sigma_p;
    res.map_sigma_rad = std::sqrt(cov.bottomRightCorner<3, 3>().diagonal().maxCoeff());
    res.map_correction_m = dp;
    if (apply) {
      *T_WC = T_WC_new;
      res.map_corrected = true;
    }
    adopt_map_matches(n_in);
  }

  // Projects every map point cur does not already see into cur from T_CW and
  // matches it in a circle (level, depth and descriptor gates); fills corr
  // (points in the guess camera frame) and returns how many matched.
  int match_map_points(const TrackerOptions& opt, const Eigen::Isometry3d& T_CW) {
    if (++map_stamp == 0) map_stamp = 1;
    const int n_cur = cur.feats.size();
    for (int j = 0; j < n_cur; ++j) {
      const int32_t i = cur.map_idx[j];
      if (i >= 0 && map[i].id == cur.lm_id[j]) map[i].stamp = map_stamp;
    }
    build_grid(cur);
    reset_best(n_cur);
    const double radius = opt.map_search_radius_px;
    for (int i = 0; i < map_size; ++i) {
      const MapPoint& mp = map[i];
      if (mp.id == 0 || mp.stamp == map_stamp) continue;
      const Eigen::Vector3d p_C = T_CW * mp.p_W;
      if (p_C.z() < 0.1) continue;
      const Eigen::Vector2d uv = cam.distort_normalized_to_pixel(p_C.head<2>() / p_C.z());
      if (!cam.in_image(uv)) continue;
      const double z_tol = opt.map_depth_tol_rel * p_C.z() + 0.03;
      const BestTwoMatches bt = search_circle(uv, radius, mp.desc, [&](int j, const OrbKeypoint& ckp) {
        return cur.lm_id[j] == 0 && cur.has_depth[j] &&
               std::abs(ckp.level - mp.level) <= opt.match_max_level_diff &&
               std::abs(cur.p_C[j].z() - p_C.z()) <= z_tol;
      });
      if (bt.best_index < 0 || bt.best > opt.map_match_max_hamming || !bt.passes_ratio(opt.map_match_ratio))
        continue;
      keep_best(bt, i);
    }
    int n = 0;
    for (int j = 0; j < n_cur; ++j) {
      if (best_kf[j] < 0) continue;
      const OrbKeypoint& ckp = cur.feats.keypoint(j);
      Correspondence2D3D& c = corr[n];
      c.p_prev = T_CW * map[best_kf[j]].p_W;
      c.u_cur = cam.undistort_pixel(Eigen::Vector2d(ckp.x, ckp.y));
      c.sigma_px = static_cast<float>(opt.keypoint_sigma_px * extractor.level_scale(ckp.level));
      c.id = static_cast<uint32_t>(j);
      order[n] = static_cast<uint32_t>(n);
      ++n;
    }
    return n;
  }

  // The motion-model fallback (TrackerOptions::motion_model_min_inliers):
  // from the predicted R, t, Huber Gauss-Newton on the kept matches, then keep
  // those within the consistency bound; three rounds. The inliers are
  // model_inl[0..*n_in).
  bool track_motion_model(const TrackerOptions& opt, int n, Eigen::Matrix3d* R, Eigen::Vector3d* t,
                          size_t* n_in) {
    *n_in = static_cast<size_t>(n);
    for (int k = 0; k < n; ++k) model_inl[k] = static_cast<uint32_t>(k);
    for (int round = 0; round < 3; ++round) {
      if (!refine_pose_gauss_newton(R, t, K, corr.get(), static_cast<size_t>(n), model_inl.get(), *n_in,
                                    opt.refine)
               .ok)
        return false;
      *n_in = 0;
      for (int k = 0; k < n; ++k) {
        const Eigen::Vector3d q = *R * corr[k].p_prev + *t;
        if (q.z() < opt.rigid.consistency.min_depth_m) continue;
        const Eigen::Vector2d e(K.fx * q.x() / q.z() + K.cx - corr[k].u_cur.x(),
                                K.fy * q.y() / q.z() + K.cy - corr[k].u_cur.y());
        if (e.squaredNorm() <= opt.rigid.consistency.threshold2(corr[k]))
          model_inl[(*n_in)++] = static_cast<uint32_t>(k);
      }
      if (static_cast<int>(*n_in) < opt.motion_model_min_inliers) return false;
    }
    return true;
  }

  // RGB-D PnP on corr[0..n) from the guess: two rounds, dropping matches
  // beyond 3 sigma (3-row error) in between. The inliers are order[0..*n_in).
  bool solve_map_pose(const TrackerOptions& opt, int n, Eigen::Matrix3d* R, Eigen::Vector3d* t,
                      Eigen::Matrix<double, 6, 6>* cov, size_t* n_in) {
    for (int k = 0; k < n; ++k) {
      const double zk = cur.p_C[corr[k].id].z();
      map_z[k] = zk;
      map_sz[k] = std::max(0.005, depth.sigma_coeff_per_m * zk * zk);
    }
    *n_in = static_cast<size_t>(n);
    for (int round = 0; round < 2; ++round) {
      if (!refine_pose_rgbd(R, t, K, corr.get(), map_z.get(), map_sz.get(), order.get(), *n_in, 2.0, cov))
        return false;
      *n_in = 0;
      for (int k = 0; k < n; ++k) {
        const Eigen::Vector3d q = *R * corr[k].p_prev + *t;
        if (q.z() < 0.1) continue;
        const double s = 1.0 / corr[k].sigma_px;
        const Eigen::Vector3d e(s * (K.fx * q.x() / q.z() + K.cx - corr[k].u_cur.x()),
                                s * (K.fy * q.y() / q.z() + K.cy - corr[k].u_cur.y()),
                                (q.z() - map_z[k]) / map_sz[k]);
        if (e.norm() <= 3.0) order[(*n_in)++] = static_cast<uint32_t>(k);
      }
      if (static_cast<int>(*n_in) < opt.map_min_inliers) return false;
    }
    return true;
  }

  // The PnP inliers' features take their map points' ids and become observations.
  void adopt_map_matches(size_t n_in) {
    for (size_t k = 0; k < n_in; ++k) {
      const int j = static_cast<int>(corr[order[k]].id);
      const int i = best_kf[j];
      map[i].stamp = map_stamp;
      cur.lm_id[j] = map[i].id;
      cur.map_idx[j] = i;
      mark[j] |= FeatureMark::kMapPoint;
      add_observation(map[i].id, corr[order[k]].u_cur, cur.p_C[j].z(), corr[order[k]].sigma_px, i);
    }
  }

  // map_i: the ring slot of the landmark (-1: none); a map point's refined
  // position goes with the observation to the window as a prior.
  void add_observation(uint32_t id, const Eigen::Vector2d& uv, double depth_m, float sigma_px,
                       int32_t map_i) {
    WindowObservation& o = obs[n_obs++];
    o.landmark_id = id;
    o.uv = uv;
    o.depth_m = depth_m;
    o.sigma_px = sigma_px;
    attach_map_point(o, map_i);
  }

  void attach_map_point(WindowObservation& o, int32_t i) const {
    o.map_sigma_m = 0.0f;
    if (i < 0 || map[i].id != o.landmark_id || !(map[i].sigma_m > 0.0f)) return;
    o.map_sigma_m = map[i].sigma_m;
    o.map_p_W = map[i].p_W;
  }

  // Ring slot of a landmark id through the direct-mapped id cache; -1 when
  // not (or no longer) in the ring.
  int32_t find_in_map(uint32_t id) const {
    const int32_t i = id_slot[id & id_mask];
    return i >= 0 && map[i].id == id ? i : -1;
  }

  // The next ring slot (the oldest entry once full).
  int take_ring_slot() {
    const int i = map_next;
    map_next = (map_next + 1) % map_capacity;
    map_size = std::max(map_size, i + 1);
    return i;
  }

  // ---- Tracking against the keyframe -----------------------------------------
  // Projects the keyframe's depth-backed points into cur with the IMU-predicted
  // motion (R_pred, t_pred: keyframe camera -> current camera) and matches each
  // in a circle of `radius`; fills corr / corr_cur and returns how many matched.
  [[gnu::noinline]] int match_keyframe(const TrackerOptions& opt, const Eigen::Matrix3d& R_pred,
                                       const Eigen::Vector3d& t_pred, double radius, TrackResult& res) {
    build_grid(cur);
    const int n_cur = cur.feats.size();
    reset_best(n_cur);
    for (int i = 0; i < kf.feats.size(); ++i) {
      if (!kf.has_depth[i]) continue;
      const Eigen::Vector3d p_C = R_pred * kf.p_C[i] + t_pred;
      if (p_C.z() < 0.1) continue;
      const Eigen::Vector2d uv = cam.distort_normalized_to_pixel(p_C.head<2>() / p_C.z());
      if (!cam.in_image(uv)) continue;
      ++res.predicted;
      const int kf_level = kf.feats.keypoint(i).level;
      const BestTwoMatches bt =
          search_circle(uv, radius, kf.feats.descriptor(i), [&](int, const OrbKeypoint& ckp) {
            return std::abs(ckp.level - kf_level) <= opt.match_max_level_diff;
          });
      if (bt.best_index < 0 || bt.best > opt.match_max_hamming || !bt.passes_ratio(opt.match_ratio)) continue;
      keep_best(bt, i);
    }
    int n = 0;
    for (int j = 0; j < n_cur; ++j) {
      if (best_kf[j] < 0) continue;
      const OrbKeypoint& ckp = cur.feats.keypoint(j);
      Correspondence2D3D& c = corr[n];
      c.p_prev = kf.p_C[best_kf[j]];
      c.u_cur = cam.undistort_pixel(Eigen::Vector2d(ckp.x, ckp.y));
      c.sigma_px = static_cast<float>(opt.keypoint_sigma_px * extractor.level_scale(ckp.level));
      c.match_cost = static_cast<float>(best_dist[j]);
      c.id = static_cast<uint32_t>(j);
      corr_cur[n] = j;
      mark[j] |= FeatureMark::kMatched;
      ++n;
    }
    return n;
  }

  // LONSC's inliers carry their keyframe point's landmark id into cur and
  // become this frame's observations.
  // inl: the motion's inliers (LONSC's, or the rigid model's without an IMU rotation).
  void adopt_tracked_inliers(const uint32_t* inl, size_t n_inl) {
    for (size_t k = 0; k < n_inl; ++k) {
      const uint32_t idx = inl[k];
      const int j = corr_cur[idx];
      cur.lm_id[j] = kf.lm_id[best_kf[j]];
      cur.map_idx[j] = kf.map_idx[best_kf[j]];
      mark[j] |= FeatureMark::kInlier;
      add_observation(cur.lm_id[j], corr[idx].u_cur, cur.has_depth[j] ? cur.p_C[j].z() : 0.0,
                      corr[idx].sigma_px, cur.map_idx[j]);
    }
  }

  // ---- Far tracks ---------------------------------------------------------------
  // A keyframe feature without depth lies on its ray, and (holes and depth
  // edges aside) beyond the sensor's range: with the frame's motion known (R,
  // t: keyframe camera -> current camera) it is between the ray's projections
  // at max_range_m and at infinity. A short segment: a few pixels for a
  // camera moving centimetres past a wall metres away. The motion comes from
  // the depth-backed points before this runs, so these matches cannot bend
  // it; a wrong one costs the window a 2-row outlier, which its robust cost
  // and triangulation's parallax test meet first. Allocation-free.
  [[gnu::noinline]] void track_far_points(const TrackerOptions& opt, const Eigen::Matrix3d& R,
                                          const Eigen::Vector3d& t, TrackResult& res) {
    const double near_m = depth.max_range_m;
    if (!(near_m > 0)) return;  // no range: nothing is known to be beyond it
    const int n_cur = cur.feats.size();
    reset_best(n_cur);
    for (int i = 0; i < kf.feats.size(); ++i) {
      if (kf.has_depth[i] || kf.lm_id[i] == 0) continue;
      const Eigen::Vector3d q_inf = R * kf.p_C[i];  // p_C: the ray at unit depth
      if (q_inf.z() < 0.1) continue;
      const Eigen::Vector3d q_near = near_m * q_inf + t;
      if (q_near.z() < 0.1) continue;
      const Eigen::Vector2d a = cam.distort_normalized_to_pixel(q_inf.head<2>() / q_inf.z());
      const Eigen::Vector2d b = cam.distort_normalized_to_pixel(q_near.head<2>() / q_near.z());
      if (!cam.in_image(a) && !cam.in_image(b)) continue;
      const Eigen::Vector2d ab = b - a;
      const double len2 = ab.squaredNorm();
      if (len2 > opt.far_max_segment_px * opt.far_max_segment_px) continue;
      ++res.far_predicted;
      const OrbKeypoint& kp = kf.feats.keypoint(i);
      const double r = opt.far_search_radius_px * extractor.level_scale(kp.level);
      const BestTwoMatches bt =
          search_circle(0.5 * (a + b), 0.5 * std::sqrt(len2) + r, kf.feats.descriptor(i),
                        [&](int j, const OrbKeypoint& ckp) {
                          if (cur.lm_id[j] != 0 || std::abs(ckp.level - kp.level) > opt.match_max_level_diff)
                            return false;
                          const Eigen::Vector2d ap(ckp.x - a.x(), ckp.y - a.y());
                          const double s = len2 > 0 ? std::clamp(ap.dot(ab) / len2, 0.0, 1.0) : 0.0;
                          return (ap - s * ab).squaredNorm() <= r * r;
                        });
      if (bt.best_index < 0 || bt.best > opt.match_max_hamming || !bt.passes_ratio(opt.match_ratio)) continue;
      keep_best(bt, i);
    }
    for (int j = 0; j < n_cur; ++j) {
      if (best_kf[j] < 0) continue;
      const OrbKeypoint& ckp = cur.feats.keypoint(j);
      cur.lm_id[j] = kf.lm_id[best_kf[j]];
      cur.map_idx[j] = -1;
      mark[j] |= FeatureMark::kFar;
      add_observation(cur.lm_id[j], cam.undistort_pixel(Eigen::Vector2d(ckp.x, ckp.y)),
                      cur.has_depth[j] ? cur.p_C[j].z() : 0.0,
                      static_cast<float>(opt.keypoint_sigma_px * extractor.level_scale(ckp.level)), -1);
      ++res.far_tracked;
    }
  }

  // cur becomes the keyframe at T_WC (after the local map had its say):
  // features that matched a keyframe point keep its id; the others with a
  // depth start new landmarks, observed here for the first time, and enter the map.
  [[gnu::noinline]] void make_keyframe(const TrackerOptions& opt, Eigen::Isometry3d T_WC, TrackResult& res) {
    if (map_capacity > 0) search_map(opt, &T_WC, !kf.valid, res);
    cur.T_WC = T_WC;
    for (int j = 0; j < cur.feats.size(); ++j) {
      if (cur.lm_id[j] != 0 || !cur.has_depth[j]) continue;
      cur.lm_id[j] = next_lm_id++;
      if (next_lm_id == 0) next_lm_id = 1;
      const OrbKeypoint& kp = cur.feats.keypoint(j);
      add_observation(cur.lm_id[j], cam.undistort_pixel(Eigen::Vector2d(kp.x, kp.y)), cur.p_C[j].z(),
                      static_cast<float>(opt.keypoint_sigma_px * extractor.level_scale(kp.level)), -1);
      add_to_map(cur, j);
    }
    // Far tracks: the features without depth keep (or start) a landmark seen
    // here without depth, after every depth-backed one, so that a window short
    // of landmark slots drops these first. p_C holds their ray at unit depth.
    if (opt.far_tracks) {
      for (int j = 0; j < cur.feats.size(); ++j) {
        if (cur.has_depth[j]) continue;
        const OrbKeypoint& kp = cur.feats.keypoint(j);
        cur.p_C[j] = cam.back_project(Eigen::Vector2d(kp.x, kp.y), 1.0);
        if (cur.lm_id[j] != 0) continue;
        cur.lm_id[j] = next_lm_id++;
        if (next_lm_id == 0) next_lm_id = 1;
        add_observation(cur.lm_id[j], cam.undistort_pixel(Eigen::Vector2d(kp.x, kp.y)), 0.0,
                        static_cast<float>(opt.keypoint_sigma_px * extractor.level_scale(kp.level)), -1);
      }
    }
    cur.valid = true;
    kf.swap(cur);
    cur.valid = false;
    mark_in_kf = true;
    res.keyframe = true;
  }

  // A keyframe's new points enter the map (overwriting the oldest when full).
  void add_to_map(FrameData& f, int j) {
    if (map_capacity <= 0) return;
    const int i = take_ring_slot();
    MapPoint& mp = map[i];
    mp.p_W = f.T_WC * f.p_C[j];
    mp.desc = f.feats.descriptor(j);
    mp.id = f.lm_id[j];
    mp.level = f.feats.keypoint(j).level;
    mp.stamp = 0;
    mp.sigma_m = 0.0f;
    id_slot[mp.id & id_mask] = i;
    f.map_idx[j] = i;
    f.owned[j] = 1;
  }

  PinholeCamera cam;
  DepthModel depth;
  PinholeK K;
  OrbExtractor extractor;
  int capacity;
  FrameData cur, kf;
  int grid_cols, grid_rows;
  std::unique_ptr<int[]> cell_start, cell_fill, cell_items;
  std::unique_ptr<int[]> best_kf, best_dist;
  std::unique_ptr<Correspondence2D3D[]> corr;
  std::unique_ptr<int[]> corr_cur;
  std::unique_ptr<uint32_t[]> order;
  std::unique_ptr<uint32_t[]> model_inl;  // the motion-model fallback's inliers
  std::unique_ptr<uint8_t[]> area_detected, area_matched;
  std::unique_ptr<WindowObservation[]> obs;
  int n_obs = 0;
  // FeatureMark flags of the last frame's features, by feature index; that
  // frame is kf after it became the keyframe (swapped), else cur.
  std::unique_ptr<uint8_t[]> mark;
  int n_mark = 0;
  bool mark_in_kf = false;
  int map_capacity;
  std::unique_ptr<MapPoint[]> map;
  std::unique_ptr<double[]> map_z, map_sz;  // per map match: measured depth and its sigma
  // Landmark id -> ring slot, direct-mapped (id & id_mask): a cache, checked
  // against the slot's id; a collision only costs a duplicate ring entry.
  std::unique_ptr<int32_t[]> id_slot;
  uint32_t id_mask = 0;
  int map_size = 0;
  int map_next = 0;  // ring cursor: the oldest entry once full
  uint32_t map_stamp = 0;
  uint32_t next_lm_id = 1;
  LonscEstimator lonsc;
  RigidConsensus rigid;
  // 6-DoF tracking: per correspondence the current point (from its depth), and its depth with the sigma.
  std::unique_ptr<Eigen::Vector3d[]> corr_q;
  std::unique_ptr<uint8_t[]> corr_has_q;
  std::unique_ptr<double[]> corr_z, corr_sz;
  CorrespondenceOrderer orderer;
  // Stereo rigs: the row search and its per-feature buffers.
  bool stereo_on;
  double stereo_fb_px_m;  // f * baseline
  StereoMatcher stereo;
  std::unique_ptr<float[]> kp_x, kp_y, disparity;
};

Tracker::Tracker(const Rig& rig, const TrackerOptions& opt) : opt_(opt) {
  const std::string err = opt.validate();
  if (!err.empty()) throw std::invalid_argument("TrackerOptions:\n" + err);
  if (rig.rgb.width <= 0 || rig.rgb.height <= 0 || rig.rgb.fx <= 0 || rig.rgb.fy <= 0)
    throw std::invalid_argument("Tracker: the rig has no camera intrinsics (camera.width_px, fx_px, ...)");
  impl_ = std::make_unique<Impl>(rig, opt);
}

Tracker::~Tracker() = default;

void Tracker::reset() { impl_->kf.valid = false; }
bool Tracker::has_keyframe() const { return impl_->kf.valid; }
int64_t Tracker::keyframe_t_ns() const { return impl_->kf.t_ns; }
int Tracker::num_observations() const { return impl_->n_obs; }
const WindowObservation* Tracker::observations() const { return impl_->obs.get(); }

int Tracker::copy_last_features(FeatureMark* out, int max_n) const {
  const Impl& m = *impl_;
  const FrameData& f = m.mark_in_kf ? m.kf : m.cur;
  const int n = std::min({m.n_mark, f.feats.size(), std::max(max_n, 0)});
  for (int j = 0; j < n; ++j) {
    const OrbKeypoint& kp = f.feats.keypoint(j);
    out[j].x_px = kp.x;
    out[j].y_px = kp.y;
    out[j].flags = m.mark[j];
  }
  return n;
}

int Tracker::copy_map_points(float* xyz, int max_n) const {
  const Impl& m = *impl_;
  if (max_n <= 0 || m.map_size == 0) return 0;
  const int stride = (m.map_size + max_n - 1) / max_n;
  int n = 0;
  for (int i = 0; i < m.map_size && n < max_n; i += stride) {
    const MapPoint& mp = m.map[i];
    if (mp.id == 0) continue;
    xyz[3 * n + 0] = static_cast<float>(mp.p_W.x());
    xyz[3 * n + 1] = static_cast<float>(mp.p_W.y());
    xyz[3 * n + 2] = static_cast<float>(mp.p_W.z());
    ++n;
  }
  return n;
}

bool Tracker::set_keyframe_pose(int64_t t_ns, const Eigen::Isometry3d& T_WC) {
  if (!impl_->kf.valid || impl_->kf.t_ns != t_ns) return false;
  Impl& m = *impl_;
  m.kf.T_WC = T_WC;
  // The points this keyframe put into the map move with it; points it
  // re-found belong to older keyframes and stay where they are.
  for (int j = 0; j < m.kf.feats.size(); ++j) {
    const int32_t i = m.kf.map_idx[j];
    if (m.kf.owned[j] && i >= 0 && m.map[i].id == m.kf.lm_id[j] && m.map[i].sigma_m == 0.0f)
      m.map[i].p_W = T_WC * m.kf.p_C[j];
  }
  return true;
}

Eigen::Isometry3d Tracker::keyframe_pose() const { return impl_->kf.T_WC; }

int Tracker::keyframe_features(KeyframeFeature* out, int capacity) const {
  const Impl& m = *impl_;
  if (!m.kf.valid) return 0;
  const int n = std::min(capacity, m.kf.feats.size());
  for (int j = 0; j < n; ++j) {
    const OrbKeypoint& kp = m.kf.feats.keypoint(j);
    KeyframeFeature& f = out[j];
    f.x_px = kp.x;
    f.y_px = kp.y;
    const Eigen::Vector2d uv = m.cam.undistort_pixel(Eigen::Vector2d(kp.x, kp.y));
    f.u_px = static_cast<float>(uv.x());
    f.v_px = static_cast<float>(uv.y());
    f.depth_m = m.kf.has_depth[j] ? static_cast<float>(m.kf.p_C[j].z()) : 0.0f;
    f.level = kp.level;
    f.landmark_id = m.kf.lm_id[j];
    f.desc = m.kf.feats.descriptor(j);
  }
  return n;
}

void Tracker::apply_map_points(const MapPointUpdate* pts, int n) {
  Impl& m = *impl_;
  if (m.map_capacity <= 0) return;
  for (int k = 0; k < n; ++k) {
    const MapPointUpdate& u = pts[k];
    if (u.landmark_id == 0 || !u.p_W.allFinite()) continue;
    int32_t i = m.find_in_map(u.landmark_id);
    if (i < 0) {
      i = m.take_ring_slot();
      m.map[i].stamp = 0;
      m.id_slot[u.landmark_id & m.id_mask] = i;
    }
    MapPoint& mp = m.map[i];
    mp.id = u.landmark_id;
    mp.p_W = u.p_W;
    mp.desc = u.desc;
    mp.level = u.level;
    mp.sigma_m = std::max(u.sigma_m, 1e-4f);
  }
}

void Tracker::clear_map() {
  Impl& m = *impl_;
  for (int i = 0; i < m.map_size; ++i) m.map[i].id = 0;
  m.map_size = 0;
  m.map_next = 0;
}

const TrackResult& Tracker::track(int64_t t_ns, const ImageView& image, const ImageView& depth,
                                  const Eigen::Isometry3d& T_WC_pred, double pred_sigma_px,
                                  bool rotation_known) {
  return track(t_ns, image, depth, ImageView{}, T_WC_pred, pred_sigma_px, rotation_known);
}

bool Tracker::stereo() const { return impl_->stereo_on; }

const TrackResult& Tracker::track(int64_t t_ns, const ImageView& image, const ImageView& depth,
                                  const ImageView& right, const Eigen::Isometry3d& T_WC_pred,
                                  double pred_sigma_px, bool rotation_known) {
  Impl& m = *impl_;
  result_ = TrackResult{};
  result_.T_WC = T_WC_pred;
  m.n_obs = 0;
  m.n_mark = 0;
  m.mark_in_kf = false;
  if (image.data == nullptr) {
    result_.status = TrackStatus::kNoImage;
    return result_;
  }
  if (m.extractor.extract(image, m.cur.feats) != OrbStatus::kOk) {
    result_.status = TrackStatus::kFeatureError;
    return result_;
  }
  if (m.stereo_on) {
    result_.stereo_no_right = right.data == nullptr;
    result_.stereo_searched = m.stereo_depth(m.cur, image, right);
  } else {
    m.back_project(m.cur, depth, opt_.depth_edge_rel);
  }
  m.cur.t_ns = t_ns;
  std::fill(m.cur.lm_id.get(), m.cur.lm_id.get() + m.cur.feats.size(), 0u);
  std::fill(m.cur.map_idx.get(), m.cur.map_idx.get() + m.cur.feats.size(), -1);
  std::fill(m.cur.owned.get(), m.cur.owned.get() + m.cur.feats.size(), uint8_t{0});
  result_.detected = m.cur.feats.size();
  result_.with_depth = m.cur.with_depth;
  m.n_mark = m.cur.feats.size();
  for (int j = 0; j < m.n_mark; ++j) m.mark[j] = m.cur.has_depth[j] ? FeatureMark::kDepth : uint8_t{0};

  if (!m.kf.valid) {
    if (m.cur.with_depth >= 2 * opt_.min_inliers) {
      m.make_keyframe(opt_, T_WC_pred, result_);
      result_.T_WC = m.kf.T_WC;
      result_.status = TrackStatus::kNewKeyframe;
    } else {
      result_.status = TrackStatus::kTooFewMatches;
    }
    return result_;
  }

  // ---- IMU-predicted projection and circle-window search ------------------
  const Eigen::Isometry3d T_CK_pred = T_WC_pred.inverse() * m.kf.T_WC;
  const Eigen::Matrix3d R_pred = T_CK_pred.linear();
  const Eigen::Vector3d t_pred = T_CK_pred.translation();
  const double radius =
      std::clamp(opt_.search_k_sigma * pred_sigma_px, opt_.search_radius_min_px, opt_.search_radius_max_px);
  result_.search_radius_px = radius;
  const int n = m.match_keyframe(opt_, R_pred, t_pred, radius, result_);
  result_.matched = n;
  if (n < opt_.min_inliers) {
    result_.status = TrackStatus::kTooFewMatches;
    return result_;
  }

  // ---- LONSC with the IMU rotation (or a 6-DoF rigid model without one), ---
  // ---- then Gauss-Newton on the inliers ------------------------------------
  const size_t n_ordered = m.orderer.order(opt_.order, m.corr.get(), static_cast<size_t>(n), m.order.get(),
                                           m.cam.width(), m.cam.height());
  Eigen::Matrix3d R = R_pred;
  Eigen::Vector3d t = t_pred;
  const uint32_t* inl = nullptr;
  size_t n_inl = 0;
  if (rotation_known) {
    const MotionEstimate est = m.lonsc.estimate(R_pred, m.K, m.corr.get(), static_cast<size_t>(n),
                                                n_ordered > 0 ? m.order.get() : nullptr, t_pred);
    result_.motion_status = est.status;
    if (!est.ok() || static_cast<int>(est.num_inliers) < opt_.min_inliers) {
      result_.status = TrackStatus::kMotionFailed;
      result_.inliers = static_cast<int>(est.num_inliers);
      return result_;
    }
    t = est.t;
    const PoseRefineResult ref = refine_pose_gauss_newton(
        &R, &t, m.K, m.corr.get(), static_cast<size_t>(n), m.lonsc.inlier_indices(), est.num_inliers,
        opt_.refine, opt_.refine.rotation_prior_sigma_rad > 0 ? &R_pred : nullptr);
    if (!ref.ok) {
      R = R_pred;
      t = est.t;
    }
    inl = m.lonsc.inlier_indices();
    n_inl = est.num_inliers;
    result_.inlier_rms_px = est.inlier_rms_px;
  } else {
    for (int k = 0; k < n; ++k) {
      const int j = m.corr_cur[k];
      m.corr_has_q[k] = m.cur.has_depth[j];
      m.corr_q[k] = m.cur.p_C[j];
      m.corr_z[k] = m.cur.has_depth[j] ? m.cur.p_C[j].z() : 1.0;
      // No depth: the depth row weighs nothing.
      m.corr_sz[k] =
          m.cur.has_depth[j] ? std::max(0.005, m.depth.sigma_coeff_per_m * m.corr_z[k] * m.corr_z[k]) : 1e9;
    }
    const RigidEstimate est =
        m.rigid.estimate(opt_.rigid_method, m.K, m.corr.get(), m.corr_q.get(), m.corr_has_q.get(),
                         static_cast<size_t>(n), n_ordered > 0 ? m.order.get() : nullptr);
    result_.six_dof = true;
    result_.model_estimates = est.model_estimates;
    result_.motion_status = est.status;
    if (!est.ok() || static_cast<int>(est.num_inliers) < opt_.min_inliers) {
      size_t n_model = 0;
      if (opt_.motion_model_min_inliers > 0 && m.track_motion_model(opt_, n, &R, &t, &n_model)) {
        inl = m.model_inl.get();
        n_inl = n_model;
        result_.motion_model = true;
      } else {
        result_.status = TrackStatus::kMotionFailed;
        result_.inliers = static_cast<int>(est.num_inliers);
        return result_;
      }
    } else {
      R = est.R;
      t = est.t;
      Eigen::Matrix<double, 6, 6> cov;
      if (!refine_pose_rgbd(&R, &t, m.K, m.corr.get(), m.corr_z.get(), m.corr_sz.get(),
                            m.rigid.inlier_indices(), est.num_inliers, opt_.refine.huber_px, &cov)) {
        R = est.R;
        t = est.t;
      }
      inl = m.rigid.inlier_indices();
      n_inl = est.num_inliers;
      result_.inlier_rms_px = est.inlier_rms_px;
    }
  }
  result_.inliers = static_cast<int>(n_inl);
  if (n_inl > 0) {
    double sum2 = 0;
    for (size_t k = 0; k < n_inl; ++k) {
      const Correspondence2D3D& c = m.corr[inl[k]];
      const Eigen::Vector3d q = R * c.p_prev + t;
      if (q.z() <= 0) continue;
      sum2 += (Eigen::Vector2d(m.K.fx * q.x() / q.z() + m.K.cx, m.K.fy * q.y() / q.z() + m.K.cy) - c.u_cur)
                  .squaredNorm();
    }
    result_.refined_rms_px = std::sqrt(sum2 / static_cast<double>(n_inl));
  }
  Eigen::Isometry3d T_CK = Eigen::Isometry3d::Identity();
  T_CK.linear() = R;
  T_CK.translation() = t;
  const Eigen::Isometry3d T_WC = m.kf.T_WC * T_CK.inverse();
  result_.T_WC = T_WC;
  result_.area_ratio = m.area_ratio(opt_, inl, n_inl);
  result_.status = TrackStatus::kTracked;
  m.adopt_tracked_inliers(inl, n_inl);
  if (opt_.far_tracks) m.track_far_points(opt_, R, t, result_);

  const bool stale = 1e-9 * static_cast<double>(t_ns - m.kf.t_ns) > opt_.keyframe_max_interval_s;
  const bool new_kf =
      result_.area_ratio < opt_.keyframe_area_ratio || result_.inliers < opt_.keyframe_min_inliers || stale;
  if (new_kf && m.cur.with_depth >= 2 * opt_.min_inliers) {
    m.make_keyframe(opt_, T_WC, result_);
  }
  return result_;
}

}  // namespace kestrel::core

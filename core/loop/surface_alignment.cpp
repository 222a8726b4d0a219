#include "kestrel/core/surface_alignment.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>

namespace kestrel::core {

void depth_grid_points_normals(const DepthGridShape& shape, const uint16_t* z_mm, double max_step_rel,
                               Eigen::Vector3d* pt, Eigen::Vector3d* n) {
  const int cols = shape.cols, rows = shape.rows, cells = shape.cells();
  for (int c = 0; c < cells; ++c) {
    pt[c] = z_mm[c] > 0 ? shape.point_C(c, z_mm[c]) : Eigen::Vector3d::Zero();
    n[c].setZero();
  }
  for (int y = 1; y + 1 < rows; ++y) {
    for (int x = 1; x + 1 < cols; ++x) {
      const int c = y * cols + x;
      if (z_mm[c] == 0) continue;
      const int l = c - 1, r = c + 1, u = c - cols, d = c + cols;
      const double z = z_mm[c], tol = max_step_rel * z + 20.0;
      bool ok = true;
      for (int o : {l, r, u, d}) ok = ok && z_mm[o] > 0 && std::abs(z_mm[o] - z) <= tol;
      if (!ok) continue;
      Eigen::Vector3d nn = (pt[r] - pt[l]).cross(pt[d] - pt[u]);
      const double len = nn.norm();
      if (!(len > 0)) continue;
      nn /= len;
      if (nn.dot(pt[c]) > 0) nn = -nn;  // towards the camera
      n[c] = nn;
    }
  }
}

void SurfaceAligner::set_shape(const DepthGridShape& shape, double depth_sigma_coeff_per_m) {
  shape_ = shape;
  k_ = depth_sigma_coeff_per_m;
}

SurfaceFit SurfaceAligner::align(const uint16_t* z_q, const Eigen::Isometry3d& T_MC_q, const uint16_t* z_c,
                                 const Eigen::Isometry3d& T_MC_c, const SurfaceAlignOptions& opt) {
  SurfaceView q, c;
  q.z_mm = z_q;
  q.T_MC = T_MC_q;
  c.z_mm = z_c;
  c.T_MC = T_MC_c;
  return align(&q, 1, &c, 1, opt);
}

SurfaceFit SurfaceAligner::align(const SurfaceView* query, int n_query, const SurfaceView* cand, int n_cand,
                                 const SurfaceAlignOptions& opt) {
  SurfaceFit f;
  n_query = std::min(n_query, kMaxViews);
  n_cand = std::min(n_cand, kMaxViews);
  if (!enabled() || n_query < 1 || n_cand < 1 || query[0].z_mm == nullptr || cand[0].z_mm == nullptr) {
    f.failed = "no_grid";
    return f;
  }
  const size_t cells = static_cast<size_t>(shape_.cells());
  c_pt_.resize(cells * static_cast<size_t>(n_cand));
  c_n_.resize(cells * static_cast<size_t>(n_cand));
  Eigen::Isometry3d T_CM_c[kMaxViews];
  Eigen::Matrix3d R_MC_c[kMaxViews];
  int nc = 0;
  for (int v = 0; v < n_cand; ++v) {
    if (cand[v].z_mm == nullptr) continue;
    depth_grid_points_normals(shape_, cand[v].z_mm, opt.normal_max_step_rel, &c_pt_[cells * nc],
                              &c_n_[cells * nc]);
    T_CM_c[nc] = cand[v].T_MC.inverse();
    R_MC_c[nc] = cand[v].T_MC.linear();
    ++nc;
  }
  q_pt_.clear();
  q_n_.clear();
  q_z_.clear();
  for (int v = 0; v < n_query; ++v) {
    const uint16_t* z_q = query[v].z_mm;
    if (z_q == nullptr) continue;
    q_pt_C_.resize(cells);
    q_n_C_.resize(cells);
    depth_grid_points_normals(shape_, z_q, opt.normal_max_step_rel, q_pt_C_.data(), q_n_C_.data());
    for (size_t c = 0; c < cells; ++c) {
      if (z_q[c] == 0) continue;
      q_pt_.push_back(query[v].T_MC * q_pt_C_[c]);
      q_n_.push_back(query[v].T_MC.linear() * q_n_C_[c]);
      q_z_.push_back(z_q[c] * 1e-3);
    }
  }
  f.query_cells = static_cast<int>(q_pt_.size());
  if (f.query_cells < 20) {
    f.failed = "overlap";
    return f;
  }
  // Rotation about the query camera's centre: yaw and translation decouple.
  const Eigen::Vector3d centre = query[0].T_MC.translation();
  const double cos_max = std::cos(opt.max_normal_angle_rad);
  const Eigen::Vector3d ez(0, 0, 1);
  const double cell_rad = static_cast<double>(shape_.width) / shape_.cols / shape_.K.fx;  // one cell's angle
  double yaw = 0;
  Eigen::Vector3d t = Eigen::Vector3d::Zero();

  // One pass over the query: pairs within bound_m (+ a cell's width at the
  // range, which the projective pairing cannot resolve), their normal
  // equations, and the final counts.
  struct Pass {
    Eigen::Matrix4d H = Eigen::Matrix4d::Zero(), A = Eigen::Matrix4d::Zero();
    Eigen::Vector4d b = Eigen::Vector4d::Zero();
    int landed = 0, paired = 0, inliers = 0;
    double sq = 0, lever_sq = 0;
  };
  const auto pass = [&](double bound_m, bool final_pass) {
    Pass s;
    const Eigen::Matrix3d Rz = Eigen::AngleAxisd(yaw, ez).toRotationMatrix();
    for (size_t i = 0; i < q_pt_.size(); ++i) {
      const Eigen::Vector3d a = Rz * (q_pt_[i] - centre);
      const Eigen::Vector3d p = a + centre + t;
      const Eigen::Vector3d n_q_M = Rz * q_n_[i];
      bool landed = false;
      int best_v = -1;
      double best_d = 0, best_r = 0, best_qz = 0;
      Eigen::Vector3d best_n = Eigen::Vector3d::Zero();
      for (int v = 0; v < nc; ++v) {
        const Eigen::Vector3d x = T_CM_c[v] * p;
        const int cell = shape_.cell_of(x);
        const size_t at = cells * static_cast<size_t>(v) + static_cast<size_t>(cell);
        if (cell < 0 || c_pt_[at].z() <= 0) continue;
        const Eigen::Vector3d& q = c_pt_[at];
        const double reach = bound_m + cell_rad * q.z();
        // Behind this view's surface: hidden from it, no evidence either
        // way. In front of it, the view would have seen it: evidence against.
        if (x.z() > q.z() + reach) continue;
        landed = true;
        const Eigen::Vector3d& n = c_n_[at];
        if (n.isZero()) continue;
        const Eigen::Vector3d d = x - q;
        const double dn = d.norm();
        if (dn > reach) continue;
        if (!q_n_[i].isZero() && (T_CM_c[v].linear() * n_q_M).dot(n) < cos_max) continue;
        if (best_v >= 0 && dn >= best_d) continue;
        best_v = v;
        best_d = dn;
        best_r = n.dot(d);
        best_qz = q.z();
        best_n = n;
      }
      if (!landed) continue;
      ++s.landed;
      if (best_v < 0) continue;
      const double r = best_r;
      const double sigma = std::hypot(sigma_m(q_z_[i]), sigma_m(best_qz));
      const Eigen::Vector3d n_M = R_MC_c[best_v] * best_n;
      Eigen::Vector4d J;
      J << n_M.dot(ez.cross(a)), n_M;
      ++s.paired;
      const bool inlier = std::abs(r) <= opt.inlier_floor_m + 3.0 * sigma;
      if (final_pass && !inlier) continue;
      s.inliers += inlier ? 1 : 0;
      const double e = std::abs(r) / sigma;
      const double w = (e <= 2.0 ? 1.0 : 2.0 / e) / (sigma * sigma);  // Huber at 2 sigma
      s.H += w * J * J.transpose();
      s.b += w * J * r;
      s.sq += r * r;
      s.lever_sq += a.head<2>().squaredNorm();
      s.A += J * J.transpose();  // yaw rescaled below, once the lever is known
    }
    return s;
  };
  const int iters = std::max(1, opt.iterations);
  for (int it = 0; it < iters; ++it) {
    const double frac = iters > 1 ? static_cast<double>(it) / (iters - 1) : 1.0;
    const double bound = opt.max_pair_m * std::pow(opt.min_pair_m / opt.max_pair_m, frac);
    const Pass s = pass(bound, false);
    // Where the map's poses pair less than half the overlap asked for even at
    // the widest bound, the place is not there: stop before iterating.
    if (s.paired < 20 || (it == 0 && s.landed < opt.min_overlap * f.query_cells)) {
      f.failed = "overlap";
      f.paired = s.paired;
      f.overlap = static_cast<double>(s.landed) / f.query_cells;
      return f;
    }
    const Eigen::LDLT<Eigen::Matrix4d> ldlt(s.H);
    if (ldlt.info() != Eigen::Success) {
      f.failed = "solve";
      return f;
    }
    const Eigen::Vector4d delta = -ldlt.solve(s.b);
    if (!delta.allFinite()) {
      f.failed = "solve";
      return f;
    }
    yaw += delta(0);
    t += delta.tail<3>();
  }
  const Pass s = pass(opt.min_pair_m, true);
  f.landed = s.landed;
  f.paired = s.paired;
  f.inliers = s.inliers;
  f.overlap = static_cast<double>(s.landed) / f.query_cells;
  // Of the cells in the candidate's view: occlusion and cells without a
  // normal keep a true revisit below 1; a wrong alignment pairs few.
  f.inlier_share = s.landed > 0 ? static_cast<double>(s.inliers) / s.landed : 0.0;
  f.rms_m = s.inliers > 0 ? std::sqrt(s.sq / s.inliers) : 0.0;
  if (s.inliers >= 20) {
    // Yaw as the motion it gives at the points' lever: metres, like the rest.
    const double lever = std::sqrt(s.lever_sq / s.inliers);
    Eigen::Matrix4d A = s.A / s.inliers;
    if (lever > 0) {
      A.row(0) /= lever;
      A.col(0) /= lever;
    }
    f.observability =
        Eigen::SelfAdjointEigenSolver<Eigen::Matrix4d>(A, Eigen::EigenvaluesOnly).eigenvalues()(0);
  }
  const Eigen::Matrix3d Rz = Eigen::AngleAxisd(yaw, ez).toRotationMatrix();
  f.correction.linear() = Rz;
  f.correction.translation() = centre + t - Rz * centre;
  if (f.overlap < opt.min_overlap) {
    f.failed = "overlap";
    return f;
  }
  // The pairing sees max_pair_m around the seed; a solution further away
  // slid along something the gates below may not catch (V2_02: 44 cm along a
  // wall at an observability of 0.0101, where the truth was 1 cm).
  if (t.norm() > opt.max_pair_m ||
      std::abs(yaw) * std::sqrt(s.lever_sq / std::max(1, s.inliers)) > opt.max_pair_m) {
    f.failed = "moved";
    return f;
  }
  if (f.inlier_share < opt.min_inlier_share) {
    f.failed = "inliers";
    return f;
  }
  if (f.observability < opt.min_observability) {
    f.failed = "observability";
    return f;
  }
  // Covariance of (yaw, t) about the centre, then about M's origin as
  // PlaceFit has it: t_o = centre + t - Rz centre.
  Eigen::Matrix4d cov = s.H.inverse();
  if (!cov.allFinite()) {
    f.failed = "solve";
    return f;
  }
  if (opt.independent_pairs > 0 && s.inliers > opt.independent_pairs)
    cov *= static_cast<double>(s.inliers) / opt.independent_pairs;
  Eigen::Matrix4d B = Eigen::Matrix4d::Identity();
  B.block<3, 1>(1, 0) = -ez.cross(Rz * centre);
  f.cov = B * cov * B.transpose();
  f.ok = true;
  f.failed = "";
  return f;
}

}  // namespace kestrel::core

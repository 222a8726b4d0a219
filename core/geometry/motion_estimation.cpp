#include "kestrel/core/motion_estimation.hpp"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <limits>
#include <ostream>

namespace kestrel::core {

const char* to_string(MotionStatus s) {
  switch (s) {
    case MotionStatus::kOk:
      return "ok";
    case MotionStatus::kTooFewCorrespondences:
      return "too_few_correspondences";
    case MotionStatus::kDegenerate:
      return "degenerate";
    case MotionStatus::kNoConsistentRun:
      return "no_consistent_run";
    case MotionStatus::kTooFewInliers:
      return "too_few_inliers";
  }
  return "unknown";
}

double TranslationNormalEquations::pixel_spread2() const {
  if (!(sum_w > 0) || !(A > 0) || !(B > 0)) return 0.0;
  return (E - C * C / A - D * D / B) / sum_w;
}

bool TranslationNormalEquations::solve(Eigen::Vector3d* t, double min_spread2_px2) const {
  if (rows < 2 || !(A > 0) || !(B > 0)) return false;
  // LDL^T of [A 0 C; 0 B D; C D E]: L = [1 0 0; 0 1 0; C/A D/B 1],
  // D = diag(A, B, E - C^2/A - D^2/B). No pivoting needed: A, B > 0 always.
  const double iA = 1.0 / A, iB = 1.0 / B;
  const double l20 = C * iA, l21 = D * iB;
  const double d2 = E - C * l20 - D * l21;            // = sum_w * pixel_spread2()
  if (!(d2 > min_spread2_px2 * sum_w)) return false;  // also catches NaN
  const double x2 = (g.z() - l20 * g.x() - l21 * g.y()) / d2;
  const Eigen::Vector3d x(g.x() * iA - l20 * x2, g.y() * iB - l21 * x2, x2);
  if (!x.allFinite()) return false;
  *t = x;
  return true;
}

namespace {

double sigma_of(const Correspondence2D3D& c) { return c.sigma_px > 0.0f ? double(c.sigma_px) : 1.0; }

template <class F>
void for_each_selected(const Correspondence2D3D* c, std::size_t n, const uint32_t* idx, F&& f) {
  for (std::size_t k = 0; k < n; ++k) {
    const std::size_t i = idx ? idx[k] : k;
    if (correspondence_usable(c[i])) f(c[i]);
  }
}

}  // namespace

MotionStatus translation_least_squares(const Eigen::Matrix3d& R, const PinholeK& K,
                                       const Correspondence2D3D* c, std::size_t n, Eigen::Vector3d* t_out,
                                       const uint32_t* idx) {
  TranslationNormalEquations ne;
  for_each_selected(c, n, idx, [&](const Correspondence2D3D& ci) { ne.add(R * ci.p_prev, ci.u_cur, K); });
  if (ne.rows < 2) return MotionStatus::kTooFewCorrespondences;
  return ne.solve(t_out) ? MotionStatus::kOk : MotionStatus::kDegenerate;
}

MotionStatus translation_least_squares_weighted(const Eigen::Matrix3d& R, const PinholeK& K,
                                                const Correspondence2D3D* c, std::size_t n,
                                                Eigen::Vector3d* t_out, const uint32_t* idx) {
  Eigen::Vector3d t0;
  const MotionStatus s = translation_least_squares(R, K, c, n, &t0, idx);
  if (s != MotionStatus::kOk) return s;
  TranslationNormalEquations ne;
  for_each_selected(c, n, idx, [&](const Correspondence2D3D& ci) {
    const Eigen::Vector3d Rp = R * ci.p_prev;
    // The algebraic residual is z_cur times the pixel error; dividing by z_cur
    // turns it back into pixels. Clamp keeps a wild first solve from blowing up a weight.
    const double z = std::max(Rp.z() + t0.z(), 0.05);
    const double s_px = sigma_of(ci);
    ne.add(Rp, ci.u_cur, K, 1.0 / (s_px * s_px * z * z));
  });
  return ne.solve(t_out) ? MotionStatus::kOk : MotionStatus::kDegenerate;
}

// ---------------------------------------------------------------------------

namespace {
Eigen::Matrix3d skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d S;
  S << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return S;
}
}  // namespace

Eigen::Matrix3d so3_exp(const Eigen::Vector3d& w) {
  const double th = w.norm();
  if (th < 1e-12) return Eigen::Matrix3d::Identity() + skew(w);
  return Eigen::AngleAxisd(th, w / th).toRotationMatrix();
}

Eigen::Vector3d so3_log(const Eigen::Matrix3d& R) {
  const Eigen::AngleAxisd aa(R);
  return aa.angle() * aa.axis();
}

bool reprojection_residual(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const PinholeK& K,
                           const Eigen::Vector3d& p_prev, const Eigen::Vector2d& u, Eigen::Vector2d* r,
                           Eigen::Matrix<double, 2, 6>* J) {
  const Eigen::Vector3d Rp = R * p_prev;
  const Eigen::Vector3d p = Rp + t;
  if (!(p.z() > 1e-9)) return false;
  const double iz = 1.0 / p.z();
  (*r) << K.fx * p.x() * iz + K.cx - u.x(), K.fy * p.y() * iz + K.cy - u.y();
  if (J) {
    Eigen::Matrix<double, 2, 3> Jproj;
    Jproj << K.fx * iz, 0.0, -K.fx * p.x() * iz * iz, 0.0, K.fy * iz, -K.fy * p.y() * iz * iz;
    // Exp(d) R p ~ R p + d x R p = R p - [R p]x d.
    J->leftCols<3>().noalias() = -Jproj * skew(Rp);
    J->rightCols<3>() = Jproj;
  }
  return true;
}

Eigen::Vector3d rotation_prior_residual(const Eigen::Matrix3d& R, const Eigen::Matrix3d& R_prior,
                                        Eigen::Matrix3d* J) {
  Eigen::Vector3d r = so3_log(R * R_prior.transpose());
  if (J) {
    // d Log(Exp(d) E) / dd = Jl^-1(Log E).
    const double th = r.norm();
    const Eigen::Matrix3d S = skew(r);
    double c2;
    if (th < 1e-5) {
      c2 = 1.0 / 12.0 + th * th / 720.0;
    } else {
      c2 = 1.0 / (th * th) - (1.0 + std::cos(th)) / (2.0 * th * std::sin(th));
    }
    *J = Eigen::Matrix3d::Identity() - 0.5 * S + c2 * S * S;
  }
  return r;
}

namespace {

struct GnSystem {
  Eigen::Matrix<double, 6, 6> H;
  Eigen::Matrix<double, 6, 1> g;
  double cost = 0;
  int used = 0;
};

// Builds (or, with build=false, only evaluates the cost of) the robustified system.
GnSystem gn_system(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const PinholeK& K,
                   const Correspondence2D3D* c, std::size_t n, const uint32_t* idx, std::size_t n_idx,
                   const PoseRefineOptions& opt, const Eigen::Matrix3d* R_prior, bool build) {
  GnSystem s;
  s.H.setZero();
  s.g.setZero();
  s.cost = 0;
  s.used = 0;
  const std::size_t m = idx ? n_idx : n;
  Eigen::Vector2d r;
  Eigen::Matrix<double, 2, 6> J;
  for (std::size_t k = 0; k < m; ++k) {
    const Correspondence2D3D& ci = c[idx ? idx[k] : k];
    if (!correspondence_usable(ci)) continue;
    if (!reprojection_residual(R, t, K, ci.p_prev, ci.u_cur, &r, build ? &J : nullptr)) continue;
    const double inv_s = 1.0 / sigma_of(ci);
    const double e = r.norm() * inv_s;
    double w = 1.0;
    if (opt.huber_px > 0 && e > opt.huber_px) {
      w = opt.huber_px / e;
      s.cost += opt.huber_px * e - 0.5 * opt.huber_px * opt.huber_px;
    } else {
      s.cost += 0.5 * e * e;
    }
    ++s.used;
    if (build) {
      const double wi = w * inv_s * inv_s;
      // Lower triangle only (LDLT reads nothing else), written out: Eigen's
      // rankUpdate on a 6x2 goes through its generic path and is 3x slower.
      const Eigen::Matrix<double, 2, 6> wJ = wi * J;
      for (int a = 0; a < 6; ++a)
        for (int b = 0; b <= a; ++b) s.H(a, b) += wJ(0, a) * J(0, b) + wJ(1, a) * J(1, b);
      s.g.noalias() += wi * J.transpose() * r;
    }
  }
  if (R_prior && opt.rotation_prior_sigma_rad > 0) {
    Eigen::Matrix3d Jr;
    const Eigen::Vector3d rr = rotation_prior_residual(R, *R_prior, build ? &Jr : nullptr);
    const double ip = 1.0 / (opt.rotation_prior_sigma_rad * opt.rotation_prior_sigma_rad);
    s.cost += 0.5 * ip * rr.squaredNorm();
    if (build) {
      s.H.topLeftCorner<3, 3>().noalias() += ip * Jr.transpose() * Jr;
      s.g.head<3>().noalias() += ip * Jr.transpose() * rr;
    }
  }
  return s;
}

}  // namespace

PoseRefineResult refine_pose_gauss_newton(Eigen::Matrix3d* R, Eigen::Vector3d* t, const PinholeK& K,
                                          const Correspondence2D3D* c, std::size_t n, const uint32_t* idx,
                                          std::size_t n_idx, const PoseRefineOptions& opt,
                                          const Eigen::Matrix3d* R_prior) {
  PoseRefineResult res;
  Eigen::Matrix3d R_cur = *R;
  Eigen::Vector3d t_cur = *t;
  GnSystem s = gn_system(R_cur, t_cur, K, c, n, idx, n_idx, opt, R_prior, true);
  res.cost_initial = res.cost_final = s.cost;
  if (s.used < 3) return res;  // 6 unknowns need at least 3 points
  for (int it = 0; it < opt.max_iterations; ++it) {
    const Eigen::LDLT<Eigen::Matrix<double, 6, 6>> ldlt(s.H);
    if (ldlt.info() != Eigen::Success || !ldlt.isPositive() || !(ldlt.rcond() > 1e-14)) break;
    const Eigen::Matrix<double, 6, 1> d = -ldlt.solve(s.g);
    if (!d.allFinite()) break;
    const Eigen::Matrix3d R_new = so3_exp(d.head<3>()) * R_cur;
    const Eigen::Vector3d t_new = t_cur + d.tail<3>();
    // Building the system at the candidate also yields its cost: one pass
    // per iteration; a rejected step wastes one build and ends the loop.
    GnSystem s_new = gn_system(R_new, t_new, K, c, n, idx, n_idx, opt, R_prior, true);
    ++res.iterations;
    // Plain GN with a monotonicity guard: at 30 Hz the start is within a few
    // px, so a rejected step means "converged", not "needs damping".
    if (!(s_new.cost <= s.cost) || s_new.used < s.used) break;
    R_cur = R_new;
    t_cur = t_new;
    s = s_new;
    if (d.norm() < opt.min_step) break;
  }
  res.ok = true;  // a system was formed; R, t hold the best iterate (maybe the input)
  res.cost_final = s.cost;
  *R = R_cur;
  *t = t_cur;
  return res;
}

std::ostream& operator<<(std::ostream& os, const ConsistencyTest& o) {
  return os << "consistency{threshold_px=" << o.threshold_px << " scale_by_sigma=" << o.scale_by_sigma
            << " reference_sigma_px=" << o.reference_sigma_px << " min_depth_m=" << o.min_depth_m << "}";
}

std::ostream& operator<<(std::ostream& os, const PoseRefineOptions& o) {
  return os << "pose_refine{max_iterations=" << o.max_iterations << " huber_px=" << o.huber_px
            << " rotation_prior_sigma_rad=" << o.rotation_prior_sigma_rad << " min_step=" << o.min_step
            << "}";
}

}  // namespace kestrel::core

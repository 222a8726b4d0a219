// Frame-to-frame motion from 2D-3D correspondences with the rotation given by
// the IMU (paper 000, "IMU accelerated pose calculation", eq. 2-3).
//
// Convention: a correspondence pairs a 3D point p_prev in the PREVIOUS camera
// frame with its undistorted pixel u_cur in the CURRENT frame. The motion
// (R, t) maps previous-camera coordinates into current-camera coordinates,
//   p_cur = R * p_prev + t,      lambda * [u_cur; 1] = K * p_cur,
// i.e. R = R_CcCp, t = p_CcCp in docs/frames.md terms (C_c current camera,
// C_p previous camera). With the IMU: R_CcCp = R_CB * R_BcBp * R_BC.
//
// Everything here is allocation-free: functions work on caller memory,
// classes (lonsc.hpp) size their buffers once at construction.
// Derivations and measurements: docs/lonsc.md.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <iosfwd>
#include <limits>

namespace kestrel::core {

struct PinholeK {
  double fx = 0, fy = 0, cx = 0, cy = 0;  // [px]
};

struct Correspondence2D3D {
  Eigen::Vector3d p_prev = Eigen::Vector3d::Zero();  // 3D point in the previous camera frame [m]
  Eigen::Vector2d u_cur = Eigen::Vector2d::Zero();   // undistorted pixel in the current frame [px]
  // 1-sigma reprojection noise of this correspondence [px]: keypoint noise plus,
  // if the caller wants it, the depth uncertainty projected into the image.
  // Weights are 1/sigma^2; must be > 0 (non-positive values are treated as 1 px).
  float sigma_px = 1.0f;
  // Matcher cost, lower = more reliable (Hamming distance, distance ratio...).
  // Only used to ORDER correspondences for LONSC (CorrespondenceOrder::kByMatchCost).
  float match_cost = 0.0f;
  uint32_t id = 0;  // caller's feature id, carried through untouched
};

// Outcome of a solve, counted by the caller; never thrown.
enum class MotionStatus : uint8_t {
  kOk = 0,
  kTooFewCorrespondences,  // fewer than 2 usable correspondences
  kDegenerate,             // normal equations rank-deficient (e.g. all pixels coincide)
  kNoConsistentRun,        // LONSC: no run of consecutive consistent correspondences long enough
  kTooFewInliers,          // final inlier set below min_inliers
};
const char* to_string(MotionStatus s);

// ---------------------------------------------------------------------------
// Translation given R (paper eq. 3).
//
// Each correspondence gives two equations linear in t (docs/lonsc.md):
//   [fx  0  cx-u] t = (u-cx) r3'p - fx r1'p
//   [ 0 fy  cy-v] t = (v-cy) r3'p - fy r2'p
// Their residual equals z_cur * (reprojection error in px), so the plain
// least squares (the paper's) weights far points by their depth squared.
// The weighted variant divides by sigma_px * z_cur (z_cur from a first plain
// solve), which makes it the maximum-likelihood t for Gaussian pixel noise.

// Accumulates the 3x3 normal equations H t = g; no allocation. H has the
// fixed pattern [A 0 C; 0 B D; C D E] (the two rows of a correspondence never
// couple t_x with t_y), so it is kept as five sums and solved by a closed-form
// LDL^T. Its last pivot is E - C^2/A - D^2/B = sum(w) * (weighted variance of
// the pixels u_i): t_z is observable exactly when the pixels are spread out,
// which is the only way 2+ correspondences can be degenerate (docs/lonsc.md).
struct TranslationNormalEquations {
  double A = 0, B = 0, C = 0, D = 0, E = 0;  // H entries
  Eigen::Vector3d g = Eigen::Vector3d::Zero();
  double sum_w = 0;
  int rows = 0;  // correspondences added

  void clear() { *this = TranslationNormalEquations{}; }
  // Rp = R * p_prev (precomputed by callers that test many t for one R).
  void add(const Eigen::Vector3d& Rp, const Eigen::Vector2d& u, const PinholeK& K, double w = 1.0) {
    const double du = u.x() - K.cx, dv = u.y() - K.cy;
    const double ba = du * Rp.z() - K.fx * Rp.x();  // right-hand sides of eq. 3
    const double bb = dv * Rp.z() - K.fy * Rp.y();
    A += w * K.fx * K.fx;
    B += w * K.fy * K.fy;
    C -= w * K.fx * du;
    D -= w * K.fy * dv;
    E += w * (du * du + dv * dv);
    g.x() += w * K.fx * ba;
    g.y() += w * K.fy * bb;
    g.z() -= w * (du * ba + dv * bb);
    sum_w += w;
    ++rows;
  }
  Eigen::Matrix3d normal_matrix() const {
    Eigen::Matrix3d H;
    H << A, 0, C, 0, B, D, C, D, E;
    return H;
  }
  // Weighted variance of the pixels (x and y summed) [px^2]: the t_z pivot / sum(w).
  double pixel_spread2() const;
  // Solves H t = g; false (t untouched) when fewer than 2 rows or the pixel
  // spread is below min_spread2_px2 (rank-deficient).
  bool solve(Eigen::Vector3d* t, double min_spread2_px2 = 1e-9) const;
};

// Plain least squares of eq. 3 over c[0..n) (or over c[idx[k]], k < n, when idx
// is given). Returns kOk, kTooFewCorrespondences or kDegenerate.
MotionStatus translation_least_squares(const Eigen::Matrix3d& R, const PinholeK& K,
                                       const Correspondence2D3D* c, std::size_t n, Eigen::Vector3d* t_out,
                                       const uint32_t* idx = nullptr);
// Weighted: w_i = 1 / (sigma_px_i * z_cur_i)^2, z_cur_i = r3'p_i + t_z of a first plain solve.
MotionStatus translation_least_squares_weighted(const Eigen::Matrix3d& R, const PinholeK& K,
                                                const Correspondence2D3D* c, std::size_t n,
                                                Eigen::Vector3d* t_out, const uint32_t* idx = nullptr);

// ---------------------------------------------------------------------------
// Consistency of (R, t) with a correspondence: the reprojection of R p + t
// lands within the threshold of u, in front of the camera.

struct ConsistencyTest {
  double threshold_px = 3.0;  // reprojection error bound at sigma_px == reference_sigma_px
  // When true the bound scales with sigma_px / reference_sigma_px (e.g. a
  // caller that folds depth uncertainty into sigma_px gets looser bounds on
  // uncertain points). Off by default: at 30 Hz baselines depth noise projects
  // to well under 0.1 px (docs/lonsc.md).
  bool scale_by_sigma = false;
  double reference_sigma_px = 1.0;
  double min_depth_m = 0.05;  // p_cur.z below this counts as behind the camera

  // Squared bound for one correspondence.
  double threshold2(const Correspondence2D3D& c) const {
    double thr = threshold_px;
    if (scale_by_sigma && c.sigma_px > 0.0f && reference_sigma_px > 0.0)
      thr *= c.sigma_px / reference_sigma_px;
    return thr * thr;
  }
  // Rp = R * p_prev. err2_px2 (optional) receives the squared error (infinity behind the camera).
  // Inline: the inner loop of both LONSC and RANSAC.
  bool consistent(const Eigen::Vector3d& Rp, const Eigen::Vector3d& t, const PinholeK& K,
                  const Correspondence2D3D& c, double* err2_px2 = nullptr) const {
    const Eigen::Vector3d p = Rp + t;
    if (!(p.z() > min_depth_m)) {
      if (err2_px2) *err2_px2 = std::numeric_limits<double>::infinity();
      return false;
    }
    const double iz = 1.0 / p.z();
    const double du = K.fx * p.x() * iz + K.cx - c.u_cur.x();
    const double dv = K.fy * p.y() * iz + K.cy - c.u_cur.y();
    const double e2 = du * du + dv * dv;
    if (err2_px2) *err2_px2 = e2;
    return e2 < threshold2(c);  // NaN compares false: inconsistent
  }
  bool consistent(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const PinholeK& K,
                  const Correspondence2D3D& c, double* err2_px2 = nullptr) const {
    return consistent(Eigen::Vector3d(R * c.p_prev), t, K, c, err2_px2);
  }
};

// True when the correspondence carries finite numbers, p_prev in front of the
// previous camera, sigma usable. Unusable ones are never consistent.
inline bool correspondence_usable(const Correspondence2D3D& c) {
  return c.p_prev.allFinite() && c.u_cur.allFinite() && c.p_prev.z() > 0.0 && std::isfinite(c.sigma_px);
}

// ---------------------------------------------------------------------------
// Gauss-Newton refinement of (R, t) on reprojection errors (6 DoF).
// Perturbation: R <- Exp(dtheta) * R (left, in the current camera frame),
// t <- t + dt; parameter order [dtheta(3), dt(3)].

// r = pi(K (R p + t)) - u [px], J = dr/d[dtheta, dt] (2x6). False (r, J
// untouched) when the point is not in front of the camera (z < 1e-9).
bool reprojection_residual(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const PinholeK& K,
                           const Eigen::Vector3d& p_prev, const Eigen::Vector2d& u, Eigen::Vector2d* r,
                           Eigen::Matrix<double, 2, 6>* J = nullptr);

// Rotation prior r = Log(R * R_prior^T) [rad]; J = dr/ddtheta = Jl^-1(r).
Eigen::Vector3d rotation_prior_residual(const Eigen::Matrix3d& R, const Eigen::Matrix3d& R_prior,
                                        Eigen::Matrix3d* J = nullptr);

struct PoseRefineOptions {
  int max_iterations = 4;
  double huber_px = 2.0;  // Huber threshold on the whitened error; <= 0: plain least squares
  // > 0 adds ||Log(R R_imu^T)||^2 / sigma^2: keeps R near the IMU rotation when
  // few inliers (or a degenerate geometry) leave it weakly observed. 0: off.
  double rotation_prior_sigma_rad = 0.0;
  double min_step = 1e-7;  // stop when |delta| falls below (rad / m): well under the noise
};

struct PoseRefineResult {
  bool ok = false;  // false: fewer than 3 usable inliers or a singular system (R, t untouched)
  int iterations = 0;
  double cost_initial = 0, cost_final = 0;  // 0.5 * sum robustified whitened squared errors
};

// Refines R, t in place on c[idx[k]], k < n_idx (all of c[0..n) when idx is null).
PoseRefineResult refine_pose_gauss_newton(Eigen::Matrix3d* R, Eigen::Vector3d* t, const PinholeK& K,
                                          const Correspondence2D3D* c, std::size_t n, const uint32_t* idx,
                                          std::size_t n_idx, const PoseRefineOptions& opt = {},
                                          const Eigen::Matrix3d* R_prior = nullptr);

// SO(3) helpers (rotation vector <-> matrix).
Eigen::Matrix3d so3_exp(const Eigen::Vector3d& w);
Eigen::Vector3d so3_log(const Eigen::Matrix3d& R);

std::ostream& operator<<(std::ostream& os, const ConsistencyTest& o);
std::ostream& operator<<(std::ostream& os, const PoseRefineOptions& o);

}  // namespace kestrel::core

// Local bundle adjustment of keyframe poses and map points: reprojection plus
// measured depth per observation (Huber), and a gravity prior on roll and
// pitch. Two solvers of one problem: ours (Levenberg-Marquardt with the points
// eliminated by a Schur complement and analytic Jacobians) and Ceres, kept as
// the reference that tests/map/test_bundle_adjustment.cpp checks ours against.
// Ours exists because the mapping thread spent ~95 % of its time in Ceres,
// most of it building the problem, differentiating with jets and a dynamic-size
// Schur eliminator: the same work is a few fixed-size loops here.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <vector>

#include "kestrel/core/motion_estimation.hpp"

namespace kestrel::core {

struct BaPose {
  Eigen::Matrix3d R_CM = Eigen::Matrix3d::Identity();  // p_C = R_CM p_M + t_CM
  Eigen::Vector3d t_CM = Eigen::Vector3d::Zero();
  bool fixed = false;
  bool has_gravity = false;
  Eigen::Vector3d g_C = Eigen::Vector3d::Zero();  // M's down axis (0, 0, -1) as the odometry saw it in C
};

struct BaObservation {
  int32_t pose = 0, point = 0;
  double u_px = 0, v_px = 0;
  double depth_m = 0;  // <= 0: no depth, reprojection only
  double inv_sigma_px = 1, inv_sigma_z = 0;
  bool enabled = true;  // false: left out of the solve (an outlier)
};

// Keyframe b seen from keyframe a (camera frames) as the odometry measured
// it: a factor that holds keyframes together where they share few points
// (the global BA's; the local BA has none). Whitened: rotation
// Log(R_ab^-1 R_CaCb) x inv_sigma_rad, translation (t_CaCb - t_ab) x inv_sigma_m.
struct BaRelativePose {
  int32_t a = 0, b = 0;
  Eigen::Matrix3d R_ab = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t_ab = Eigen::Vector3d::Zero();
  double inv_sigma_rad = 0, inv_sigma_m = 0;
};

struct BaProblem {
  PinholeK K;
  double huber = 2.8;            // on the whitened error of one observation
  double gravity_inv_sigma = 0;  // 1 / sigma [1/rad]; 0: no gravity prior
  std::vector<BaPose> poses;
  std::vector<Eigen::Vector3d> points_M;
  std::vector<BaObservation> obs;
  std::vector<BaRelativePose> relative;
};

struct BaResult {
  bool usable = false;
  int iterations = 0;                       // solver iterations, accepted and rejected steps alike
  double initial_cost = 0, final_cost = 0;  // 1/2 sum of Huber(chi2) + gravity terms
};

struct BaSparse;  // bundle_adjustment.cpp: the sparse reduced system

// Reusable work space: the mapping thread keeps one so that its vectors keep
// their capacity from keyframe to keyframe. The solver still allocates a
// little (the LDLT, the reduced system when its size changes): the mapping
// thread is not real time.
struct BaScratch {
  // The reduced camera system is solved dense up to this many free poses and
  // sparse (a simplicial LDLT on the covisibility pattern) above: a local BA's
  // 9 keyframes stay dense and bit for bit what they were; a global BA's
  // hundreds would make a dense system of (6n)^2 doubles and an O(n^3) solve.
  int sparse_from_free_poses = 40;
  std::vector<int32_t> free_index, by_point, point_begin, cursor, free_of;
  std::vector<Eigen::Matrix<double, 6, 3>> W;
  std::vector<Eigen::Matrix3d> V, V_inv;
  std::vector<Eigen::Vector3d> g_point, d_point, points_old;
  std::vector<Eigen::Matrix<double, 6, 6>> H_diag;  // observations and gravity touch only a pose's own block
  std::vector<Eigen::Matrix<double, 6, 6>> H_rel;   // per relative-pose factor: the (a, b) block
  std::shared_ptr<BaSparse> sparse;
  Eigen::MatrixXd S;
  Eigen::VectorXd g, b, dx;
  std::vector<Eigen::Matrix3d> R_old;
  std::vector<Eigen::Vector3d> t_old;
};

// Whitened squared error of one observation at the problem's current values.
double ba_chi2(const BaProblem& p, const BaObservation& o);
// 1/2 sum of the robust costs, as Ceres counts it (+ the relative-pose factors' squares).
double ba_cost(const BaProblem& p);
// One observation's whitened residual (u, v, depth; the depth row is zero
// without depth) and its Jacobians under the left perturbation (R <- Exp(dtheta) R,
// t <- t + dt; pose columns [dtheta, dt]), exactly as the solver linearises it.
void ba_observation_residual(const BaProblem& p, const BaObservation& o, Eigen::Vector3d* r,
                             Eigen::Matrix<double, 3, 6>* J_pose, Eigen::Matrix3d* J_point);
// The gravity prior of a pose, (-R_CM e_z - g_C) * gravity_inv_sigma, and its
// Jacobian in dtheta (the prior does not depend on t_CM).
Eigen::Vector3d ba_gravity_residual(const BaProblem& p, const BaPose& P, Eigen::Matrix3d* J_rot = nullptr);
// A relative-pose factor's whitened residual (rotation, translation) and its
// Jacobians under each pose's left perturbation (R <- Exp(dtheta) R, t <- t + dt).
void ba_relative_residual(const BaProblem& p, const BaRelativePose& e, Eigen::Matrix<double, 6, 1>* r,
                          Eigen::Matrix<double, 6, 6>* J_a, Eigen::Matrix<double, 6, 6>* J_b);

BaResult solve_bundle_adjustment(BaProblem& p, int max_iterations, BaScratch& scratch);
BaResult solve_bundle_adjustment_ceres(BaProblem& p, int max_iterations);

}  // namespace kestrel::core

// The reference solver: the same problem through Ceres (autodiff, quaternion
// manifold, dense Schur), every factor differentiated from its own code here.
// `map: ba_solver: ceres` runs it in the mapping thread.
#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <array>

#include "kestrel/core/bundle_adjustment.hpp"

namespace kestrel::core {

namespace {

// Pose block: q_CM (x, y, z, w) and t_CM, so that p_C = R_CM p_M + t_CM.
template <int kRows>
struct ObservationCost {
  ObservationCost(const PinholeK& K, const BaObservation& o) : K_(K), o_(o) {}
  template <typename T>
  bool operator()(const T* q, const T* t, const T* p, T* r) const {
    const Eigen::Quaternion<T> Q(q[3], q[0], q[1], q[2]);
    const Eigen::Matrix<T, 3, 1> P(p[0], p[1], p[2]);
    const Eigen::Matrix<T, 3, 1> c = Q * P + Eigen::Matrix<T, 3, 1>(t[0], t[1], t[2]);
    const T z = c.z() < T(1e-3) ? T(1e-3) : c.z();
    r[0] = (T(K_.fx) * c.x() / z + T(K_.cx) - T(o_.u_px)) * T(o_.inv_sigma_px);
    r[1] = (T(K_.fy) * c.y() / z + T(K_.cy) - T(o_.v_px)) * T(o_.inv_sigma_px);
    if (kRows == 3) r[2] = (c.z() - T(o_.depth_m)) * T(o_.inv_sigma_z);
    return true;
  }
  PinholeK K_;
  BaObservation o_;
};

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

// A relative-pose factor (a loop closure in global bundle adjustment): the
// whitened [Log(R_ab^T R_ab_now); t_ab_now - t_ab] with T_ab_now = T_CaM
// T_CbM^-1, differentiated by Ceres from this code alone, so the cross-check
// tests our analytic Jacobians (ba_relative_residual) too.
struct RelativePoseCost {
  explicit RelativePoseCost(const BaRelativePose& e) : e_(e), q_ab_(e.R_ab) {}
  template <typename T>
  bool operator()(const T* qa, const T* ta, const T* qb, const T* tb, T* r) const {
    const Eigen::Quaternion<T> Qa(qa[3], qa[0], qa[1], qa[2]), Qb(qb[3], qb[0], qb[1], qb[2]);
    const Eigen::Quaternion<T> Q = Qa * Qb.conjugate();
    const Eigen::Matrix<T, 3, 1> t =
        Eigen::Matrix<T, 3, 1>(ta[0], ta[1], ta[2]) - Q * Eigen::Matrix<T, 3, 1>(tb[0], tb[1], tb[2]);
    const Eigen::Quaternion<T> E = q_ab_.conjugate().cast<T>() * Q;
    const T e_wxyz[4] = {E.w(), E.x(), E.y(), E.z()};
    T aa[3];
    ceres::QuaternionToAngleAxis(e_wxyz, aa);
    for (int i = 0; i < 3; ++i) {
      r[i] = aa[i] * T(e_.inv_sigma_rad);
      r[3 + i] = (t[i] - T(e_.t_ab[i])) * T(e_.inv_sigma_m);
    }
    return true;
  }
  BaRelativePose e_;
  Eigen::Quaterniond q_ab_;
};

}  // namespace

BaResult solve_bundle_adjustment_ceres(BaProblem& pb, int max_iterations) {
  BaResult res;
  res.initial_cost = ba_cost(pb);
  std::vector<std::array<double, 7>> pose(pb.poses.size());
  std::vector<std::array<double, 3>> pt(pb.points_M.size());
  ceres::Problem::Options po;
  po.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  po.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(po);
  ceres::EigenQuaternionManifold qm;
  ceres::HuberLoss huber(pb.huber);
  for (size_t i = 0; i < pb.poses.size(); ++i) {
    const BaPose& P = pb.poses[i];
    const Eigen::Quaterniond q(P.R_CM);
    pose[i] = {q.x(), q.y(), q.z(), q.w(), P.t_CM.x(), P.t_CM.y(), P.t_CM.z()};
    problem.AddParameterBlock(pose[i].data(), 4, &qm);
    problem.AddParameterBlock(pose[i].data() + 4, 3);
    if (P.fixed) {
      problem.SetParameterBlockConstant(pose[i].data());
      problem.SetParameterBlockConstant(pose[i].data() + 4);
    } else if (P.has_gravity && pb.gravity_inv_sigma > 0) {
      problem.AddResidualBlock(
          new ceres::AutoDiffCostFunction<GravityCost, 3, 4>(new GravityCost(P.g_C, pb.gravity_inv_sigma)),
          nullptr, pose[i].data());
    }
  }
  for (size_t a = 0; a < pb.points_M.size(); ++a)
    pt[a] = {pb.points_M[a].x(), pb.points_M[a].y(), pb.points_M[a].z()};
  for (const BaObservation& o : pb.obs) {
    if (!o.enabled) continue;
    double* q = pose[static_cast<size_t>(o.pose)].data();
    ceres::CostFunction* cf;
    if (o.depth_m > 0) {
      cf = new ceres::AutoDiffCostFunction<ObservationCost<3>, 3, 4, 3, 3>(new ObservationCost<3>(pb.K, o));
    } else {
      cf = new ceres::AutoDiffCostFunction<ObservationCost<2>, 2, 4, 3, 3>(new ObservationCost<2>(pb.K, o));
    }
    problem.AddResidualBlock(cf, &huber, q, q + 4, pt[static_cast<size_t>(o.point)].data());
  }
  for (const BaRelativePose& e : pb.relative) {
    double* qa = pose[static_cast<size_t>(e.a)].data();
    double* qb = pose[static_cast<size_t>(e.b)].data();
    problem.AddResidualBlock(
        new ceres::AutoDiffCostFunction<RelativePoseCost, 6, 4, 3, 4, 3>(new RelativePoseCost(e)), nullptr,
        qa, qa + 4, qb, qb + 4);
  }
  ceres::Solver::Options so;
  so.linear_solver_type = ceres::DENSE_SCHUR;
  so.max_num_iterations = max_iterations;
  so.num_threads = 1;
  so.logging_type = ceres::SILENT;
  ceres::Solver::Summary sum;
  ceres::Solve(so, &problem, &sum);
  res.usable = sum.IsSolutionUsable();
  res.iterations = static_cast<int>(sum.iterations.size()) - 1;  // Ceres counts its initial evaluation too
  if (!res.usable) return res;
  for (size_t i = 0; i < pb.poses.size(); ++i) {
    pb.poses[i].R_CM =
        Eigen::Quaterniond(pose[i][3], pose[i][0], pose[i][1], pose[i][2]).normalized().toRotationMatrix();
    pb.poses[i].t_CM = Eigen::Vector3d(pose[i][4], pose[i][5], pose[i][6]);
  }
  for (size_t a = 0; a < pt.size(); ++a) pb.points_M[a] = Eigen::Vector3d(pt[a].data());
  res.final_cost = ba_cost(pb);
  return res;
}

}  // namespace kestrel::core

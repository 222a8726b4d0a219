#include "kestrel/core/pose_graph.hpp"

#include <ceres/ceres.h>

#include <cmath>

namespace kestrel::core {

Eigen::Matrix3d rot_z(double yaw) {
  return Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
}

Eigen::Isometry3d project_4dof(const Eigen::Isometry3d& T) {
  // The yaw that best explains R about z: the heading of R's image of x
  // (falling back to y when x is near vertical).
  const Eigen::Matrix3d& R = T.linear();
  const double yaw = std::abs(R(2, 0)) < 0.9 ? std::atan2(R(1, 0), R(0, 0)) : std::atan2(-R(0, 1), R(1, 1));
  Eigen::Isometry3d out = Eigen::Isometry3d::Identity();
  out.linear() = rot_z(yaw);
  out.translation() = T.translation();
  return out;
}

namespace {

template <typename T>
Eigen::Matrix<T, 3, 3> rot_z_t(const T& yaw) {
  const T c = ceres::cos(yaw), s = ceres::sin(yaw);
  Eigen::Matrix<T, 3, 3> R;
  R << c, -s, T(0), s, c, T(0), T(0), T(0), T(1);
  return R;
}

template <typename T>
T wrap_angle(const T& a) {
  // Into (-pi, pi] without branches Ceres' jets dislike: atan2(sin, cos).
  return ceres::atan2(ceres::sin(a), ceres::cos(a));
}

struct EdgeCost {
  EdgeCost(const PoseGraphEdge& e, const Eigen::Matrix3d& R_rest_i) : e_(e), Ri_(R_rest_i) {}
  template <typename T>
  bool operator()(const T* pi, const T* yi, const T* pj, const T* yj, T* r) const {
    const Eigen::Matrix<T, 3, 3> R_i = rot_z_t(yi[0]) * Ri_.cast<T>();
    const Eigen::Matrix<T, 3, 1> d(pj[0] - pi[0], pj[1] - pi[1], pj[2] - pi[2]);
    const Eigen::Matrix<T, 3, 1> t = R_i.transpose() * d;
    for (int k = 0; k < 3; ++k) r[k] = (t[k] - T(e_.t_ij[k])) / T(e_.sigma_m);
    r[3] = wrap_angle(yj[0] - yi[0] - T(e_.yaw_ij)) / T(e_.sigma_rad);
    return true;
  }
  PoseGraphEdge e_;
  Eigen::Matrix3d Ri_;
};

}  // namespace

int PoseGraph4::add_node(const Eigen::Isometry3d& T_MC, bool is_fixed) {
  T.push_back(T_MC);
  yaw.push_back(0.0);
  fixed.push_back(is_fixed ? 1 : 0);
  return static_cast<int>(T.size()) - 1;
}

void PoseGraph4::move_node(int a, const Eigen::Isometry3d& D) {
  const Eigen::Isometry3d d = project_4dof(D);
  T[a].translation() = d * T[a].translation();
  yaw[a] += std::atan2(d.linear()(1, 0), d.linear()(0, 0));
}

void PoseGraph4::add_edge_from_current(int i, int j, double sigma_m, double sigma_rad) {
  add_edge(i, j, T[i].linear().transpose() * (T[j].translation() - T[i].translation()), 0.0, sigma_m,
           sigma_rad);
}

void PoseGraph4::add_edge(int i, int j, const Eigen::Vector3d& t_ij, double yaw_ij, double sigma_m,
                          double sigma_rad) {
  PoseGraphEdge e;
  e.i = i;
  e.j = j;
  e.t_ij = t_ij;
  e.yaw_ij = yaw_ij;
  e.sigma_m = sigma_m;
  e.sigma_rad = sigma_rad;
  edges.push_back(e);
}

bool PoseGraph4::solve(int max_iterations) {
  const size_t n = T.size();
  std::vector<double> p(3 * n);
  for (size_t k = 0; k < n; ++k)
    for (int a = 0; a < 3; ++a) p[3 * k + a] = T[k].translation()[a];
  ceres::Problem problem;
  for (const PoseGraphEdge& e : edges) {
    auto* cost = new ceres::AutoDiffCostFunction<EdgeCost, 4, 3, 1, 3, 1>(new EdgeCost(e, T[e.i].linear()));
    problem.AddResidualBlock(cost, nullptr, &p[3 * e.i], &yaw[e.i], &p[3 * e.j], &yaw[e.j]);
  }
  for (size_t k = 0; k < n; ++k) {
    if (!fixed[k] || !problem.HasParameterBlock(&p[3 * k])) continue;
    problem.SetParameterBlockConstant(&p[3 * k]);
    problem.SetParameterBlockConstant(&yaw[k]);
  }
  ceres::Solver::Options o;
  o.linear_solver_type = ceres::IsSparseLinearAlgebraLibraryTypeAvailable(ceres::SUITE_SPARSE) ||
                                 ceres::IsSparseLinearAlgebraLibraryTypeAvailable(ceres::EIGEN_SPARSE)
                             ? ceres::SPARSE_NORMAL_CHOLESKY
                             : ceres::DENSE_QR;
  o.max_num_iterations = max_iterations;
  o.num_threads = 1;
  ceres::Solver::Summary s;
  ceres::Solve(o, &problem, &s);
  if (!s.IsSolutionUsable()) return false;
  for (size_t k = 0; k < n; ++k) {
    T[k].linear() = rot_z(yaw[k]) * T[k].linear();
    yaw[k] = 0.0;
    T[k].translation() = Eigen::Vector3d(p[3 * k], p[3 * k + 1], p[3 * k + 2]);
  }
  return true;
}

}  // namespace kestrel::core

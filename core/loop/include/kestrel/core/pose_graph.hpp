// The 4-DoF pose graph of loop closing (x, y, z, yaw per keyframe; roll and
// pitch stay where the odometry's gravity put them): VINS-Mono's
// formulation, with each keyframe's rotation R = Rz(yaw) * R_rest, R_rest its
// rotation before the solve, so yaw starts at 0 everywhere. Edges are
// relative positions in the first keyframe's frame and yaw differences.
// Not real time (the loop thread; Ceres allocates). docs/map.md.
#pragma once

#include <Eigen/Geometry>
#include <vector>

namespace kestrel::core {

struct PoseGraphEdge {
  int i = 0, j = 0;                                // node indices
  Eigen::Vector3d t_ij = Eigen::Vector3d::Zero();  // R_i^T (p_j - p_i)
  double yaw_ij = 0.0;                             // yaw_j - yaw_i
  double sigma_m = 0.01, sigma_rad = 0.005;
};

struct PoseGraph4 {
  // Nodes: camera poses in M; fixed ones do not move.
  // T: position and R_rest (rotation at yaw 0); yaw: the node's yaw on top
  // (0 until move_node or solve; solve folds it into T).
  std::vector<Eigen::Isometry3d> T;
  std::vector<double> yaw;
  std::vector<char> fixed;
  std::vector<PoseGraphEdge> edges;

  int add_node(const Eigen::Isometry3d& T_MC, bool is_fixed);
  // An edge measured from the nodes' current poses (they agree with it now; call before move_node).
  void add_edge_from_current(int i, int j, double sigma_m, double sigma_rad);
  // A starting guess: the node moved by the 4-DoF part of D (edges made
  // before keep their measurements).
  void move_node(int a, const Eigen::Isometry3d& D);
  // A measured edge: t_ij in node i's frame at yaw 0, yaw_ij = yaw_j - yaw_i.
  void add_edge(int i, int j, const Eigen::Vector3d& t_ij, double yaw_ij, double sigma_m, double sigma_rad);
  // Solves in place; false when Ceres failed (poses untouched).
  bool solve(int max_iterations);
};

// The yaw-only rotation about M's z axis.
Eigen::Matrix3d rot_z(double yaw);
// The 4-DoF part of a transform: its yaw about z and its translation.
Eigen::Isometry3d project_4dof(const Eigen::Isometry3d& T);

}  // namespace kestrel::core

// Depth grids ray-cast from boxes (the map tests' surfaces): a room's walls
// seen from inside, solid crates from outside.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "kestrel/core/depth_grid.hpp"

namespace kestrel::map_test {

struct Box {
  Eigen::Vector3d lo, hi;
};

// Distance along a unit ray to the scene: the room's walls seen from inside,
// solid boxes from outside. Infinity: nothing.
inline double cast(const Eigen::Vector3d& o, const Eigen::Vector3d& d, const Box& room,
                   const std::vector<Box>& solids, bool room_walls) {
  double best = std::numeric_limits<double>::infinity();
  if (room_walls) {
    for (int a = 0; a < 3; ++a) {
      if (d[a] > 1e-12) best = std::min(best, (room.hi[a] - o[a]) / d[a]);
      if (d[a] < -1e-12) best = std::min(best, (room.lo[a] - o[a]) / d[a]);
    }
  }
  for (const Box& b : solids) {
    double t0 = 0, t1 = std::numeric_limits<double>::infinity();
    bool hit = true;
    for (int a = 0; a < 3 && hit; ++a) {
      if (std::abs(d[a]) < 1e-12) {
        hit = o[a] >= b.lo[a] && o[a] <= b.hi[a];
        continue;
      }
      double ta = (b.lo[a] - o[a]) / d[a], tb = (b.hi[a] - o[a]) / d[a];
      if (ta > tb) std::swap(ta, tb);
      t0 = std::max(t0, ta);
      t1 = std::min(t1, tb);
      hit = t0 <= t1;
    }
    if (hit && t0 > 0) best = std::min(best, t0);
  }
  return best;
}

// A camera looking horizontally along yaw (C: x right, y down, z forward; W: z up).
inline Eigen::Isometry3d camera(const Eigen::Vector3d& p, double yaw) {
  Eigen::Matrix3d R;
  R.col(0) = Eigen::Vector3d(std::sin(yaw), -std::cos(yaw), 0);  // x_C
  R.col(1) = Eigen::Vector3d(0, 0, -1);                          // y_C
  R.col(2) = Eigen::Vector3d(std::cos(yaw), std::sin(yaw), 0);   // z_C
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = R;
  T.translation() = p;
  return T;
}

inline std::vector<uint16_t> render(const core::DepthGridShape& s, const Eigen::Isometry3d& T_WC,
                                    const Box& room, const std::vector<Box>& solids, bool room_walls = true) {
  std::vector<uint16_t> z(static_cast<size_t>(s.cells()), 0);
  for (int c = 0; c < s.cells(); ++c) {
    const Eigen::Vector2d r = s.ray(c);
    const Eigen::Vector3d ray_C(r.x(), r.y(), 1.0);
    const Eigen::Vector3d d = (T_WC.linear() * ray_C).normalized();
    const double t = cast(T_WC.translation(), d, room, solids, room_walls);
    if (!std::isfinite(t)) continue;
    const double zc = t * (T_WC.linear().transpose() * d).z();
    if (zc > 0.3 && zc < 6.0) z[static_cast<size_t>(c)] = static_cast<uint16_t>(std::lround(zc * 1e3));
  }
  return z;
}

}  // namespace kestrel::map_test

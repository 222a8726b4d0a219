// The rig's row-major 4x4 transforms (msgs.hpp Mat4d) as Eigen isometries:
// one conversion for every backend.
#pragma once

#include <Eigen/Geometry>

#include "kestrel/msgs.hpp"

namespace kestrel::core {

inline Eigen::Isometry3d to_isometry(const Mat4d& T) {
  Eigen::Isometry3d out = Eigen::Isometry3d::Identity();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) out.matrix()(r, c) = T[static_cast<size_t>(r * 4 + c)];
  return out;
}

}  // namespace kestrel::core

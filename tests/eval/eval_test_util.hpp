// Synthetic trajectories for the evaluation tests.
#pragma once

#include <cmath>
#include <cstdint>
#include <fstream>
#include <string>

#include "kestrel/tools/trajectory_eval.hpp"

namespace kestrel::test {

// A smooth, non-planar 3D trajectory with varying attitude, so alignment is
// fully constrained (no collinear or coplanar degeneracy).
inline tools::Trajectory lissajous(double duration_s = 30.0, double rate_hz = 100.0,
                                   int64_t t0_ns = 1'000'000'000) {
  tools::Trajectory traj;
  const int n = static_cast<int>(duration_s * rate_hz) + 1;
  for (int i = 0; i < n; ++i) {
    const double t = i / rate_hz;
    tools::TimedPose p;
    p.t_ns = t0_ns + static_cast<int64_t>(std::llround(t * 1e9));
    p.p = Eigen::Vector3d(2.0 * std::sin(0.3 * t), 1.5 * std::sin(0.5 * t + 0.4),
                          1.0 + 0.4 * std::cos(0.7 * t));
    p.q = Eigen::AngleAxisd(0.6 * std::sin(0.2 * t), Eigen::Vector3d::UnitZ()) *
          Eigen::AngleAxisd(0.2 * std::sin(0.9 * t), Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(0.15 * std::cos(0.4 * t), Eigen::Vector3d::UnitX());
    traj.push_back(p);
  }
  return traj;
}

// Applies x -> s R x + t to positions and R to attitudes (a change of world frame).
inline tools::Trajectory transformed(const tools::Trajectory& in, double s, const Eigen::Matrix3d& R,
                                     const Eigen::Vector3d& t) {
  tools::Trajectory out = in;
  const Eigen::Quaterniond qR(R);
  for (auto& p : out) {
    p.p = s * (R * p.p) + t;
    p.q = (qR * p.q).normalized();
  }
  return out;
}

inline void write_text(const std::string& path, const std::string& text) {
  std::ofstream f(path, std::ios::binary);
  f << text;
}

}  // namespace kestrel::test

// The rendered room the dense map's tests fly in (test_dense_accuracy,
// test_dense_reanchor, test_dense_live, test_dense_query): its true geometry
// as a distance function, the surface-error quantiles, the circle the camera
// flies, its camera and frame times, and the odometry's drift.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "kestrel/tools/sim_render.hpp"

namespace kestrel::dense_test {

// Distance to a yawed box's surface, inside or out.
inline double box_distance(const tools::SceneBox& b, const Eigen::Vector3d& p_W) {
  const Eigen::Matrix3d R = Eigen::AngleAxisd(b.yaw_rad, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  const Eigen::Vector3d q = (R.transpose() * (p_W - b.center_W)).cwiseAbs() - b.half_m;
  if ((q.array() <= 0).all()) return -q.maxCoeff();
  return q.cwiseMax(0.0).norm();
}

// Distance to the room's walls, floor and ceiling.
inline double room_distance(const Eigen::AlignedBox3d& room, const Eigen::Vector3d& p) {
  if (room.contains(p)) return std::min((p - room.min()).minCoeff(), (room.max() - p).minCoeff());
  return (p - p.cwiseMax(room.min()).cwiseMin(room.max())).norm();
}

// Distance to the nearest true surface of the scene.
inline double scene_distance(const tools::Scene& s, const Eigen::Vector3d& p) {
  double d = room_distance(s.room, p);
  for (const tools::SceneBox& b : s.boxes) d = std::min(d, box_distance(b, p));
  return d;
}

// A 5.5 x 5.5 x 3 m room with two yawed boxes.
inline tools::Scene room_with_boxes() {
  tools::Scene s;
  s.room = Eigen::AlignedBox3d(Eigen::Vector3d(-3.0, -2.5, 0.0), Eigen::Vector3d(2.5, 3.0, 3.0));
  tools::SceneBox b1;
  b1.center_W = {1.7, 0.4, 0.5};
  b1.half_m = {0.3, 0.5, 0.5};
  b1.yaw_rad = 0.4;
  tools::SceneBox b2;
  b2.center_W = {-1.6, -1.2, 0.7};
  b2.half_m = {0.4, 0.25, 0.7};
  b2.yaw_rad = -0.3;
  s.boxes = {b1, b2};
  return s;
}

inline double quantile(std::vector<double> v, double q) {
  if (v.empty()) return NAN;
  const auto k = static_cast<std::size_t>(q * static_cast<double>(v.size() - 1));
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
  return v[k];
}

// A camera at p looking along fwd (not vertical), level: x_C horizontal (z forward, y down).
inline Eigen::Isometry3d camera_looking(const Eigen::Vector3d& p, const Eigen::Vector3d& fwd) {
  Eigen::Matrix3d R;
  R.col(2) = fwd.normalized();
  R.col(0) = R.col(2).cross(Eigen::Vector3d::UnitZ()).normalized();
  R.col(1) = R.col(2).cross(R.col(0));
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = R;
  T.translation() = p;
  return T;
}

// Camera on a circle in the room, looking outwards and a little down.
inline Eigen::Isometry3d pose_on_circle(double a) {
  return camera_looking(Eigen::Vector3d(0.8 * std::cos(a), 0.8 * std::sin(a), 1.4 + 0.2 * std::sin(3 * a)),
                        Eigen::Vector3d(std::cos(a + 0.6), std::sin(a + 0.6), -0.25));
}

// The camera the room is flown with: 320 x 240 at 262.5 px, body = camera (T_BC identity).
inline Rig room_rig() {
  Rig r;
  r.rgb.width = 320;
  r.rgb.height = 240;
  r.rgb.fx = r.rgb.fy = 262.5;
  r.rgb.cx = 159.5;
  r.rgb.cy = 119.5;
  return r;
}

// Frame f's time: 30 Hz from 1 s.
constexpr int64_t kRoomFrameNs = 33'000'000;
inline int64_t room_frame_t_ns(int f) { return 1'000'000'000LL + f * kRoomFrameNs; }

// The map's correction C_MW = T_map_odom that frame f's odometry needs when
// the odometry drifts by a fixed yaw and translation a frame until frame
// `until` and is exact relative to its pose there after it: odometry = C(f)^-1 * truth.
inline Eigen::Isometry3d linear_drift_correction(int f, int until, double yaw_deg_per_frame,
                                                 const Eigen::Vector3d& m_per_frame) {
  const int g = std::min(f, until);
  Eigen::Isometry3d C = Eigen::Isometry3d::Identity();
  C.linear() =
      Eigen::AngleAxisd(-g * yaw_deg_per_frame * M_PI / 180.0, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  C.translation() = -g * m_per_frame;
  return C;
}

}  // namespace kestrel::dense_test

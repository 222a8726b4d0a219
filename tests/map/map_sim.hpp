// A synthetic room for the map's tests: points on the walls of a 8 x 8 x 3 m
// room, keyframes along a path looking at them, each keyframe's features the
// noisy projections (undistorted pinhole) and depths of the points it sees.
#pragma once

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <memory>
#include <random>
#include <vector>

#include "kestrel/core/local_mapper.hpp"
#include "kestrel/core/map.hpp"

namespace kestrel::map_test {

struct SimKeyframe {
  Eigen::Isometry3d T_WC_true = Eigen::Isometry3d::Identity();
  std::vector<core::KeyframeFeature> features;
  std::vector<int> point_index;  // per feature: which true point
};

inline core::MapCamera sim_camera() {
  core::MapCamera c;
  c.K = {300.0, 300.0, 160.0, 120.0};
  c.width = 320;
  c.height = 240;
  c.depth_sigma_coeff_per_m = 0.0025;
  c.keypoint_sigma_px = 1.0;
  c.level_scale = 1.2;
  return c;
}

struct SimRoom {
  std::vector<Eigen::Vector3d> points;
  std::vector<core::OrbDescriptor> desc;

  explicit SimRoom(int n, uint64_t seed) {
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> U(0.0, 1.0);
    for (int i = 0; i < n; ++i) {
      const int face = i % 4;
      const double a = U(rng), b = U(rng);
      Eigen::Vector3d p;
      switch (face) {
        case 0:
          p = {4.0, -4.0 + 8 * a, 3 * b};
          break;
        case 1:
          p = {-4.0, -4.0 + 8 * a, 3 * b};
          break;
        case 2:
          p = {-4.0 + 8 * a, 4.0, 3 * b};
          break;
        default:
          p = {-4.0 + 8 * a, -4.0, 3 * b};
          break;
      }
      points.push_back(p);
      core::OrbDescriptor d;
      for (auto& w : d) w = rng();
      desc.push_back(d);
    }
  }

  // A camera at p looking along yaw (z forward, x right, y down; W z up).
  static Eigen::Isometry3d camera(const Eigen::Vector3d& p, double yaw) {
    Eigen::Matrix3d R_WC;
    const Eigen::Vector3d fwd(std::cos(yaw), std::sin(yaw), 0), up(0, 0, 1);
    R_WC.col(2) = fwd;
    R_WC.col(0) = fwd.cross(up).normalized();
    R_WC.col(1) = R_WC.col(2).cross(R_WC.col(0));
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = R_WC;
    T.translation() = p;
    return T;
  }

  // What a keyframe at T_WC sees; ids are the point index + id_offset.
  SimKeyframe observe(const Eigen::Isometry3d& T_WC, std::mt19937_64& rng, uint32_t id_offset = 1,
                      double pixel_noise = 0.5) const {
    const core::MapCamera cam = sim_camera();
    std::normal_distribution<double> N(0.0, 1.0);
    SimKeyframe k;
    k.T_WC_true = T_WC;
    const Eigen::Isometry3d T_CW = T_WC.inverse();
    for (size_t i = 0; i < points.size() && k.features.size() < 300; ++i) {
      const Eigen::Vector3d c = T_CW * points[i];
      if (c.z() < 0.3 || c.z() > 6.0) continue;
      const double u = cam.K.fx * c.x() / c.z() + cam.K.cx + pixel_noise * N(rng);
      const double v = cam.K.fy * c.y() / c.z() + cam.K.cy + pixel_noise * N(rng);
      if (u < 1 || v < 1 || u > cam.width - 2 || v > cam.height - 2) continue;
      core::KeyframeFeature f;
      f.x_px = f.u_px = static_cast<float>(u);
      f.y_px = f.v_px = static_cast<float>(v);
      f.depth_m = static_cast<float>(c.z() + cam.sigma_depth_m(c.z()) * N(rng));
      f.level = 0;
      f.landmark_id = static_cast<uint32_t>(i) + id_offset;
      f.desc = desc[i];
      k.features.push_back(f);
      k.point_index.push_back(static_cast<int>(i));
    }
    return k;
  }
};

// A place-recognition vocabulary of a room's own descriptors (documents of 300).
inline std::shared_ptr<const core::Vocabulary> room_vocabulary(const SimRoom& room) {
  std::vector<std::vector<core::OrbDescriptor>> docs;
  for (size_t i = 0; i < room.desc.size(); i += 300)
    docs.emplace_back(room.desc.begin() + static_cast<long>(i),
                      room.desc.begin() + static_cast<long>(std::min(room.desc.size(), i + 300)));
  core::Vocabulary::TrainOptions o;
  o.k = 10;
  o.levels = 3;
  return std::make_shared<core::Vocabulary>(core::Vocabulary::train(docs, o));
}

inline Eigen::Isometry3d perturbed(const Eigen::Isometry3d& T, std::mt19937_64& rng, double pos_m,
                                   double rot_rad) {
  std::normal_distribution<double> N(0.0, 1.0);
  Eigen::Isometry3d d = Eigen::Isometry3d::Identity();
  const Eigen::Vector3d w(N(rng), N(rng), N(rng));
  d.linear() = Eigen::AngleAxisd(rot_rad * w.norm() / std::sqrt(3.0), w.normalized()).toRotationMatrix();
  d.translation() = pos_m / std::sqrt(3.0) * Eigen::Vector3d(N(rng), N(rng), N(rng));
  return T * d;
}

inline double pos_err(const Eigen::Isometry3d& a, const Eigen::Isometry3d& b) {
  return (a.translation() - b.translation()).norm();
}

// The map as drifting odometry builds it: each keyframe at its drifted pose,
// points placed from its depths; landmark ids live for `id_life` keyframes
// (the tracker loses them), so a place seen again is new points.
struct DriftedMap {
  core::Map map;
  int last = -1;
  std::vector<Eigen::Isometry3d> truth;  // by slot
  explicit DriftedMap(std::shared_ptr<const core::Vocabulary> v)
      : map(
            [] {
              core::MapOptions o;
              o.max_keyframes = 200;
              o.max_points = 60000;
              return o;
            }(),
            300, std::move(v)),
        truth(200) {}

  // edit: changes the keyframe's features before they are linked (a test
  // links some to older points, as the mapping thread's fusing does).
  int add(const SimRoom& room, const Eigen::Isometry3d& T_true, const Eigen::Isometry3d& T_odom, int64_t t_ns,
          uint32_t id_offset, std::mt19937_64& rng, const std::function<void(SimKeyframe&)>& edit = {}) {
    SimKeyframe s = room.observe(T_true, rng, id_offset);
    if (edit) edit(s);
    const int kf =
        map.add_keyframe(t_ns, T_odom, T_odom, s.features.data(), static_cast<int>(s.features.size()), last);
    if (kf < 0) return kf;
    if (last >= 0)
      map.keyframe(kf).path_m =
          map.keyframe(last).path_m + (T_odom.translation() - map.keyframe(last).T_WC.translation()).norm();
    const core::MapCamera cam = sim_camera();
    for (int j = 0; j < map.keyframe(kf).n; ++j) {
      const core::KeyframeFeature& f = map.feature(kf, j);
      const int p = map.find_point(f.landmark_id);
      if (p >= 0) {
        map.add_observation(p, kf, j);
        continue;
      }
      map.add_point(f.landmark_id, T_odom * cam.point_C(f), f.desc, 0, kf, j);
    }
    truth[static_cast<size_t>(kf)] = T_true;
    last = kf;
    return kf;
  }
};

}  // namespace kestrel::map_test

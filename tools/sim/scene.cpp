// Scene layout: a room around the flight and clutter that keeps clear of it.
#include <algorithm>
#include <cmath>
#include <limits>
#include <unordered_set>

#include "kestrel/tools/sim_random.hpp"
#include "kestrel/tools/sim_render.hpp"

namespace kestrel::tools {
namespace {

double box_distance(const SceneBox& b, const Eigen::Vector3d& p) {
  const Eigen::Vector3d d = p - b.center_W;
  const double c = std::cos(b.yaw_rad), s = std::sin(b.yaw_rad);
  const Eigen::Vector3d local(c * d.x() + s * d.y(), -s * d.x() + c * d.y(), d.z());
  return (local.cwiseAbs() - b.half_m).cwiseMax(0.0).norm();
}

double cylinder_distance(const SceneCylinder& c, const Eigen::Vector3d& p) {
  const double radial = std::max(0.0, (p.head<2>() - c.center_W).norm() - c.radius_m);
  const double vertical = std::max({0.0, c.z0_m - p.z(), p.z() - c.z1_m});
  return std::hypot(radial, vertical);
}

}  // namespace

double Scene::clutter_distance(const Eigen::Vector3d& p) const {
  double d = std::numeric_limits<double>::infinity();
  for (const auto& b : boxes) d = std::min(d, box_distance(b, p));
  for (const auto& c : cylinders) d = std::min(d, cylinder_distance(c, p));
  return d;
}

Scene Scene::build(const MotionModel& traj, const Eigen::Isometry3d& T_BC, uint64_t seed,
                   const SceneOptions& opt) {
  // The path, thinned to one point per 5 cm voxel: clearance checks then
  // cost the same for a 10 s and a 1000 s flight.
  constexpr double kVoxel = 0.05;
  std::vector<Eigen::Vector3d> path;
  std::unordered_set<uint64_t> seen;
  Eigen::AlignedBox3d bbox;
  const double T = traj.duration_s();
  const int n = std::max(2, static_cast<int>(std::ceil(T * 50.0)) + 1);
  for (int k = 0; k < n; ++k) {
    const TrajectoryState s = traj.state(std::min(T, k / 50.0));
    const Eigen::Isometry3d T_WB = Eigen::Translation3d(s.p_WB) * s.q_WB;
    for (const Eigen::Vector3d& p : {s.p_WB, Eigen::Vector3d(T_WB * T_BC.translation())}) {
      bbox.extend(p);
      const auto key = [&](int i) {
        return static_cast<uint64_t>(static_cast<int64_t>(std::floor(p[i] / kVoxel)) & 0x1FFFFF);
      };
      if (seen.insert(key(0) | key(1) << 21 | key(2) << 42).second) path.push_back(p);
    }
  }
  // Thinning moves a point by up to a voxel diagonal; 50 Hz sampling skips
  // up to 5 cm between samples below 5 m/s.
  const double slack = kVoxel * std::sqrt(3.0) + 0.05;

  Scene scene;
  Eigen::Vector3d lo = bbox.min(), hi = bbox.max();
  for (int i = 0; i < 2; ++i) {
    // The far wall stays within max_wall_distance_m of every point of the
    // path while the path allows it (depth range 6 m, FOV corners further).
    const double margin =
        std::clamp(opt.max_wall_distance_m - (hi[i] - lo[i]), opt.min_margin_m, opt.margin_m);
    lo[i] -= margin;
    hi[i] += margin;
    const double grow = 0.5 * std::max(0.0, opt.min_room_m - (hi[i] - lo[i]));
    lo[i] -= grow;
    hi[i] += grow;
  }
  lo.z() = std::min(0.0, bbox.min().z() - 0.2);
  hi.z() = std::max(lo.z() + opt.min_height_m, bbox.max().z() + 1.0);
  scene.room = Eigen::AlignedBox3d(lo, hi);

  // Clutter: boxes on the floor, tall pillars and cylinders, rejected when
  // they come near the path or overlap each other (footprint circles).
  SimRng rng(seed, RngStream::kScene);
  const double area = (hi.x() - lo.x()) * (hi.y() - lo.y());
  const int wanted = std::clamp(static_cast<int>(std::lround(area * opt.clutter_per_m2)), 4, opt.max_clutter);
  struct Disc {
    double x, y, r;
  };
  std::vector<Disc> taken;
  const double floor = lo.z(), height = hi.z() - lo.z();
  int placed = 0;
  for (int attempt = 0; attempt < wanted * 60 && placed < wanted; ++attempt) {
    const double kind = rng.uniform();
    const double x = rng.uniform(lo.x(), hi.x());
    const double y = rng.uniform(lo.y(), hi.y());
    SceneBox box;
    SceneCylinder cyl;
    double foot_r;
    bool is_box = true;
    if (kind < 0.6) {  // box on the floor, sometimes turned
      box.half_m = {rng.uniform(0.15, 0.6), rng.uniform(0.15, 0.6), rng.uniform(0.15, 0.8)};
      box.yaw_rad = rng.bernoulli(0.5) ? rng.uniform(0.0, 1.5707963) : 0.0;
      box.center_W = {x, y, floor + box.half_m.z()};
      foot_r = box.half_m.head<2>().norm();
    } else if (kind < 0.75) {  // pillar to the ceiling
      const double h = rng.uniform(0.15, 0.3);
      box.half_m = {h, h, 0.5 * height};
      box.yaw_rad = rng.bernoulli(0.5) ? rng.uniform(0.0, 1.5707963) : 0.0;
      box.center_W = {x, y, floor + 0.5 * height};
      foot_r = box.half_m.head<2>().norm();
    } else {  // cylinder, short or to the ceiling
      is_box = false;
      cyl.center_W = {x, y};
      cyl.radius_m = rng.uniform(0.12, 0.4);
      cyl.z0_m = floor;
      cyl.z1_m = rng.bernoulli(0.5) ? hi.z() : floor + rng.uniform(0.4, 1.5);
      foot_r = cyl.radius_m;
    }
    if (x - foot_r < lo.x() || x + foot_r > hi.x() || y - foot_r < lo.y() || y + foot_r > hi.y()) continue;
    bool ok = true;
    for (const Disc& d : taken)
      if (std::hypot(d.x - x, d.y - y) < d.r + foot_r + 0.1) ok = false;
    for (size_t k = 0; ok && k < path.size(); ++k) {
      const double dist = is_box ? box_distance(box, path[k]) : cylinder_distance(cyl, path[k]);
      if (dist < opt.clearance_m + slack) ok = false;
    }
    if (!ok) continue;
    taken.push_back({x, y, foot_r});
    if (is_box) {
      scene.boxes.push_back(box);
    } else {
      scene.cylinders.push_back(cyl);
    }
    ++placed;
  }
  return scene;
}

}  // namespace kestrel::tools

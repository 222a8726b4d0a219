// The dense map against the simulator's true geometry on a loop-closing
// flight (issue 44 item 2, the figures of docs/dense.md): a simulated flight
// replayed with the map, loop closing and relocalisation on; the surface fused
// along the odometry (--dense-out, frame W) and the one re-integrated along the
// map's final trajectory (--dense-map-out, frame M) are each brought into the
// simulator's world by the se3 alignment of their own trajectory to the ground
// truth, and every point's distance to the true room and clutter is taken.
// Environment: KESTREL_DENSE_LOOP_SCENARIO (figure8), _DURATION_S (60),
// _SEED (3), _COVER_AT_S (0: no covered lens; the kidnap flight: 16). Or a
// hybrid log already written by `kestrel sim --trajectory GT.csv`:
// KESTREL_DENSE_LOOP_LOG (the .klog), KESTREL_DENSE_LOOP_GT (the csv it was
// rendered along; its scene is rebuilt from it with the seed the log's first
// event names, and the default room), KESTREL_DENSE_LOOP_CONFIG (a config file's dense: section).
// First the scene check (raw depth along the log's ground truth against the
// rebuilt scene, KESTREL_DENSE_LOOP_SCENE_CHECK_FRAMES frames, 40);
// KESTREL_DENSE_LOOP_SCENE_CHECK_ONLY=1 stops after it (a loud skip).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include "../map/map_pipeline.hpp"
#include "kestrel/core/tsdf_map.hpp"
#include "kestrel/dense/dense_config.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/tools/config_file.hpp"
#include "kestrel/tools/sim_render.hpp"
#include "kestrel/tools/sim_trajectory.hpp"
#include "kestrel/tools/simulator.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "test_data.hpp"

namespace kestrel {
namespace {

double env_or(const char* name, double fallback) {
  const char* v = std::getenv(name);
  return v != nullptr && *v != 0 ? std::atof(v) : fallback;
}

double room_distance(const Eigen::AlignedBox3d& room, const Eigen::Vector3d& p) {
  if (room.contains(p)) return std::min((p - room.min()).minCoeff(), (room.max() - p).minCoeff());
  return (p - p.cwiseMax(room.min()).cwiseMin(room.max())).norm();
}

double quantile(std::vector<double> v, double q) {
  if (v.empty()) return NAN;
  const auto k = static_cast<std::size_t>(q * static_cast<double>(v.size() - 1));
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
  return v[k];
}

// x_gt = s R x_est + t from the trajectory's own poses against the ground truth.
tools::Sim3 align_to_truth(const tools::Trajectory& est, const tools::Trajectory& gt) {
  std::vector<Eigen::Vector3d> e, g;
  for (const tools::TimedPose& p : est) {
    const auto q = tools::pose_at(gt, p.t_ns, 20'000'000);
    if (!q) continue;
    e.push_back(p.p);
    g.push_back(q->p);
  }
  return tools::align_positions(e, g, tools::Alignment::kSe3);
}

struct Score {
  double median = NAN, p95 = NAN, within_4cm = NAN;
  std::size_t points = 0;
};

Score score(const std::vector<core::SurfacePoint>& pts, const tools::Sim3& a, const tools::Scene& scene) {
  std::vector<double> d;
  d.reserve(pts.size());
  std::size_t near = 0;
  for (const core::SurfacePoint& s : pts) {
    const Eigen::Vector3d p = a.scale * (a.R * s.p.cast<double>()) + a.t;
    const double x = std::min(room_distance(scene.room, p), scene.clutter_distance(p));
    d.push_back(x);
    near += x <= 0.04 ? 1 : 0;
  }
  Score r;
  r.points = pts.size();
  r.median = quantile(d, 0.5);
  r.p95 = quantile(d, 0.95);
  r.within_4cm = pts.empty() ? NAN : static_cast<double>(near) / static_cast<double>(pts.size());
  return r;
}

// The scene check: raw depth of `frames` frames spread over the log,
// back-projected along the log's own ground truth (no estimator, no fusion),
// against the rebuilt scene. On the scene the renderer drew this is the depth
// noise (millimetres); a scene rebuilt wrong shows here first.
Score raw_depth_against_scene(const std::string& log, const tools::Trajectory& gt, const tools::Scene& scene,
                              int frames) {
  auto src = drivers::open_log(log);
  const Rig rig = src->rig();
  Eigen::Isometry3d T_BC;
  T_BC.matrix() = Eigen::Map<const Eigen::Matrix<double, 4, 4, Eigen::RowMajor>>(rig.T_BC.data());
  int depth_total = 0;
  drivers::LogRecord rec;
  while (src->next(rec))
    if (rec.type == drivers::RecordType::kDepth) ++depth_total;
  src->rewind();
  const int every = std::max(1, depth_total / std::max(1, frames));
  std::vector<core::SurfacePoint> pts;
  int k = 0;
  while (src->next(rec)) {
    if (rec.type != drivers::RecordType::kDepth || k++ % every != 0) continue;
    const auto g = tools::pose_at(gt, rec.image.t_ns, 20'000'000);
    if (!g) continue;
    Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();
    T_WB.linear() = g->q.toRotationMatrix();
    T_WB.translation() = g->p;
    const Eigen::Isometry3d T_WC = T_WB * T_BC;
    const auto* d = reinterpret_cast<const uint16_t*>(rec.image.pixels.data());
    for (int v = 0; v < rec.image.height; v += 8)
      for (int u = 0; u < rec.image.width; u += 8) {
        const double z = rig.depth.scale_m_per_unit * d[v * rec.image.width + u];
        if (!(z >= rig.depth.min_range_m && z <= std::min(3.5, rig.depth.max_range_m))) continue;
        const Eigen::Vector3d p_C((u - rig.rgb.cx) / rig.rgb.fx * z, (v - rig.rgb.cy) / rig.rgb.fy * z, z);
        core::SurfacePoint sp{(T_WC * p_C).cast<float>(), {0, 0, 0}};
        pts.push_back(sp);
      }
  }
  tools::Sim3 identity;
  identity.scale = 1;
  identity.R.setIdentity();
  identity.t.setZero();
  return score(pts, identity, scene);
}

TEST(DenseLoopsBench, SurfacesAgainstTheTrueGeometryAlongOdometryAndAlongTheMap) {
  const std::string dir = test::temp_dir("dense_loops");
  tools::SimOptions so = map_test::figure8(env_or("KESTREL_DENSE_LOOP_DURATION_S", 60), 3, 320, 240);
  const char* log_env = std::getenv("KESTREL_DENSE_LOOP_LOG");
  const bool given = log_env != nullptr && *log_env != 0;
  tools::Scene scene;
  if (given) {
    const char* gt_env = std::getenv("KESTREL_DENSE_LOOP_GT");
    ASSERT_TRUE(gt_env != nullptr && *gt_env != 0) << "KESTREL_DENSE_LOOP_LOG needs KESTREL_DENSE_LOOP_GT";
    so.out_path = log_env;
    so.scenario = std::string("hybrid ") + log_env;
    // The seed the log was rendered with, from its first event ("kestrel sim: ..., seed N, room ..."): the
    // clutter is placed by it, and a wrong one puts a third of the scene elsewhere (docs/dense.md, MH_01).
    int64_t log_seed = -1;
    {
      auto src = drivers::open_log(log_env);
      drivers::LogRecord rec;
      while (log_seed < 0 && src->next(rec)) {
        if (rec.type != drivers::RecordType::kEvent) continue;
        const std::size_t at = rec.event.text.find(", seed ");
        if (rec.event.text.rfind("kestrel sim:", 0) == 0 && at != std::string::npos)
          log_seed = std::atoll(rec.event.text.c_str() + at + 7);
        break;  // the simulator's event is the first record; anything else: not a simulated log
      }
    }
    ASSERT_GE(log_seed, 0) << log_env << ": no \"kestrel sim: ..., seed N\" event first: not a simulated log";
    so.seed = static_cast<uint64_t>(env_or("KESTREL_DENSE_LOOP_SEED", static_cast<double>(log_seed)));
    ASSERT_EQ(so.seed, static_cast<uint64_t>(log_seed))
        << "KESTREL_DENSE_LOOP_SEED differs from the log's seed";
    so.cover_s = 0;
    tools::SplineTrajectory::FitOptions fo;
    const tools::SplineTrajectory traj = tools::SplineTrajectory::from_file(gt_env, 0.0, -1.0, fo);
    so.duration_s = traj.duration_s();
    const Rig rig = drivers::open_log(log_env)->rig();
    Eigen::Isometry3d T_BC;
    T_BC.matrix() = Eigen::Map<const Eigen::Matrix<double, 4, 4, Eigen::RowMajor>>(rig.T_BC.data());
    scene = tools::Scene::build(traj, T_BC, so.seed);
    std::printf("scene: room %.1f x %.1f x %.1f m, %zu objects\n", scene.room.sizes().x(),
                scene.room.sizes().y(), scene.room.sizes().z(), scene.boxes.size() + scene.cylinders.size());
  } else {
    if (const char* s = std::getenv("KESTREL_DENSE_LOOP_SCENARIO"); s != nullptr && *s != 0) so.scenario = s;
    so.seed = static_cast<uint64_t>(env_or("KESTREL_DENSE_LOOP_SEED", 3));
    so.cover_at_s = env_or("KESTREL_DENSE_LOOP_COVER_AT_S", 0);
    so.cover_s = so.cover_at_s > 0 ? 2.0 : 0.0;
    so.out_path = dir + "/flight.klog";
    const tools::SimSummary sim = tools::run_simulation(so);
    // The scene exactly as the simulator built it (simulator.cpp: scenario, T_BC, seed, default room).
    tools::ScenarioOptions sco;
    sco.yaw_follows_path = so.yaw_follows_path;
    const auto traj = tools::make_scenario(so.scenario, so.duration_s, sco);
    Eigen::Isometry3d T_BC;
    T_BC.matrix() = Eigen::Map<const Eigen::Matrix<double, 4, 4, Eigen::RowMajor>>(sim.rig.T_BC.data());
    scene = tools::Scene::build(*traj, T_BC, so.seed);
    ASSERT_TRUE(scene.room.sizes().isApprox(sim.room_size_m, 1e-9)) << "the scene is not the simulator's";
  }

  {
    std::vector<std::string> w;
    const Score raw =
        raw_depth_against_scene(so.out_path, tools::load_trajectory(so.out_path, &w), scene,
                                static_cast<int>(env_or("KESTREL_DENSE_LOOP_SCENE_CHECK_FRAMES", 40)));
    std::printf(
        "scene check: raw depth along the log's ground truth against the rebuilt scene: median %.1f mm, "
        "95%% %.1f mm, %.1f %% within 4 cm (%zu points)\n",
        1e3 * raw.median, 1e3 * raw.p95, 100 * raw.within_4cm, raw.points);
    // The renderer's own depth noise keeps ~97-99 % within 4 cm (sigma 0.0025 z^2 up to 3.5 m); a scene
    // rebuilt wrong drops far below (MH_01 with the wrong seed: 53 %).
    EXPECT_GT(raw.within_4cm, 0.9) << "the rebuilt scene is not the one the log was rendered in";
    if (env_or("KESTREL_DENSE_LOOP_SCENE_CHECK_ONLY", 0) != 0)
      GTEST_SKIP()
          << "KESTREL_DENSE_LOOP_SCENE_CHECK_ONLY: the scene check alone, the flight is not replayed";
  }
  cli::ReplayOptions ro;
  ro.path = so.out_path;
  ro.pace = drivers::ReplayPace::kLockstep;
  ro.config = map_test::map_config("window");
  if (const char* c = std::getenv("KESTREL_DENSE_LOOP_CONFIG"); c != nullptr && *c != 0)
    ro.dense = tools::load_config(c).dense;
  std::vector<core::SurfacePoint> in_W, in_M, live;
  ro.on_dense_map = [&](const core::TsdfMap& m) { m.extract_surface(in_W); };
  // With dense.live_reanchor the map as flown is in the map frame of the
  // online map trajectory (T_map_odom(t) T_WB(t)): scored against that one.
  if (ro.dense.live_reanchor) ro.on_dense_map_live = [&](const core::TsdfMap& m) { m.extract_surface(live); };
  ro.on_dense_map_rebuilt = [&](const core::TsdfMap& m) { m.extract_surface(in_M); };
  const cli::ReplayReport r = cli::run_replay(ro);
  std::vector<std::string> warnings;
  const tools::Trajectory gt = tools::load_trajectory(so.out_path, &warnings);
  ASSERT_FALSE(r.trajectory.empty());
  const tools::Trajectory& M = r.map_final_trajectory.empty() ? r.trajectory : r.map_final_trajectory;
  const Score w = score(in_W, align_to_truth(r.trajectory, gt), scene);
  const Score m = score(in_M, align_to_truth(M, gt), scene);
  tools::EvalOptions eo;
  eo.align = tools::Alignment::kSe3;
  const double ate_w = tools::evaluate(gt, r.trajectory, eo).ate_m.rmse;
  const double ate_m = tools::evaluate(gt, M, eo).ate_m.rmse;
  const dense::DenseStats& d = r.dense_stats;
  std::printf(
      "DENSE LOOPS %s %.0f s seed %llu cover %.0f s: %llu loop closures, %llu relocalisations; se3 ATE "
      "odometry "
      "%.1f mm, map final %.1f mm\n"
      "  along the odometry (--dense-out): median %.1f mm, 95%% %.1f mm, %.1f %% within 4 cm (%zu points)\n"
      "  re-integrated along the map (--dense-map-out): median %.1f mm, 95%% %.1f mm, %.1f %% within 4 cm "
      "(%zu "
      "points)\n"
      "  %llu keyframes fused live in %.2f CPU-s; re-integration %d keyframes (%d without a pose, %llu "
      "overwritten) in %.2f s\n",
      so.scenario.c_str(), so.duration_s, static_cast<unsigned long long>(so.seed), so.cover_s,
      static_cast<unsigned long long>(r.map.loop_closures),
      static_cast<unsigned long long>(r.map.relocalisations), 1e3 * ate_w, 1e3 * ate_m, 1e3 * w.median,
      1e3 * w.p95, 100 * w.within_4cm, w.points, 1e3 * m.median, 1e3 * m.p95, 100 * m.within_4cm, m.points,
      static_cast<unsigned long long>(d.integrated), d.cpu_s, d.rebuild.fused, d.rebuild.no_pose,
      static_cast<unsigned long long>(r.dense_archive_overwritten),
      1e-9 * static_cast<double>(d.rebuild.cpu_ns));
  if (ro.dense.live_reanchor) {
    const tools::Trajectory& online = r.map_trajectory.empty() ? r.trajectory : r.map_trajectory;
    const Score l = score(live, align_to_truth(online, gt), scene);
    std::printf(
        "  live, re-anchored in flight (dense.live_reanchor): median %.1f mm, 95%% %.1f mm, %.1f %% within 4 "
        "cm "
        "(%zu points); %llu corrections, %llu map keyframe lists, %llu keyframes re-fused in %.2f CPU-s (at "
        "most %d waiting, %d left at the end), caught up max %.0f ms\n",
        1e3 * l.median, 1e3 * l.p95, 100 * l.within_4cm, l.points,
        static_cast<unsigned long long>(d.corrections), static_cast<unsigned long long>(d.map_moves),
        static_cast<unsigned long long>(d.reanchored), d.reanchor_cpu_s, d.reanchor_pending_max,
        d.reanchor_left, 1e-6 * static_cast<double>(d.reanchor_catch_up.max()));
    EXPECT_GT(l.points, 1000u);
  }
  EXPECT_TRUE(d.rebuilt);
  EXPECT_GT(m.points, 1000u);
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace kestrel

// The dense map in the pipeline (tools/dense through kestrel replay's
// harness): a simulated figure-8 replayed with --dense-out and
// --dense-octomap-out; the PLY is read back (the contract: vertex x y z as
// float), the .bt read back with liboctomap and checked against the PLY (one
// frame for both), the estimator thread's allocation count stays zero, and
// with the map off nothing of it runs.
#include <gtest/gtest.h>
#include <octomap/OcTree.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "kestrel/dense/dense_config.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/tools/simulator.hpp"
#include "test_data.hpp"

namespace kestrel {
namespace {

// Reads a binary little-endian PLY with float x y z first in its vertex
// record; fails the test on anything else.
std::vector<Eigen::Vector3f> read_ply(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  EXPECT_TRUE(f.good()) << path;
  std::string line;
  std::size_t n = 0, stride = 0;
  std::vector<std::string> props;
  std::getline(f, line);
  EXPECT_EQ(line, "ply");
  while (std::getline(f, line) && line != "end_header") {
    std::istringstream s(line);
    std::string w, type, name;
    s >> w;
    if (w == "format") {
      s >> type;
      EXPECT_EQ(type, "binary_little_endian");
    } else if (w == "element") {
      s >> type >> n;
      EXPECT_EQ(type, "vertex");
    } else if (w == "property") {
      s >> type >> name;
      props.push_back(name);
      stride += type == "float" ? 4 : type == "uchar" ? 1 : 0;
    }
  }
  EXPECT_GE(props.size(), 3u);
  EXPECT_EQ(props[0], "x");
  EXPECT_EQ(props[1], "y");
  EXPECT_EQ(props[2], "z");
  std::vector<Eigen::Vector3f> pts(n);
  std::vector<char> rec(stride);
  for (std::size_t i = 0; i < n; ++i) {
    f.read(rec.data(), static_cast<std::streamsize>(stride));
    EXPECT_TRUE(f.good()) << "PLY ends at vertex " << i << " of " << n;
    std::memcpy(pts[i].data(), rec.data(), 12);
  }
  return pts;
}

std::string simulate(const std::string& dir, double duration_s) {
  tools::SimOptions so;
  so.scenario = "figure8";
  so.duration_s = duration_s;
  so.seed = 3;
  so.width = 320;
  so.height = 240;
  so.threads = 2;
  so.out_path = dir + "/f8.klog";
  tools::run_simulation(so);
  return so.out_path;
}

TEST(DensePipeline, ReplayWritesPlyAndOctomapInOneFrameWithoutAllocating) {
  ASSERT_TRUE(rt::alloc_hook_linked());
  const std::string dir = test::temp_dir("dense_pipeline");
  cli::ReplayOptions ro;
  ro.path = simulate(dir, 8.0);
  ro.pace = drivers::ReplayPace::kLockstep;
  ro.dense_out = dir + "/map.ply";
  ro.dense_octomap_out = dir + "/map.bt";
  int queries_free = 0, queries_occupied = 0;
  ro.on_dense_map = [&](const core::TsdfMap& m) {
    // The planner's query along the flown path: a segment between two
    // nearby poses it flew is not occupied.
    queries_free += m.segment({0, 0, 0}, {0.05, 0, 0}) != core::Occupancy::kOccupied;
    std::vector<Eigen::Vector3f> occ;
    m.occupied_voxels(occ);
    if (!occ.empty())
      queries_occupied += m.occupancy(occ.front().cast<double>()) == core::Occupancy::kOccupied;
  };
  const cli::ReplayReport r = cli::run_replay(ro);
  ASSERT_TRUE(r.dense);
  std::printf("%s", cli::replay_summary(r).c_str());
  EXPECT_EQ(r.steady_allocs, 0) << "the dense hand-off allocated on the estimator thread";
  bool dense_thread = false;
  for (const cli::AppliedThread& t : r.threads) dense_thread = dense_thread || t.name == "kst-dense";
  EXPECT_TRUE(dense_thread);
  EXPECT_GT(r.dense_stats.keyframes, 10u);
  EXPECT_EQ(r.dense_stats.integrated, r.dense_stats.keyframes) << "lockstep waits: nothing dropped";
  EXPECT_EQ(r.dense_stats.dropped, 0u);
  EXPECT_EQ(queries_free, 1);
  EXPECT_EQ(queries_occupied, 1);

  const std::vector<Eigen::Vector3f> pts = read_ply(ro.dense_out);
  ASSERT_EQ(pts.size(), r.dense_points);
  ASSERT_GT(pts.size(), 1000u);
  for (const Eigen::Vector3f& p : pts) ASSERT_TRUE(p.allFinite());

  octomap::OcTree tree(0.1);
  ASSERT_TRUE(tree.readBinary(ro.dense_octomap_out)) << ro.dense_octomap_out;
  EXPECT_DOUBLE_EQ(tree.getResolution(), 0.05);
  EXPECT_GT(tree.getNumLeafNodes(), 0u);
  // The surface points lie in occupied cells of the OctoMap (or next to
  // one: a zero crossing sits between an occupied and a free voxel).
  std::size_t near_occupied = 0;
  for (std::size_t i = 0; i < pts.size(); i += 10) {
    bool hit = false;
    for (int d = 0; d < 7 && !hit; ++d) {
      octomap::point3d q(pts[i].x(), pts[i].y(), pts[i].z());
      if (d > 0) q((d - 1) / 2) += (d % 2 ? 0.05f : -0.05f);
      const octomap::OcTreeNode* n = tree.search(q);
      hit = n != nullptr && tree.isNodeOccupied(n);
    }
    near_occupied += hit;
  }
  EXPECT_GT(static_cast<double>(near_occupied), 0.95 * static_cast<double>((pts.size() + 9) / 10));
}

TEST(DensePipeline, RealtimePaceDropsInsteadOfWaitingAndCounts) {
  const std::string dir = test::temp_dir("dense_realtime");
  cli::ReplayOptions ro;
  ro.path = simulate(dir, 5.0);
  ro.pace = drivers::ReplayPace::kRealtime;
  ro.dense.enabled = true;
  ro.dense.handoff_slots = 1;
  const cli::ReplayReport r = cli::run_replay(ro);
  ASSERT_TRUE(r.dense);
  std::printf("%s", cli::replay_summary(r).c_str());
  EXPECT_EQ(r.steady_allocs, 0);
  EXPECT_GT(r.dense_stats.keyframes, 5u);
  // Every keyframe is accounted for: fused, or dropped and counted.
  EXPECT_EQ(r.dense_stats.integrated + r.dense_stats.dropped, r.dense_stats.keyframes);
  // The same counts by path, as the metrics JSON and the viewer read them.
  EXPECT_EQ(r.counters.count("dense.keyframes"), r.dense_stats.keyframes);
  EXPECT_EQ(r.counters.count("dense.integrated"), r.dense_stats.integrated);
  EXPECT_EQ(r.counters.count("dense.dropped"), r.dense_stats.dropped);
}

// ReplayOptions::on_dense_live: a planner thread gets the running mapper
// before the first record and queries it while the flight goes on (realtime
// pace, as in the air); the handle is withdrawn once kst-dense stopped, and
// the final map answers as the live one last did. The withdrawal waits for a
// query in progress (the mutex the planner holds around its use of the
// mapper), as the contract asks: the mapper is destroyed soon after.
TEST(DensePipeline, APlannerQueriesTheLiveMapThroughTheWholeFlight) {
  ASSERT_TRUE(rt::alloc_hook_linked());
  const std::string dir = test::temp_dir("dense_live_query");
  cli::ReplayOptions ro;
  ro.path = simulate(dir, 5.0);
  ro.pace = drivers::ReplayPace::kRealtime;
  ro.dense.enabled = true;
  std::mutex in_use;                         // held by the planner while it uses the mapper
  const dense::DenseMapper* live = nullptr;  // under in_use
  std::atomic<int> given{0}, withdrawn{0};
  ro.on_dense_live = [&](const dense::DenseMapper* m) {
    (m != nullptr ? given : withdrawn).fetch_add(1);
    const std::lock_guard<std::mutex> lock(in_use);
    live = m;
  };
  std::atomic<bool> done{false};
  std::vector<std::size_t> occupied_seen;
  uint64_t queries = 0;
  std::thread planner([&] {
    while (!done.load(std::memory_order_acquire)) {
      {
        const std::lock_guard<std::mutex> lock(in_use);
        if (live != nullptr) {
          live->read([&](const core::TsdfMap& map) {
            std::vector<Eigen::Vector3f> occ;
            map.occupied_voxels(occ);
            occupied_seen.push_back(occ.size());
          });
          queries = live->queries();
        }
      }
      rt::sleep_for_ns(20'000'000);
    }
  });
  std::size_t final_occupied = 0;
  ro.on_dense_map = [&](const core::TsdfMap& m) {
    std::vector<Eigen::Vector3f> occ;
    m.occupied_voxels(occ);
    final_occupied = occ.size();
  };
  const cli::ReplayReport r = cli::run_replay(ro);
  done.store(true, std::memory_order_release);
  planner.join();
  ASSERT_TRUE(r.dense);
  EXPECT_EQ(given.load(), 1);
  EXPECT_EQ(withdrawn.load(), 1);
  EXPECT_EQ(live, nullptr);
  EXPECT_EQ(r.steady_allocs, 0) << "a planner's queries made the estimator thread allocate";
  // About 4 s of flight sampled every 20 ms; the map the planner saw grew.
  ASSERT_GE(occupied_seen.size(), 20u);
  EXPECT_GT(queries, 20u);
  EXPECT_LT(occupied_seen.front(), occupied_seen.back());
  EXPECT_GT(occupied_seen.back(), 100u);
  EXPECT_LE(occupied_seen.back(), final_occupied + final_occupied / 10)
      << "the live map held more than the finished one";
}

TEST(DensePipeline, WithTheMapOffNothingRuns) {
  const std::string dir = test::temp_dir("dense_off");
  cli::ReplayOptions ro;
  ro.path = simulate(dir, 3.0);
  ro.pace = drivers::ReplayPace::kLockstep;
  const cli::ReplayReport r = cli::run_replay(ro);
  EXPECT_FALSE(r.dense);
  for (const cli::AppliedThread& t : r.threads) EXPECT_NE(t.name, "kst-dense");
  EXPECT_EQ(cli::replay_summary(r).find("dense map"), std::string::npos);
}

// --dense-map-out: every keyframe re-fused from the archive; without a map
// (the default backend has none) M = W, so the two surfaces are the same
// walls: each map-frame point lies within a voxel of some W point.
TEST(DensePipeline, MapFrameSurfaceIsReintegratedFromEveryKeyframe) {
  const std::string dir = test::temp_dir("dense_map_out");
  cli::ReplayOptions ro;
  ro.path = simulate(dir, 6.0);
  ro.pace = drivers::ReplayPace::kLockstep;
  ro.dense_out = dir + "/w.ply";
  ro.dense_map_out = dir + "/m.ply";
  const cli::ReplayReport r = cli::run_replay(ro);
  ASSERT_TRUE(r.dense);
  EXPECT_TRUE(r.dense_stats.rebuilt);
  EXPECT_EQ(static_cast<uint64_t>(r.dense_stats.rebuild.fused), r.dense_stats.integrated);
  EXPECT_EQ(r.dense_stats.rebuild.no_pose, 0);
  EXPECT_EQ(r.dense_archive_overwritten, 0u);
  EXPECT_NE(cli::replay_summary(r).find("dense map in the map frame:"), std::string::npos);
  const std::vector<Eigen::Vector3f> w = read_ply(dir + "/w.ply"), m = read_ply(dir + "/m.ply");
  ASSERT_GT(w.size(), 1000u);
  ASSERT_GT(m.size(), 1000u);
  EXPECT_EQ(m.size(), r.dense_map_points);
  std::size_t near = 0;
  for (std::size_t i = 0; i < m.size(); i += 50) {
    float best = 1e9f;
    for (const Eigen::Vector3f& p : w) best = std::min(best, (p - m[i]).norm());
    near += best <= 0.05f ? 1 : 0;
  }
  EXPECT_GE(static_cast<double>(near), 0.95 * static_cast<double>((m.size() + 49) / 50));
}

// dense.live_reanchor through the pipeline: the corrections come with every
// frame, the estimator thread still allocates nothing, and --dense-out keeps
// its contract (W): fused again along the odometry at the end, it matches the
// surface of the same flight fused without live re-anchoring.
TEST(DensePipeline, LiveReanchoringKeepsDenseOutInWAndAllocatesNothing) {
  const std::string dir = test::temp_dir("dense_live_reanchor");
  const std::string log = simulate(dir, 6.0);
  cli::ReplayOptions ro;
  ro.path = log;
  ro.pace = drivers::ReplayPace::kLockstep;
  ro.dense_out = dir + "/plain.ply";
  const cli::ReplayReport plain = cli::run_replay(ro);
  ro.dense_out = dir + "/live.ply";
  ro.dense.live_reanchor = true;
  const cli::ReplayReport r = cli::run_replay(ro);
  ASSERT_TRUE(r.dense);
  EXPECT_TRUE(r.dense_live_reanchor);
  EXPECT_EQ(r.steady_allocs, 0)
      << "note_correction or the archive hand-off allocated on the estimator thread";
  EXPECT_GE(r.dense_stats.corrections, 1u) << "the map's first alignment never reached kst-dense";
  EXPECT_EQ(static_cast<uint64_t>(r.dense_w_rebuild.fused), r.dense_stats.integrated);
  const std::string summary = cli::replay_summary(r);
  EXPECT_NE(summary.find("dense map live re-anchoring:"), std::string::npos) << summary;
  const std::vector<Eigen::Vector3f> a = read_ply(dir + "/plain.ply"), b = read_ply(dir + "/live.ply");
  ASSERT_GT(a.size(), 1000u);
  ASSERT_GT(b.size(), 1000u);
  std::size_t near = 0;
  for (std::size_t i = 0; i < b.size(); i += 50) {
    float best = 1e9f;
    for (const Eigen::Vector3f& p : a) best = std::min(best, (p - b[i]).norm());
    near += best <= 0.05f ? 1 : 0;
  }
  EXPECT_GE(static_cast<double>(near), 0.95 * static_cast<double>((b.size() + 49) / 50));
  EXPECT_GT(plain.dense_points, 0u);
}

TEST(DenseConfig, SectionReadAndBadKeysNamed) {
  const dense::DenseOptions o =
      dense::dense_options_from_yaml("dense:\n  enabled: true\n  voxel_size_m: 0.1\n", "test.yaml");
  EXPECT_TRUE(o.enabled);
  EXPECT_DOUBLE_EQ(o.tsdf.voxel_size_m, 0.1);
  try {
    dense::dense_options_from_yaml("dense:\n  voxel_size: 0.1\n", "test.yaml");
    FAIL() << "accepted an unknown key";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("test.yaml:2: dense.voxel_size: unknown key"), std::string::npos)
        << e.what();
  }
  try {
    dense::dense_options_from_yaml("dense:\n  voxel_size_m: big\n", "test.yaml");
    FAIL() << "accepted a bad value";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("dense.voxel_size_m"), std::string::npos) << e.what();
  }
  EXPECT_THROW(dense::dense_options_from_yaml("dense:\n  voxel_size_m: 0\n", "test.yaml"),
               std::runtime_error);
  // Every key of the table reads back what it prints.
  EXPECT_EQ(dense::dense_options_table(dense::DenseOptions{}).size(), 22u);
  // The keyframe archive's keys (--dense-map-out), and a bad stride named.
  const dense::DenseOptions a = dense::dense_options_from_yaml(
      "dense:\n  archive_budget_mb: 12\n  archive_stride_px: 4\n", "test.yaml");
  EXPECT_DOUBLE_EQ(a.archive.budget_mb, 12.0);
  EXPECT_EQ(a.archive.stride_px, 4);
  try {
    dense::dense_options_from_yaml("dense:\n  archive_stride_px: 0\n", "test.yaml");
    FAIL() << "accepted stride 0";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("dense.archive_stride_px"), std::string::npos) << e.what();
  }
  // Live re-anchoring's keys, and the viewer's cap (its own `viewer:` section).
  const dense::DenseOptions l = dense::dense_options_from_yaml(
      "dense:\n  live_reanchor: true\n  reanchor_min_shift_m: 0.05\n  reanchor_cpu_s_per_s: 0.1\n",
      "test.yaml");
  EXPECT_TRUE(l.live_reanchor);
  EXPECT_DOUBLE_EQ(l.reanchor_min_shift_m, 0.05);
  EXPECT_DOUBLE_EQ(l.reanchor_cpu_s_per_s, 0.1);
  try {
    dense::dense_options_from_yaml("dense:\n  live_reanchor: true\n  archive_budget_mb: 0\n", "test.yaml");
    FAIL() << "accepted live re-anchoring without an archive";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("dense.live_reanchor"), std::string::npos) << e.what();
  }
  EXPECT_DOUBLE_EQ(dense::dense_view_options_from_yaml("dense:\n  enabled: true\n", "test.yaml").max_kbps,
                   dense::DenseViewOptions{}.max_kbps);
  const dense::DenseViewOptions v = dense::dense_view_options_from_yaml(
      "viewer:\n  dense_max_kbps: 500\n  dense_period_s: 0.2\n", "test.yaml");
  EXPECT_DOUBLE_EQ(v.max_kbps, 500.0);
  EXPECT_DOUBLE_EQ(v.period_s, 0.2);
  try {
    dense::dense_view_options_from_yaml("viewer:\n  dense_kbps: 500\n", "test.yaml");
    FAIL() << "accepted an unknown viewer key";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("test.yaml:2: viewer.dense_kbps: unknown key"), std::string::npos)
        << e.what();
  }
  try {
    dense::dense_view_options_from_yaml("viewer:\n  dense_max_kbps: 10\n", "test.yaml");
    FAIL() << "accepted a cap below one block a second";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("viewer.dense_max_kbps must be"), std::string::npos) << e.what();
  }
  try {
    dense::dense_view_options_from_yaml("viewer:\n  dense_period_s: soon\n", "test.yaml");
    FAIL() << "accepted a bad period";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("test.yaml:2: viewer.dense_period_s: bad value"), std::string::npos)
        << e.what();
  }
}

}  // namespace
}  // namespace kestrel

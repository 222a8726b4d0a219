// The ROS outputs' map hand-off (tools/kestrel/map_topics.hpp, docs/ros2.md)
// through the real harness in fast pace (estimator and output on their own
// threads): the local map's points at most map_points_rate_hz of log time,
// every keyframe, the map's final word; and no heap allocation on the
// estimator thread after warm-up with the hand-off on.
#include <algorithm>

#include "kestrel/rt/alloc_counter.hpp"
#include "pipeline_fixture.hpp"

namespace kestrel::pipeline_test {
namespace {

TEST(MapTopics, CloudsAtTheRateKeyframesAndTheFinalMapWithoutEstimatorAllocations) {
  ASSERT_TRUE(rt::alloc_hook_linked())
      << "the allocation hook is not linked: steady_allocs cannot be checked";
  const std::string dir = test::temp_dir("map_topics");
  tools::SimOptions o = small_sim(8.0, 5);
  o.scenario = "figure8";  // it moves: keyframes and a growing map
  o.width = 320;
  o.height = 240;
  o.out_path = dir + "/f8.klog";
  tools::run_simulation(o);

  cli::ReplayOptions ro;
  ro.path = o.out_path;
  ro.pace = drivers::ReplayPace::kFast;
  ro.estimator = "window";
  ro.map_points_rate_hz = 2.0;
  std::vector<std::pair<int64_t, int>> clouds;  // t_ns, points
  int max_abs_coordinate_m = 0;
  std::vector<int64_t> keyframes;
  ro.on_map_cloud = [&](const cli::MapCloud& c) {
    clouds.emplace_back(c.t_ns, c.n);
    for (int i = 0; i < 3 * c.n; ++i)
      max_abs_coordinate_m = std::max(max_abs_coordinate_m, static_cast<int>(std::abs(c.xyz_W[i])));
  };
  ro.on_keyframe = [&](const cli::KeyframePose& k) { keyframes.push_back(k.t_ns); };
  int finals = 0;
  size_t final_keyframes = 0;
  ro.on_map_final = [&](const cli::MapFinal& f) {
    ++finals;
    final_keyframes = f.keyframes.size();
  };
  const cli::ReplayReport r = cli::run_replay(ro);
  std::filesystem::remove_all(dir);

  EXPECT_TRUE(r.alloc_counting);
  EXPECT_EQ(r.steady_allocs, 0) << "heap allocations on the estimator thread after warm-up";
  ASSERT_GE(clouds.size(), 3u);
  EXPECT_EQ(r.counters.count("ros2.map_clouds"), clouds.size());
  EXPECT_EQ(r.counters.count("ros2.map_clouds_dropped"), 0u);
  EXPECT_EQ(r.counters.count("ros2.map_keyframes_dropped"), 0u);
  // At most 2 Hz of log time: 8 s give at most 16 (+1 for the first).
  EXPECT_LE(clouds.size(), 17u);
  for (size_t i = 1; i < clouds.size(); ++i)
    EXPECT_GE(clouds[i].first - clouds[i - 1].first, 500'000'000) << "cloud " << i << " too soon";
  for (const auto& [t, n] : clouds) {
    EXPECT_GT(n, 0);
    EXPECT_LE(n, cli::kMapCloudMaxPoints);
  }
  EXPECT_LT(max_abs_coordinate_m, 100) << "map points far outside the simulated room";
  ASSERT_GE(keyframes.size(), 3u);
  EXPECT_TRUE(std::is_sorted(keyframes.begin(), keyframes.end()));
  EXPECT_EQ(std::adjacent_find(keyframes.begin(), keyframes.end()), keyframes.end()) << "a keyframe twice";
  ASSERT_TRUE(r.has_map) << "the window backend maps by default";
  EXPECT_EQ(finals, 1);
  EXPECT_GE(final_keyframes, 2u);
}

}  // namespace
}  // namespace kestrel::pipeline_test

// The map's memory over a long flight that keeps revisiting the same circuit
// (docs/map.md "Soak"): a simulated figure-8, replayed with the map and loop
// closing on. After the warm-up the process's RSS and the map's keyframes and
// points must stay flat: the map is sized once, culling keeps a revisited
// place from growing it. Label bench: 3 minutes of flight by default;
// KESTREL_SOAK_S sets another length (docs/map.md: the 30-minute figure).
#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <vector>

#include "kestrel/replay_runner.hpp"
#include "kestrel/tools/simulator.hpp"
#include "map_pipeline.hpp"
#include "test_data.hpp"

namespace kestrel::map_test {
namespace {

TEST(MapSoak, MemoryAndMapStayFlatOverARevisitedCircuit) {
  const char* env = std::getenv("KESTREL_SOAK_S");
  const double flight_s = env != nullptr && std::atof(env) > 0 ? std::atof(env) : 180.0;
  const std::string dir = test::temp_dir("map_soak");
  tools::SimOptions so = figure8(flight_s, 9, 160, 120);
  so.out_path = dir + "/soak.klog";
  tools::run_simulation(so);
  cli::ReplayOptions ro;
  ro.path = so.out_path;
  ro.pace = drivers::ReplayPace::kFast;
  ro.config = map_config();
  struct Sample {
    double t_s, rss_mb;
    uint32_t keyframes, points;
  };
  std::vector<Sample> samples;
  samples.reserve(4096);
  int64_t t0 = -1;
  double next_s = 0;
  ro.on_pose = [&](const core::PoseSample& p) {
    if (t0 < 0) t0 = p.t_ns;
    const double t = 1e-9 * static_cast<double>(p.t_ns - t0);
    if (t < next_s) return;
    next_s = t + 10.0;
    samples.push_back({t, test::rss_mb(), p.map.keyframes, p.map.points});
  };
  const cli::ReplayReport r = cli::run_replay(ro);
  ASSERT_GT(samples.size(), 6u);
  // Warm-up: the first third (two laps at least); then the flat part.
  const double warm_s = std::max(30.0, flight_s / 3);
  double rss_lo = 1e18, rss_hi = 0;
  uint32_t kf_lo = ~0u, kf_hi = 0, pt_hi = 0, pt_lo = ~0u;
  for (const Sample& s : samples) {
    std::printf("SOAK t %6.0f s: RSS %.1f MB, %u keyframes, %u points\n", s.t_s, s.rss_mb, s.keyframes,
                s.points);
    if (s.t_s < warm_s) continue;
    rss_lo = std::min(rss_lo, s.rss_mb);
    rss_hi = std::max(rss_hi, s.rss_mb);
    kf_lo = std::min(kf_lo, s.keyframes);
    kf_hi = std::max(kf_hi, s.keyframes);
    pt_lo = std::min(pt_lo, s.points);
    pt_hi = std::max(pt_hi, s.points);
  }
  std::printf(
      "SOAK-TABLE | %.0f s | RSS %.1f-%.1f MB after %.0f s | keyframes %u-%u | points %u-%u | loops %llu "
      "|\n%s\n",
      flight_s, rss_lo, rss_hi, warm_s, kf_lo, kf_hi, pt_lo, pt_hi,
      static_cast<unsigned long long>(r.map.loop_closures), r.backend_summary.c_str());
  EXPECT_LT(rss_hi - rss_lo, 10.0) << "RSS grew after the warm-up";
  EXPECT_LT(kf_hi, 1.5 * kf_lo + 10) << "the map keeps growing on a circuit it has mapped";
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace kestrel::map_test

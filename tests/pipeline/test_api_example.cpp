// docs/api.md's example program (extracted from the page at configure time,
// built as `api_example`) run on a short simulated log: its TUM output must
// follow the simulator's ground truth.
#include <gtest/gtest.h>

#include <array>
#include <cstdio>
#include <sstream>
#include <string>

#include "kestrel/tools/simulator.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "run_command.hpp"
#include "test_data.hpp"

TEST(ApiExample, TracksTheSimulatedFlight) {
  const std::string dir = kestrel::test::temp_dir("api_example");
  kestrel::tools::SimOptions o;
  o.scenario = "hover";
  o.duration_s = 8.0;
  o.seed = 5;
  o.width = 160;
  o.height = 120;
  o.threads = 1;
  o.out_path = dir + "/hover.klog";
  kestrel::tools::run_simulation(o);

  const std::string cmd =
      kestrel::test::built_program("api_example") + " " + o.out_path + " vo 2>" + dir + "/err.txt";
  FILE* p = popen(cmd.c_str(), "r");
  ASSERT_NE(p, nullptr);
  std::string out;
  std::array<char, 4096> buf{};
  size_t n;
  while ((n = fread(buf.data(), 1, buf.size(), p)) > 0) out.append(buf.data(), n);
  const int st = pclose(p);
  ASSERT_TRUE(WIFEXITED(st) && WEXITSTATUS(st) == 0) << out;

  kestrel::tools::Trajectory est;
  std::istringstream in(out);
  double t, x, y, z, qx, qy, qz, qw;
  while (in >> t >> x >> y >> z >> qx >> qy >> qz >> qw) {
    kestrel::tools::TimedPose tp;
    tp.t_ns = static_cast<int64_t>(t * 1e9 + 0.5);
    tp.p = Eigen::Vector3d(x, y, z);
    tp.q = Eigen::Quaterniond(qw, qx, qy, qz).normalized();
    est.push_back(tp);
  }
  // One line per frame after initialisation: 30 Hz for most of 8 s.
  ASSERT_GT(est.size(), 180u) << out.substr(0, 500);
  std::vector<std::string> warnings;
  const auto gt = kestrel::tools::load_trajectory(o.out_path, &warnings);
  kestrel::tools::EvalOptions eo;
  eo.max_gap_ms = 10;
  const auto res = kestrel::tools::evaluate(gt, est, eo);
  EXPECT_GT(res.matched, 180);
  EXPECT_LT(res.ate_m.rmse, 0.05) << kestrel::tools::to_text(res);
  std::printf("api_example: %zu poses, ATE rmse %.4f m, RPE %.4f m per %.1f s\n", est.size(), res.ate_m.rmse,
              res.rpe_trans_rmse_m, res.rpe_delta_s);
}

#include <fstream>
#include <map>

#include "kestrel/core/kestrel.hpp"
#include "kestrel/drivers/open_log.hpp"

// The embedding API's defaults are the command line's (issue 45): `auto`
// picks the window backend with its map and loop closer, whose work runs
// inline after each frame, so the poses are those `kestrel replay --pace
// lockstep` writes for the same log; MapWork::kCaller leaves that work to
// map_step() on a thread of the caller's.
TEST(EmbeddedApi, TheDefaultsAreTheCommandLinesWithTheMapInline) {
  const std::string dir = kestrel::test::temp_dir("api_defaults");
  kestrel::tools::SimOptions o;
  o.scenario = "figure8";
  o.duration_s = 6.0;
  o.seed = 9;
  o.width = 160;
  o.height = 120;
  o.out_path = dir + "/f8.klog";
  kestrel::tools::run_simulation(o);
  const kestrel::test::CmdResult r = kestrel::test::run_kestrel(
      "replay " + o.out_path + " --pace lockstep --traj-out " + dir + "/replay.txt");
  ASSERT_EQ(r.code, 0) << r.out;
  std::map<int64_t, Eigen::Vector3d> replay;
  {
    std::ifstream f(dir + "/replay.txt");
    std::string line;
    while (std::getline(f, line)) {
      if (line.empty() || line[0] == '#') continue;
      std::istringstream in(line);
      double t, x, y, z;
      in >> t >> x >> y >> z;
      replay[static_cast<int64_t>(std::llround(t * 1e9))] = Eigen::Vector3d(x, y, z);
    }
  }
  ASSERT_GT(replay.size(), 150u);

  auto run = [&](kestrel::MapWork work, size_t* compared, double* max_diff_m, uint64_t* map_steps) {
    auto log = kestrel::drivers::open_log(o.out_path);
    kestrel::Estimator est(log->rig(), "auto", work);
    EXPECT_STREQ(est.backend_name(), "window");
    EXPECT_TRUE(est.has_map());
    *compared = 0;
    *max_diff_m = 0;
    est.on_state(
        [&](const kestrel::State& s) {
          if (s.quality == kestrel::core::TrackingQuality::kUninitialized ||
              s.quality == kestrel::core::TrackingQuality::kLost)
            return;
          const auto it = replay.find(s.t_ns);
          if (it == replay.end()) return;
          ++*compared;
          *max_diff_m = std::max(*max_diff_m, (it->second - s.p_WB).norm());
        },
        /*imu_rate=*/false);
    kestrel::drivers::LogRecord rec;
    kestrel::drivers::LogImage rgb;
    while (log->next(rec)) {
      if (rec.type == kestrel::drivers::RecordType::kImu) est.feed_imu(rec.imu);
      if (rec.type == kestrel::drivers::RecordType::kRgb) rgb = rec.image;
      if (rec.type == kestrel::drivers::RecordType::kDepth && rec.image.t_ns == rgb.t_ns)
        est.feed_rgbd(rgb.t_ns, rgb.view(), rec.image.view());
      if (work == kestrel::MapWork::kCaller)
        while (est.map_step()) ++*map_steps;
    }
    EXPECT_TRUE(est.state().map_active);
  };
  size_t n_inline = 0, n_caller = 0;
  double d_inline = 0, d_caller = 0;
  uint64_t steps_inline = 0, steps_caller = 0;
  run(kestrel::MapWork::kInline, &n_inline, &d_inline, &steps_inline);
  run(kestrel::MapWork::kCaller, &n_caller, &d_caller, &steps_caller);
  std::printf(
      "embedded auto: %zu poses compared, max |diff| %.2e m inline; %zu, %.2e m with map_step() (%llu "
      "steps)\n",
      n_inline, d_inline, n_caller, d_caller, static_cast<unsigned long long>(steps_caller));
  EXPECT_GT(n_inline, replay.size() * 95 / 100);
  EXPECT_LT(d_inline, 2e-6) << "the inline map must give lockstep replay's poses";
  EXPECT_EQ(steps_inline, 0u);
  EXPECT_GT(steps_caller, 10u) << "map_step() did the map's work";
  EXPECT_GT(n_caller, replay.size() * 95 / 100);
  EXPECT_LT(d_caller, 2e-6);
}

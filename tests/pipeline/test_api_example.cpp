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

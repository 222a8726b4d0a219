// `kestrel bench --cpu-budget` end to end: a 3 s, 160x120 figure-8 through
// the window backend under callgrind (3 s: the replay's timing statistics
// start after 2 s). The figures themselves are the bench's
// business (docs/embedded.md); this checks that every stage is found and
// charged, and that the parts add up as a call tree must.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <string>

#include "run_command.hpp"

namespace fs = std::filesystem;

TEST(CpuBudgetCli, EveryStageIsChargedAndThePartsFitTheWhole) {
  if (kestrel::test::cross_emulated())
    GTEST_SKIP()
        << "SKIPPED LOUDLY: this build runs under an emulator (" << KESTREL_RUN_PREFIX
        << "); `kestrel bench --cpu-budget` starts the host's valgrind, which cannot run its binaries. "
           "The native suites run this test.";
  const fs::path dir = fs::temp_directory_path() / ("kestrel_cpu_budget_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const std::string json = (dir / "budget.json").string();
  const auto r = kestrel::test::run_kestrel(
      "bench --cpu-budget --duration 3 --width 160 --height 120 --mapping off --workdir " + dir.string() +
      " --json " + json);
  ASSERT_EQ(r.code, 0) << r.out;
  std::ifstream f(json);
  ASSERT_TRUE(f.good()) << json;
  const nlohmann::json j = nlohmann::json::parse(f);
  EXPECT_EQ(j["backend"], "window");
  const double frames = j["frames"].get<double>();
  EXPECT_GE(frames, 80.0);  // 3 s at 30 Hz, less a few frames before the start
  EXPECT_GE(j["optimizer_solves"].get<double>(), frames - 5);
  EXPECT_GE(j["imu_samples"].get<double>(), 1000.0);
  std::map<std::string, double> per;
  for (const auto& st : j["stages"]) {
    ASSERT_TRUE(st["instructions_per_unit"].is_number()) << st.dump();
    EXPECT_GT(st["calls"].get<double>(), 0.0) << st["stage"];
    per[st["stage"].get<std::string>()] = st["instructions_per_unit"].get<double>();
  }
  ASSERT_EQ(per.size(), 10u);
  const double parts = per["ORB extraction"] + per["depth back-projection"] + per["IMU-predicted matching"] +
                       per["LONSC"] + per["pose refinement"] + per["keyframe"];
  EXPECT_LT(parts, per["tracking, whole frame"]);
  EXPECT_GT(parts, 0.9 * per["tracking, whole frame"])
      << "tracking's instructions went somewhere no stage names";
  EXPECT_GT(per["optimizer solve"], 1e5);
  EXPECT_GT(per["IMU propagation"], 50.0);
  EXPECT_LT(per["IMU propagation"], 1e4);
  EXPECT_TRUE(j["here"]["tracking_ms_p50"].is_number());
  EXPECT_FALSE(fs::exists(dir / "cpu_budget.klog")) << "the generated log is removed unless --keep-logs";
  fs::remove_all(dir);
}

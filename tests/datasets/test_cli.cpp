// A simulated RGB-D + IMU flight exported to the ETH3D layout runs through
// `kestrel replay` and `kestrel eval` end to end, and scores like the .klog.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>

#include "run_command.hpp"
#include "test_data.hpp"
#include "test_scale.hpp"

namespace {

using kestrel::test::CmdResult;
CmdResult run(const std::string& args) { return kestrel::test::run_kestrel(args); }

double ate_of(const CmdResult& e) {
  const size_t k = e.out.find("ate_rmse_m: ");
  if (k == std::string::npos) return NAN;
  return std::stod(e.out.substr(k + 12));
}

TEST(DatasetsCli, SimExportedToEth3dReplaysAndScoresLikeTheKlog) {
  const std::string dir = kestrel::test::temp_dir("datasets_cli_" + std::to_string(getpid()));
  const std::string klog = dir + "/sim.klog", eth3d = dir + "/sim_eth3d";
  // Nine runs of `kestrel` over the flight: 4 s, 3 s sanitizer-sized (test_scale.hpp).
  const std::string duration = kestrel::test::scaled<std::string>("4", "3");
  const CmdResult sim = run("sim --scenario figure8 --duration " + duration +
                            " --seed 5 --width 160 --height 120 --out " + klog);
  ASSERT_EQ(sim.code, 0) << sim.out;
  const CmdResult conv =
      run("convert " + klog + " --to eth3d --out " + eth3d + " --rig-out " + dir + "/rig.yaml");
  ASSERT_EQ(conv.code, 0) << conv.out;
  for (const char* f :
       {"rgb.txt", "depth.txt", "associated.txt", "calibration.txt", "groundtruth.txt", "imu.txt"})
    EXPECT_TRUE(std::filesystem::exists(eth3d + "/" + f)) << f;

  // Detected as ETH3D; T_BC and the IMU noise come from --rig (the ETH3D layout has no place for them).
  const CmdResult rep =
      run("replay " + eth3d + " --rig " + dir + "/rig.yaml --traj-out " + dir + "/est_eth3d.txt");
  ASSERT_EQ(rep.code, 0) << rep.out;
  EXPECT_NE(rep.out.find("eth3d"), std::string::npos) << rep.out;
  EXPECT_EQ(rep.out.find("problem:"), std::string::npos) << rep.out;
  ASSERT_EQ(run("replay " + klog + " --traj-out " + dir + "/est_klog.txt -q").code, 0);

  // Ground truth read back from the folder (camera poses turned into body poses) scores the estimate.
  const CmdResult e1 = run("eval --gt " + eth3d + " --est " + dir + "/est_eth3d.txt");
  ASSERT_EQ(e1.code, 0) << e1.out;
  const CmdResult e2 = run("eval --gt " + klog + " --est " + dir + "/est_klog.txt");
  ASSERT_EQ(e2.code, 0) << e2.out;
  const double ate_eth3d = ate_of(e1), ate_klog = ate_of(e2);
  ASSERT_TRUE(std::isfinite(ate_eth3d)) << e1.out;
  ASSERT_TRUE(std::isfinite(ate_klog)) << e2.out;
  // The simulated camera has lens distortion and ETH3D images are undistorted pinhole, so the
  // export undistorts them: the tracker sees other pixels and scores close to, not exactly, the .klog.
  EXPECT_LT(ate_eth3d, 2.0 * ate_klog + 0.05) << e1.out << e2.out;
  // The IMU stream and the ground truth cross the format exactly (ground truth to 1e-12 m through the
  // camera-pose conversion): IMU dead reckoning scores the same on both to the printed digits.
  ASSERT_EQ(run("replay " + eth3d + " --estimator imu --traj-out " + dir + "/imu_eth3d.txt -q").code, 0);
  ASSERT_EQ(run("replay " + klog + " --estimator imu --traj-out " + dir + "/imu_klog.txt -q").code, 0);
  const double imu_eth3d = ate_of(run("eval --gt " + eth3d + " --est " + dir + "/imu_eth3d.txt"));
  const double imu_klog = ate_of(run("eval --gt " + klog + " --est " + dir + "/imu_klog.txt"));
  ASSERT_TRUE(std::isfinite(imu_klog));
  EXPECT_NEAR(imu_eth3d, imu_klog, 1e-9);
  // And the estimate scored against the .klog's own ground truth agrees with the folder's.
  const CmdResult e3 = run("eval --gt " + klog + " --est " + dir + "/est_eth3d.txt");
  ASSERT_EQ(e3.code, 0) << e3.out;
  EXPECT_NEAR(ate_of(e3), ate_eth3d, 1e-6);

  // The folder's own kestrel_rig.yaml stands in for --rig: same trajectory.
  ASSERT_EQ(run("replay " + eth3d + " --traj-out " + dir + "/est_own.txt -q").code, 0);
  const CmdResult e4 = run("eval --gt " + eth3d + " --est " + dir + "/est_own.txt");
  EXPECT_NEAR(ate_of(e4), ate_eth3d, 1e-9) << e4.out;
  // Without any rig the folder still replays, with the missing extrinsic said out loud.
  std::filesystem::remove(eth3d + "/kestrel_rig.yaml");
  const CmdResult norig = run("replay " + eth3d + " --traj-out " + dir + "/est_norig.txt");
  EXPECT_EQ(norig.code, 0) << norig.out;
  EXPECT_NE(norig.out.find("assumed"), std::string::npos) << norig.out;
  // A folder without calibration.txt and no --rig: the error names the missing field.
  std::filesystem::remove(eth3d + "/calibration.txt");
  const CmdResult nocal = run("replay " + eth3d + " --format eth3d");
  EXPECT_EQ(nocal.code, 1) << nocal.out;
  EXPECT_NE(nocal.out.find("fx fy cx cy"), std::string::npos) << nocal.out;
}

TEST(DatasetsCli, SimWritesAnEth3dFolderDirectly) {
  const std::string dir = kestrel::test::temp_dir("datasets_sim_eth3d_" + std::to_string(getpid()));
  const std::string eth3d = dir + "/flight";
  const CmdResult sim = run("sim --scenario hover --duration 3 --seed 2 --width 160 --height 120 --out " +
                            dir + "/sim.klog --export-eth3d " + eth3d);
  ASSERT_EQ(sim.code, 0) << sim.out;
  EXPECT_NE(sim.out.find("ETH3D folder"), std::string::npos) << sim.out;
  const CmdResult rep = run("replay " + eth3d + " --traj-out " + dir + "/est.txt");
  ASSERT_EQ(rep.code, 0) << rep.out;
  EXPECT_NE(rep.out.find("eth3d"), std::string::npos) << rep.out;
  const CmdResult ev = run("eval --gt " + eth3d + " --est " + dir + "/est.txt");
  ASSERT_EQ(ev.code, 0) << ev.out;
  EXPECT_LT(ate_of(ev), 0.05) << ev.out;
}

TEST(DatasetsCli, ConvertRejectsUnknownFormats) {
  EXPECT_EQ(run("convert x --out y.klog --format banana").code, 2);
  EXPECT_EQ(run("convert x --out y --to banana").code, 2);
  EXPECT_EQ(run("convert x --out folder").code, 2) << "no --to and no telling extension";
  const CmdResult r = run("convert /nonexistent/folder --out y.klog");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.out.find("/nonexistent/folder"), std::string::npos) << r.out;
}

}  // namespace

// `kestrel devices | record | run` without hardware: devices says what it
// found and what is built; record and run exit 1 naming what is missing.
// Runs the kestrel binary of this build; skips loudly when it is not built
// yet or predates these commands.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include "run_command.hpp"

namespace {

const std::string kBin = std::string(KESTREL_BIN_DIR) + "/kestrel";
const std::string kSrc = KESTREL_SOURCE_DIR;

int run(const std::string& args, std::string& out) {
  const kestrel::test::CmdResult r = kestrel::test::run_kestrel(args);
  out = r.out;
  return r.code;
}

bool have_commands() {
  std::string out;
  return std::filesystem::exists(kBin) && run("help", out) == 0 && out.find("record") != std::string::npos;
}
#define require_commands() \
  if (!have_commands()) GTEST_SKIP() << "kestrel binary missing or without the driver commands: " << kBin

TEST(CliDrivers, DevicesListsOrSaysNone) {
  require_commands();
  std::string out;
  EXPECT_EQ(run("devices", out), 0) << out;
  EXPECT_NE(out.find("drivers in this build:"), std::string::npos) << out;
}

TEST(CliDrivers, RecordWithoutHardwareExitsOneNamingTheDevices) {
  require_commands();
  const auto klog = std::filesystem::temp_directory_path() / "kestrel_cli_record_none.klog";
  std::string out;
  EXPECT_EQ(run("record --config " + kSrc + "/configs/openni2_bmx055_i2c.yaml --out " + klog.string(), out),
            1)
      << out;
  EXPECT_NE(out.find("cannot start the live sensors"), std::string::npos) << out;
  EXPECT_NE(out.find("OpenNI2"), std::string::npos) << out;
  EXPECT_NE(out.find("/dev/i2c-1"), std::string::npos) << out;
  EXPECT_FALSE(std::filesystem::exists(klog));  // nothing half-written
}

TEST(CliDrivers, RunWithoutHardwareExitsOne) {
  require_commands();
  std::string out;
  EXPECT_EQ(run("run --config " + kSrc + "/configs/realsense_v4l2_bmx055_usb.yaml", out), 1) << out;
  EXPECT_NE(out.find("/dev/video4"), std::string::npos) << out;
  EXPECT_NE(out.find("USB"), std::string::npos) << out;
  EXPECT_NE(out.find("cannot start the live sensors"), std::string::npos) << out;
}

TEST(CliDrivers, RunChecksTheEstimatorBeforeTheSensors) {
  require_commands();
  const auto cfg = std::filesystem::temp_directory_path() / "kestrel_cli_run_backend.yaml";
  {
    std::ifstream in(kSrc + "/configs/openni2_bmx055_i2c.yaml");
    std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    const auto at = text.find("backend: ekf");
    ASSERT_NE(at, std::string::npos) << "the shipped config names its backend";
    text.replace(at, 12, "backend: kalman");
    std::ofstream(cfg) << text;
  }
  std::string out;
  EXPECT_EQ(run("run --config " + cfg.string(), out), 1) << out;
  EXPECT_NE(out.find("estimator.backend: unknown backend 'kalman'"), std::string::npos) << out;
  EXPECT_NE(out.find("ekf"), std::string::npos) << out;  // the list of known names
  EXPECT_EQ(run("run --config " + kSrc + "/configs/openni2_bmx055_i2c.yaml --estimator nope", out), 2) << out;
  EXPECT_NE(out.find("unknown --estimator 'nope'"), std::string::npos) << out;
  std::filesystem::remove(cfg);
}

TEST(CliDrivers, ReplayTakesTheBackendFromAConfig) {
  require_commands();
  const auto dir = std::filesystem::temp_directory_path() / "kestrel_cli_replay_config";
  std::filesystem::create_directories(dir);
  const std::string log = (dir / "static.klog").string(), metrics = (dir / "m.json").string();
  const std::string cfg = (dir / "est.yaml").string();
  std::string out;
  ASSERT_EQ(run("sim --scenario static --duration 1 --width 64 --height 48 --out " + log, out), 0) << out;
  std::ofstream(cfg) << "estimator:\n  backend: imu\n";
  ASSERT_EQ(run("replay " + log + " --config " + cfg + " -q --metrics-out " + metrics, out), 0) << out;
  std::ifstream m(metrics);
  const std::string json((std::istreambuf_iterator<char>(m)), std::istreambuf_iterator<char>());
  EXPECT_NE(json.find("\"estimator\": \"imu-dead-reckoning\""), std::string::npos) << json;
  // --estimator wins over the config.
  ASSERT_EQ(run("replay " + log + " --config " + cfg + " --estimator ekf -q --metrics-out " + metrics, out),
            0)
      << out;
  std::ifstream m2(metrics);
  const std::string json2((std::istreambuf_iterator<char>(m2)), std::istreambuf_iterator<char>());
  EXPECT_NE(json2.find("\"estimator\": \"ekf\""), std::string::npos) << json2;
  std::ofstream(cfg) << "estimator:\n  backend: kalman\n";
  EXPECT_EQ(run("replay " + log + " --config " + cfg, out), 1) << out;
  EXPECT_NE(out.find("estimator.backend: unknown backend 'kalman'"), std::string::npos) << out;
  std::filesystem::remove_all(dir);
}

TEST(CliDrivers, BadConfigNamesFileAndKey) {
  require_commands();
  const auto cfg = std::filesystem::temp_directory_path() / "kestrel_cli_bad.yaml";
  std::ofstream(cfg)
      << "rig:\n  camera: {width_px: 640, height_px: 480, fx_px: 1, fy_px: 1, cx_px: 0, cy_px: 0}\n"
         "drivers:\n  imu: {type: bmx055_i2c, gyro_range_dps: 3000, i2c: {bus_device: /dev/i2c-1}}\n";
  std::string out;
  EXPECT_EQ(run("record --config " + cfg.string() + " --out /tmp/x.klog", out), 1) << out;
  EXPECT_NE(out.find("drivers.imu.gyro_range_dps"), std::string::npos) << out;
  std::filesystem::remove(cfg);
}

}  // namespace

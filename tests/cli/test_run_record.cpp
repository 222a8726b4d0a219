// `kestrel run` end to end without hardware: the `log` sensors play a
// simulated flight through the live drivers' sinks and threads, and run
// estimates it while --record writes the sensors to a .klog (replayable, the
// same records as the source), --traj-out the trajectory (scored against the
// source's ground truth) and --mavlink-udp the link (HEARTBEAT + ODOMETRY).
// The flight's camera is 12 ms off the IMU and the rig says so: the live path
// applies the offset as the readers do.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <fstream>
#include <map>
#include <thread>
#include <vector>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/mavlink/mavlink_decoder.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "run_command.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

std::vector<drivers::LogRecord> read_all(const std::string& path) {
  drivers::KlogReader r(path);
  std::vector<drivers::LogRecord> v;
  drivers::LogRecord rec;
  while (r.next(rec)) v.push_back(rec);
  return v;
}

TEST(RunRecord, RecordsTheFlightItEstimatesAndWritesItsTrajectory) {
  const std::string dir = temp_dir("run_record");
  const std::string src = dir + "/src.klog";
  CmdResult r = run_kestrel(
      "sim --scenario figure8 --duration 6 --seed 4 --width 160 --height 120 --time-offset-ms 12 "
      "--out " +
      src);
  ASSERT_EQ(r.code, 0) << r.out;
  const Rig rig = drivers::KlogReader(src).rig();
  ASSERT_EQ(rig.time_offset_cam_imu_ns, 12'000'000);
  std::ofstream(dir + "/rig.yaml") << drivers::rig_to_yaml(rig);
  std::ofstream(dir + "/live.yaml") << "rig: rig.yaml\n"
                                       "drivers:\n"
                                       "  camera: {type: log, width_px: 160, height_px: 120, rate_hz: 30}\n"
                                       "  imu: {type: log}\n"
                                       "  log: {path: src.klog}\n"
                                       "estimator:\n"
                                       "  backend: window\n";
  // A flight controller on loopback.
  const int rx = socket(AF_INET, SOCK_DGRAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(bind(rx, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
  socklen_t len = sizeof a;
  getsockname(rx, reinterpret_cast<sockaddr*>(&a), &len);
  std::vector<uint8_t> link;
  std::thread reader([&] {
    uint8_t buf[2048];
    pollfd p{rx, POLLIN, 0};
    while (poll(&p, 1, 4000) > 0) {
      const ssize_t n = recv(rx, buf, sizeof buf, 0);
      if (n <= 0) break;
      link.insert(link.end(), buf, buf + n);
    }
  });
  r = run_kestrel("run --config " + dir + "/live.yaml --duration 7.5 --record " + dir +
                  "/rec.klog --traj-out " + dir +
                  "/traj.txt --mavlink-udp 127.0.0.1:" + std::to_string(ntohs(a.sin_port)));
  reader.join();
  close(rx);
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("recording the sensors to"), std::string::npos) << r.out;

  // The recording holds the same sensor records as the source, stamps and all
  // (both read through the reader, which applies the same 12 ms).
  const auto a_recs = read_all(src);
  const auto b_recs = read_all(dir + "/rec.klog");
  EXPECT_EQ(drivers::KlogReader(dir + "/rec.klog").rig().time_offset_cam_imu_ns, 12'000'000);
  std::vector<int64_t> imu_a, imu_b, rgb_a, rgb_b;
  size_t depth_b = 0;
  for (const auto& x : a_recs) {
    if (x.type == drivers::RecordType::kImu) imu_a.push_back(x.imu.t_ns);
    if (x.type == drivers::RecordType::kRgb) rgb_a.push_back(x.image.t_ns);
  }
  for (const auto& x : b_recs) {
    if (x.type == drivers::RecordType::kImu) imu_b.push_back(x.imu.t_ns);
    if (x.type == drivers::RecordType::kRgb) rgb_b.push_back(x.image.t_ns);
    depth_b += x.type == drivers::RecordType::kDepth;
  }
  EXPECT_EQ(imu_b, imu_a) << "every IMU sample recorded";
  EXPECT_EQ(rgb_b, rgb_a) << "every frame recorded with its stamp";
  EXPECT_EQ(depth_b, rgb_b.size());

  // The trajectory it estimated live, against the source's ground truth.
  std::vector<std::string> warnings;
  const tools::Trajectory gt = tools::load_trajectory(src, &warnings);
  const tools::Trajectory est = tools::load_trajectory(dir + "/traj.txt", &warnings);
  EXPECT_GT(est.size(), rgb_a.size() * 8 / 10);
  const tools::EvalResult e = tools::evaluate(gt, est, tools::EvalOptions{});
  std::printf("run: %zu poses, ATE %.2f cm over %.1f m\n", est.size(), 100 * e.ate_m.rmse, e.gt_length_m);
  EXPECT_LT(e.ate_m.rmse, 0.10);

  // And the recording replays.
  r = run_kestrel("replay " + dir + "/rec.klog --estimator vo --traj-out " + dir + "/replayed.txt");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_GT(tools::load_trajectory(dir + "/replayed.txt", &warnings).size(), rgb_a.size() * 8 / 10);

  mavlink::MavlinkDecoder d;
  std::map<uint32_t, int> n;
  d.feed(link.data(), link.size(), [&](const mavlink::MavlinkFrame& f) { ++n[f.msgid]; });
  EXPECT_GE(n[mavlink::kMsgIdHeartbeat], 5) << "1 Hz over 7.5 s";
  EXPECT_GE(n[mavlink::kMsgIdOdometry], 50);
}

TEST(RunRecord, BadLogSensorConfigsAreNamed) {
  const std::string dir = temp_dir("run_record_bad");
  std::ofstream(dir + "/a.yaml")
      << "rig: {camera: {width_px: 160, height_px: 120, fx_px: 100, fy_px: 100, cx_px: 80, "
         "cy_px: 60}}\ndrivers:\n  camera: {type: log}\n  imu: {type: none}\n";
  CmdResult r = run_kestrel("run --config " + dir + "/a.yaml --duration 1");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("camera.type and imu.type must both be log"), std::string::npos) << r.out;
  std::ofstream(dir + "/b.yaml")
      << "rig: {camera: {width_px: 160, height_px: 120, fx_px: 100, fy_px: 100, cx_px: 80, "
         "cy_px: 60}}\ndrivers:\n  camera: {type: log}\n  imu: {type: log}\n  log: {path: "
         "nope.klog}\n";
  r = run_kestrel("run --config " + dir + "/b.yaml --duration 1 --record " + dir + "/x.klog");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("nope.klog"), std::string::npos) << r.out;
  EXPECT_EQ(
      run_kestrel("run --config " + dir + "/b.yaml --record " + dir + "/x.klog --record-buffer-s 0").code, 2);
}

std::string file_bytes(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
}

// Issue 45's contract: a live config whose sensors are a log at lockstep pace
// (no rig: the log's) runs through replay's pipeline, so `kestrel run` writes
// the very bytes `kestrel replay --pace lockstep` writes.
TEST(RunRecord, LockstepLogRunWritesTheReplaysTrajectoryByteForByte) {
  const std::string dir = temp_dir("run_lockstep");
  const std::string src = dir + "/src.klog";
  CmdResult r =
      run_kestrel("sim --scenario figure8 --duration 5 --seed 6 --width 160 --height 120 --out " + src);
  ASSERT_EQ(r.code, 0) << r.out;
  std::ofstream(dir + "/live.yaml")
      << "drivers: {camera: {type: log}, imu: {type: log}, log: {path: src.klog, pace: "
         "lockstep}}\nestimator: {backend: window}\n";
  r = run_kestrel("run --config " + dir + "/live.yaml --traj-out " + dir + "/run.txt");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("through the replay pipeline"), std::string::npos) << r.out;
  r = run_kestrel("replay " + src + " --pace lockstep --traj-out " + dir + "/replay.txt");
  ASSERT_EQ(r.code, 0) << r.out;
  const std::string a = file_bytes(dir + "/run.txt"), b = file_bytes(dir + "/replay.txt");
  EXPECT_GT(a.size(), 1000u);
  EXPECT_TRUE(a == b) << "run and replay trajectories differ";

  // A pace it does not know, and options a log at lockstep pace cannot honour, are named.
  std::ofstream(dir + "/bad.yaml")
      << "drivers: {camera: {type: log}, imu: {type: log}, log: {path: src.klog, pace: "
         "slow}}\n";
  r = run_kestrel("run --config " + dir + "/bad.yaml");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("drivers.log.pace"), std::string::npos) << r.out;
  r = run_kestrel("run --config " + dir + "/live.yaml --record " + dir + "/x.klog");
  EXPECT_EQ(r.code, 2) << r.out;
  EXPECT_NE(r.out.find("already a recording"), std::string::npos) << r.out;
  // Live sensors still need a rig.
  std::ofstream(dir + "/norig.yaml")
      << "drivers: {camera: {type: v4l2, v4l2: {color_device: /dev/video0}}, imu: {type: none}}\n";
  r = run_kestrel("run --config " + dir + "/norig.yaml");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("rig: missing"), std::string::npos) << r.out;
}

// Live stereo through the live sensor threads: a stereo log played by the
// `log` camera at its own pace delivers each right image with its frame, so
// the stereo tracker gets every pair (docs/stereo.md, "Live stereo").
TEST(RunRecord, ALiveStereoRigGetsEveryRightImage) {
  const std::string dir = temp_dir("run_stereo");
  const std::string src = dir + "/src.klog";
  CmdResult r = run_kestrel(
      "sim --scenario figure8 --duration 4 --seed 5 --width 160 --height 120 --stereo --out " + src);
  ASSERT_EQ(r.code, 0) << r.out;
  const Rig rig = drivers::KlogReader(src).rig();
  ASSERT_TRUE(rig.stereo.present);
  std::ofstream(dir + "/rig.yaml") << drivers::rig_to_yaml(rig);
  std::ofstream(dir + "/live.yaml") << "rig: rig.yaml\n"
                                       "drivers:\n"
                                       "  camera: {type: log, width_px: 160, height_px: 120, rate_hz: 30}\n"
                                       "  imu: {type: log}\n"
                                       "  log: {path: src.klog}\n"
                                       "estimator:\n"
                                       "  backend: window\n";
  r = run_kestrel("run --config " + dir + "/live.yaml --duration 5 --traj-out " + dir +
                  "/traj.txt --record " + dir + "/rec.klog");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("stereo: rectified at start-up"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("frames without a right image 0 "), std::string::npos) << r.out;
  size_t lines = 0;
  std::ifstream t(dir + "/traj.txt");
  for (std::string l; std::getline(t, l);) lines += !l.empty() && l[0] != '#';
  EXPECT_GT(lines, 90u) << r.out;
  // The recording keeps the right images beside the left ones.
  size_t left = 0, right = 0;
  for (const drivers::LogRecord& rec : read_all(dir + "/rec.klog")) {
    left += rec.type == drivers::RecordType::kRgb;
    right += rec.type == drivers::RecordType::kRight;
  }
  EXPECT_GT(left, 90u);
  EXPECT_EQ(right, left);
}

// Options that depend on the backend are refused before the replay runs.
TEST(RunRecord, AMapOutputForABackendWithoutAMapIsRefusedBeforeTheReplay) {
  const std::string dir = temp_dir("replay_map_check");
  const std::string src = dir + "/src.klog";
  CmdResult r =
      run_kestrel("sim --scenario hover --duration 3 --seed 2 --width 160 --height 120 --out " + src);
  ASSERT_EQ(r.code, 0) << r.out;
  r = run_kestrel("replay " + src + " --estimator rgbd --map-traj-out " + dir + "/m.txt --traj-out " + dir +
                  "/t.txt");
  EXPECT_EQ(r.code, 2) << r.out;
  EXPECT_NE(r.out.find("--map-traj-out: the backend 'rgbd' runs without a map"), std::string::npos) << r.out;
  EXPECT_EQ(r.out.find("poses out:"), std::string::npos) << "the replay ran: " << r.out;
  EXPECT_FALSE(std::ifstream(dir + "/t.txt").good()) << "the replay ran and wrote its trajectory";
}

}  // namespace
}  // namespace kestrel::test

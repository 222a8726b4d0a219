// rosbag2 / MCAP against independent implementations from npm (@mcap/core,
// @foxglove/rosmsg2-serialization; install_node_mcap.sh puts them in the build
// tree, and without node or npm these tests are SKIPPED, loudly), and the
// command-line contracts: `kestrel convert LOG --to rosbag2`, `kestrel replay
// DIR`, `kestrel replay LOG --mcap-out FILE`.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <sstream>

#include "../datasets/dataset_fixtures.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/mcap.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/ros2_msgs.hpp"
#include "kestrel/drivers/rosbag2.hpp"
#include "run_command.hpp"

namespace kestrel::test {
namespace {

namespace fs = std::filesystem;
using drivers::RecordType;
using nlohmann::json;

std::string dir() {
  static const std::string d = temp_dir("rosbag2_npm");
  return d;
}

// "" when the npm packages are usable, else why not.
std::string node_ready() {
  static const std::string why = [] {
    const std::string cache = std::string(KESTREL_BUILD_DIR) + "/npm-cache-mcap";
    const CmdResult r =
        run_command("sh " + std::string(KESTREL_SOURCE_DIR) + "/tests/rosbag2/install_node_mcap.sh " + cache);
    return r.code == 0 ? std::string() : (r.out.empty() ? std::string("install failed") : r.out);
  }();
  return why;
}

#define REQUIRE_NODE()                                                                         \
  do {                                                                                         \
    const std::string why_ = node_ready();                                                     \
    if (!why_.empty()) {                                                                       \
      std::fprintf(stderr, "SKIPPED: @mcap/core unavailable, independent check NOT run: %s\n", \
                   why_.c_str());                                                              \
      GTEST_SKIP() << "@mcap/core unavailable, independent check NOT run: " << why_;           \
    }                                                                                          \
  } while (0)

CmdResult node(const std::string& args) {
  return run_command("NODE_PATH=" + std::string(KESTREL_BUILD_DIR) + "/npm-cache-mcap/node_modules node " +
                     std::string(KESTREL_SOURCE_DIR) + "/tests/rosbag2/mcap_check.js " + args);
}

json node_read(const std::string& file) {
  const CmdResult r = run_command("NODE_PATH=" + std::string(KESTREL_BUILD_DIR) +
                                  "/npm-cache-mcap/node_modules node " + std::string(KESTREL_SOURCE_DIR) +
                                  "/tests/rosbag2/mcap_check.js read " + file + " 2>/dev/null");
  EXPECT_EQ(r.code, 0) << node("read " + file).out;
  return json::parse(r.out);
}

uint64_t byte_sum(const std::vector<uint8_t>& v) {
  uint64_t s = 0;
  for (uint8_t b : v) s = (s + b) % 4294967296ull;
  return s;
}

TEST(Rosbag2Npm, McapCoreAndTheSerializerDecodeEverythingWeWrite) {
  REQUIRE_NODE();
  const std::string klog = dir() + "/small.klog";
  write_small_klog(klog);
  for (const auto& [comp, chunk] :
       std::vector<std::pair<std::string, size_t>>{{"zstd", 4096}, {"lz4", 4096}, {"", 0}}) {
    SCOPED_TRACE("compression '" + comp + "' chunk " + std::to_string(chunk));
    const std::string out = dir() + "/bag_" + (comp.empty() ? "none" : comp);
    drivers::KlogReader src(klog);
    drivers::Rosbag2WriteOptions wo;
    wo.mcap.compression = comp;
    wo.mcap.chunk_size_bytes = chunk;
    drivers::export_rosbag2(src, out, wo);
    const json j = node_read(out + "/" + fs::path(out).filename().string() + "_0.mcap");
    // 200 IMU + 10 colour + 10 CameraInfo + 10 depth + 50 ground truth + 1 tf_static.
    const int total = 200 + 10 + 10 + 10 + 50 + 1;
    EXPECT_EQ(j["stream"]["done"], true);
    EXPECT_EQ(j["stream"]["counts"]["Message"], total);
    EXPECT_EQ(j["stream"]["counts"]["DataEnd"], 1);
    EXPECT_EQ(j["stream"]["counts"]["Footer"], 1);
    EXPECT_EQ(j["indexed"]["profile"], "ros2");
    EXPECT_EQ(j["indexed"]["statistics"]["messageCount"], std::to_string(total));
    EXPECT_EQ(j["indexed"]["chunkIndexes"].get<int>() > 0, chunk > 0);
    EXPECT_EQ(j["indexed"]["metadata"], json::array({"kestrel"}));
    EXPECT_EQ(j["indexed"]["ordered"], true);
    for (const auto& s : j["indexed"]["schemas"]) EXPECT_EQ(s["encoding"], "ros2msg");
    for (const auto& c : j["indexed"]["channels"]) EXPECT_EQ(c["messageEncoding"], "cdr");
    const json& t = j.at("topics");
    ASSERT_TRUE(t.is_object() && t.contains("/camera/imu")) << j.dump().substr(0, 2000);
    EXPECT_EQ(j["indexed"]["messagesVia"], chunk > 0 ? "indexes" : "stream");
    EXPECT_EQ(t["/camera/imu"]["count"], 200);
    EXPECT_EQ(t["/camera/imu"]["type"], "sensor_msgs/msg/Imu");
    EXPECT_EQ(t["/camera/color/image_raw"]["count"], 10);
    EXPECT_EQ(t["/camera/aligned_depth_to_color/image_raw"]["count"], 10);
    EXPECT_EQ(t["/camera/color/camera_info"]["count"], 10);
    EXPECT_EQ(t["/kestrel/ground_truth"]["count"], 50);
    EXPECT_EQ(t["/tf_static"]["count"], 1);
    for (const auto& [name, topic] : t.items()) {
      EXPECT_EQ(topic["trailing"], 0) << name << ": bytes after the message's end";
      EXPECT_EQ(topic["reencodedDiffers"], 0)
          << name << ": the serializer encodes the same message differently";
    }
    // Field values, as decoded by @foxglove/rosmsg2-serialization.
    const ImuSample s0 = imu_at(0);
    const json& imu = t["/camera/imu"]["first"];
    EXPECT_EQ(imu["header"]["stamp"]["sec"].get<int64_t>() * 1000000000 +
                  imu["header"]["stamp"]["nanosec"].get<int64_t>(),
              s0.t_ns);
    EXPECT_EQ(imu["angular_velocity"]["x"].get<double>(), s0.gyro_rps[0]);
    EXPECT_EQ(imu["angular_velocity"]["z"].get<double>(), s0.gyro_rps[2]);
    EXPECT_EQ(imu["linear_acceleration"]["y"].get<double>(), s0.acc_mps2[1]);
    EXPECT_EQ(imu["orientation_covariance"][0].get<double>(), -1.0);
    const drivers::LogImage rgb0 = image_at(s0.t_ns, 0, PixelFormat::kRgb8);
    const json& img = t["/camera/color/image_raw"]["first"];
    EXPECT_EQ(img["width"], 8);
    EXPECT_EQ(img["height"], 6);
    EXPECT_EQ(img["encoding"], "rgb8");
    EXPECT_EQ(img["step"], 24);
    EXPECT_EQ(img["data"]["length"], rgb0.pixels.size());
    EXPECT_EQ(img["data"]["sum"].get<uint64_t>(), byte_sum(rgb0.pixels));
    const drivers::LogImage d9 = image_at(imu_at(180).t_ns, 9, PixelFormat::kDepthU16);
    const json& dep = t["/camera/aligned_depth_to_color/image_raw"]["last"];
    EXPECT_EQ(dep["encoding"], "16UC1");
    EXPECT_EQ(dep["data"]["sum"].get<uint64_t>(), byte_sum(d9.pixels));
    const json& ci = t["/camera/color/camera_info"]["first"];
    EXPECT_EQ(ci["k"][0].get<double>(), small_rig().rgb.fx);
    EXPECT_EQ(ci["k"][5].get<double>(), small_rig().rgb.cy);
    const json& tf = t["/tf_static"]["first"]["transforms"][1];
    EXPECT_EQ(tf["child_frame_id"], "camera_color_optical_frame");
    EXPECT_EQ(tf["transform"]["translation"]["x"].get<double>(), small_rig().T_BC[3]);
    const GroundTruthPose g = gt_at(imu_at(196).t_ns, 49);
    const json& gt = t["/kestrel/ground_truth"]["last"]["pose"];
    EXPECT_EQ(gt["position"]["x"].get<double>(), g.p_WB[0]);
    EXPECT_EQ(gt["orientation"]["w"].get<double>(), g.q_WB[0]);
    EXPECT_EQ(gt["orientation"]["z"].get<double>(), g.q_WB[3]);
  }
}

TEST(Rosbag2Npm, WeReadWhatMcapCoreWrites) {
  REQUIRE_NODE();
  for (const std::string mode : {"lz4", "none", "unchunked"}) {
    SCOPED_TRACE(mode);
    const std::string f = dir() + "/node_" + mode + ".mcap";
    const CmdResult w = node("write " + f + " " + mode);
    ASSERT_EQ(w.code, 0) << w.out;
    auto log = drivers::open_log(f);
    EXPECT_EQ(log->format_name(), "rosbag2");
    const Rig& rig = log->rig();
    EXPECT_EQ(rig.rgb.fx, 610.5);
    EXPECT_EQ(rig.rgb.cy, 1.5);
    EXPECT_EQ(rig.rgb.width, 4);
    const auto recs = read_all(*log);
    const auto imu = of_type(recs, RecordType::kImu), rgb = of_type(recs, RecordType::kRgb),
               dep = of_type(recs, RecordType::kDepth);
    ASSERT_EQ(imu.size(), 40u) << problems_text(*log);
    ASSERT_EQ(rgb.size(), 4u);
    ASSERT_EQ(dep.size(), 4u);
    const int64_t t0 = 1'700'000'000'000'000'000;
    for (size_t i = 0; i < imu.size(); ++i) {
      EXPECT_EQ(imu[i].imu.t_ns, t0 + static_cast<int64_t>(i) * 5'000'000);
      EXPECT_EQ(imu[i].imu.gyro_rps[0], 0.001 * static_cast<double>(i));
      EXPECT_EQ(imu[i].imu.gyro_rps[1], -0.5);
      EXPECT_EQ(imu[i].imu.acc_mps2[0], 0.125);
      EXPECT_EQ(imu[i].imu.acc_mps2[2], 9.81);
    }
    for (size_t k = 0; k < 4; ++k) {
      EXPECT_EQ(rgb[k].image.t_ns, t0 + static_cast<int64_t>(k) * 50'000'000);
      EXPECT_EQ(rgb[k].image.format, PixelFormat::kRgb8);
      ASSERT_EQ(rgb[k].image.pixels.size(), 36u);
      for (size_t j = 0; j < 36; ++j) EXPECT_EQ(rgb[k].image.pixels[j], (j * 7 + k) & 0xff);
      EXPECT_EQ(dep[k].image.t_ns, rgb[k].image.t_ns);  // the depth 1 ms later is paired with it
      for (size_t j = 0; j < 12; ++j) {
        uint16_t v;
        std::memcpy(&v, dep[k].image.pixels.data() + 2 * j, 2);
        EXPECT_EQ(v, 1000 + 10 * j + k);
      }
    }
  }
}

// A D4xx infrared pair as realsense-ros records it (no /tf_static): the right
// topic named, the right camera from its CameraInfo, placed by P's baseline;
// each right image paired with its left one (0.5 ms apart) on the left's stamp.
TEST(Rosbag2Npm, AnInfraredPairFromMcapCoreIsAStereoLog) {
  REQUIRE_NODE();
  const std::string f = dir() + "/node_stereo.mcap";
  const CmdResult w = node("write-stereo " + f);
  ASSERT_EQ(w.code, 0) << w.out;
  drivers::LogOpenOptions o;
  o.rgb_topic = "/cam/infra1/image_rect_raw";
  o.right_topic = "/cam/infra2/image_rect_raw";
  auto log = drivers::open_log(f, o);
  const Rig& rig = log->rig();
  ASSERT_TRUE(rig.stereo.present) << problems_text(*log);
  EXPECT_EQ(rig.stereo.intrinsics.fx, 382.5);
  EXPECT_NEAR(rig.stereo.T_BC1[3] - rig.T_BC[3], 0.05, 1e-12);  // T_BC = identity here: +x by the baseline
  EXPECT_NE(problems_text(*log).find("placed by its CameraInfo's baseline"), std::string::npos)
      << problems_text(*log);
  const auto recs = read_all(*log);
  const auto left = of_type(recs, RecordType::kRgb), right = of_type(recs, RecordType::kRight);
  ASSERT_EQ(left.size(), 4u) << problems_text(*log);
  ASSERT_EQ(right.size(), 4u) << problems_text(*log);
  for (size_t k = 0; k < 4; ++k) {
    EXPECT_EQ(right[k].image.t_ns, left[k].image.t_ns);
    EXPECT_EQ(right[k].image.format, PixelFormat::kGray8);
    ASSERT_EQ(right[k].image.pixels.size(), 12u);
    for (size_t j = 0; j < 12; ++j) EXPECT_EQ(right[k].image.pixels[j], (100 + j * 5 + k) & 0xff);
  }
  // Without --right-topic the same bag is a monocular log: nothing is taken for a right image by guess.
  auto mono = drivers::open_log(f, drivers::LogOpenOptions{});
  EXPECT_FALSE(mono->rig().stereo.present);
}

// A stereo log through rosbag2 and back: its right images and their
// CameraInfo go out on their own topics, come back as right records, and the
// lockstep trajectory is the .klog's to the last digit.
TEST(Rosbag2Cli, AStereoLogRoundTripsThroughRosbag2) {
  const std::string klog = dir() + "/st.klog", bag = dir() + "/st_ros2";
  CmdResult r = run_kestrel(
      "sim --scenario figure8 --duration 3 --seed 5 --width 320 --height 240 --stereo --out " + klog);
  ASSERT_EQ(r.code, 0) << r.out;
  r = run_kestrel("convert " + klog + " --to rosbag2 --out " + bag);
  ASSERT_EQ(r.code, 0) << r.out;
  const std::string ta = dir() + "/st_a.txt", tb = dir() + "/st_b.txt";
  r = run_kestrel("replay " + klog + " --traj-out " + ta);
  ASSERT_EQ(r.code, 0) << r.out;
  r = run_kestrel("replay " + bag + " --traj-out " + tb);
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("frames without a right image 0 "), std::string::npos) << r.out;
  std::ifstream fa(ta), fb(tb);
  const std::string a((std::istreambuf_iterator<char>(fa)), {}), b((std::istreambuf_iterator<char>(fb)), {});
  EXPECT_GT(a.size(), 1000u);
  EXPECT_EQ(a, b) << "the rosbag2 round trip changed the stereo trajectory";
  if (!node_ready().empty()) {
    std::fprintf(stderr, "SKIPPED: @mcap/core unavailable, the right topics NOT checked independently: %s\n",
                 node_ready().c_str());
    GTEST_SKIP() << "@mcap/core unavailable: " << node_ready();
  }
  const json j = node_read(bag + "/st_ros2_0.mcap");
  for (const char* topic : {"/camera/right/image_raw", "/camera/right/camera_info"}) {
    SCOPED_TRACE(topic);
    const json& t = j["topics"][topic];
    ASSERT_TRUE(t.is_object()) << j.dump();
    EXPECT_GT(t["count"].get<int>(), 80);
    EXPECT_EQ(t["trailing"], 0);
    EXPECT_EQ(t["reencodedDiffers"], 0);
  }
}

// The map's messages with known values, decoded by the serializer from our schema text.
TEST(Rosbag2Npm, PointCloud2AndMarkerArrayDecodeWithTheirValues) {
  REQUIRE_NODE();
  const std::string f = dir() + "/map_msgs.mcap";
  {
    drivers::mcap::Writer w;
    w.open(f, {});
    const char* pc = "sensor_msgs/msg/PointCloud2";
    const char* ma = "visualization_msgs/msg/MarkerArray";
    const uint16_t cpc =
        w.add_channel(w.add_schema(pc, "ros2msg", drivers::ros2::schema_text(pc)), "/pts", "cdr");
    const uint16_t cma =
        w.add_channel(w.add_schema(ma, "ros2msg", drivers::ros2::schema_text(ma)), "/mk", "cdr");
    std::vector<float> xyz;
    for (int i = 0; i < 1000; ++i) xyz.insert(xyz.end(), {0.5f * i, -1.25f, 3.0f + 0.001f * i});
    drivers::ros2::PointCloudXyz cloud;
    cloud.t_ns = 1'500'000'000;
    cloud.frame_id = "map";
    cloud.xyz = xyz.data();
    cloud.n = 1000;
    std::vector<uint8_t> buf;
    drivers::ros2::encode(cloud, buf);
    w.write(cpc, 1, 1, buf.data(), buf.size());
    std::vector<drivers::ros2::Marker> m(2);
    m[0].frame_id = m[1].frame_id = "map";
    m[0].ns = "keyframes";
    m[0].id = 7;
    m[0].pose.position = {1, 2, 3};
    m[0].scale = {0.15, 0.02, 0.02};
    m[0].color_rgba = {0.25f, 0.5f, 1.0f, 1.0f};
    m[1].ns = "loop_edges";
    m[1].id = 0;
    m[1].type = drivers::ros2::Marker::kLineList;
    m[1].points = {{0, 0, 0}, {4, 5, 6}, {1, 1, 1}, {2, 2, 2}};
    drivers::ros2::encode(m, buf);
    w.write(cma, 2, 2, buf.data(), buf.size());
    // The dense surface's layout: x y z and the colour packed in a fourth float.
    const uint16_t crgb =
        w.add_channel(w.add_schema(pc, "ros2msg", drivers::ros2::schema_text(pc)), "/rgb", "cdr");
    std::vector<uint8_t> rgb;
    for (int i = 0; i < 1000; ++i)
      rgb.insert(rgb.end(), {static_cast<uint8_t>(i), 200, static_cast<uint8_t>(255 - (i % 256))});
    cloud.rgb = rgb.data();
    drivers::ros2::encode(cloud, buf);
    w.write(crgb, 3, 3, buf.data(), buf.size());
    w.close();
  }
  {
    const json j = node_read(f);
    const json& c = j["topics"]["/rgb"];
    EXPECT_EQ(c["trailing"], 0);
    EXPECT_EQ(c["reencodedDiffers"], 0);
    EXPECT_EQ(c["sizeMismatches"], 0);
    EXPECT_EQ(c["last"]["point_step"], 16);
    ASSERT_EQ(c["lastPoints"].size(), 4u);
    EXPECT_EQ(c["lastPoints"][3][0].get<double>(), 1.5);
    EXPECT_EQ(c["lastPoints"][3][2].get<double>(), static_cast<double>(3.0f + 0.003f));
    ASSERT_EQ(c["lastColours"].size(), 4u) << c.dump();
    EXPECT_EQ(c["lastColours"][3], json::array({3, 200, 252}));
    EXPECT_FALSE(j["topics"]["/pts"].contains("lastColours")) << "a cloud without colour grew a field";
  }
  const json j = node_read(f);
  const json& p = j["topics"]["/pts"];
  EXPECT_EQ(p["type"], "sensor_msgs/msg/PointCloud2");
  EXPECT_EQ(p["trailing"], 0);
  EXPECT_EQ(p["reencodedDiffers"], 0);
  EXPECT_EQ(p["sizeMismatches"], 0);
  EXPECT_EQ(p["last"]["width"], 1000);
  EXPECT_EQ(p["last"]["height"], 1);
  EXPECT_EQ(p["last"]["header"]["frame_id"], "map");
  EXPECT_EQ(p["last"]["header"]["stamp"]["sec"], 1);
  EXPECT_EQ(p["last"]["header"]["stamp"]["nanosec"], 500000000);
  ASSERT_EQ(p["lastPoints"].size(), 4u);
  EXPECT_EQ(p["lastPoints"][3][0].get<double>(), 1.5);
  EXPECT_EQ(p["lastPoints"][3][1].get<double>(), -1.25);
  EXPECT_EQ(p["lastPoints"][3][2].get<double>(), static_cast<double>(3.0f + 0.003f));
  const json& k = j["topics"]["/mk"];
  EXPECT_EQ(k["type"], "visualization_msgs/msg/MarkerArray");
  EXPECT_EQ(k["trailing"], 0);
  EXPECT_EQ(k["reencodedDiffers"], 0);
  ASSERT_EQ(k["markers"].size(), 2u) << k.dump();
  EXPECT_EQ(k["markers"][0]["ns"], "keyframes");
  EXPECT_EQ(k["markers"][0]["id"], 7);
  EXPECT_EQ(k["markers"][0]["type"], 0);
  EXPECT_EQ(k["markers"][0]["pose"]["position"]["y"], 2.0);
  EXPECT_EQ(k["markers"][0]["scale"]["x"], 0.15);
  EXPECT_EQ(k["markers"][0]["color"]["r"], 0.25);
  EXPECT_EQ(k["markers"][1]["type"], 5);
  EXPECT_EQ(k["markers"][1]["points"], 4);
}

// The contracts through the command line: convert, replay of the folder, --mcap-out.
TEST(Rosbag2Cli, ConvertReplayAndOdometryOut) {
  const std::string klog = dir() + "/fig8.klog", bag = dir() + "/fig8_ros2";
  CmdResult r = run_kestrel("sim --scenario figure8 --duration 4 --width 320 --height 240 --out " + klog);
  ASSERT_EQ(r.code, 0) << r.out;
  r = run_kestrel("convert " + klog + " --to rosbag2 --out " + bag);
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_TRUE(fs::exists(bag + "/metadata.yaml"));
  EXPECT_TRUE(fs::exists(bag + "/fig8_ros2_0.mcap"));
  const std::string ta = dir() + "/a.txt", tb = dir() + "/b.txt", odom = dir() + "/odom.mcap";
  r = run_kestrel("replay " + klog + " --quiet --traj-out " + ta + " --mcap-out " + odom);
  ASSERT_EQ(r.code, 0) << r.out;
  r = run_kestrel("replay " + bag + " --quiet --traj-out " + tb);
  ASSERT_EQ(r.code, 0) << r.out;
  // Lockstep replay of the same records with the same rig: the same trajectory, to the last digit.
  std::ifstream fa(ta), fb(tb);
  const std::string a((std::istreambuf_iterator<char>(fa)), {}), b((std::istreambuf_iterator<char>(fb)), {});
  EXPECT_GT(a.size(), 1000u);
  EXPECT_EQ(a, b) << "the rosbag2 round trip changed the trajectory";

  if (!node_ready().empty()) {
    std::fprintf(stderr, "SKIPPED: @mcap/core unavailable, --mcap-out NOT checked independently: %s\n",
                 node_ready().c_str());
    GTEST_SKIP() << "@mcap/core unavailable: " << node_ready();
  }
  const json j = node_read(odom);
  const json& t = j["topics"]["/kestrel/odometry"];
  EXPECT_EQ(t["type"], "nav_msgs/msg/Odometry");
  EXPECT_EQ(j["indexed"]["schemas"][0]["encoding"], "ros2msg");
  EXPECT_EQ(j["indexed"]["channels"][0]["messageEncoding"], "cdr");
  EXPECT_EQ(t["trailing"], 0);
  EXPECT_EQ(t["reencodedDiffers"], 0);
  // Every trajectory pose is an odometry message, and the last ones (the final frame) agree in value.
  std::istringstream rows(a);
  std::string line, last_row;
  size_t n = 0;
  while (std::getline(rows, line))
    if (!line.empty() && line[0] != '#') last_row = line, ++n;
  double row[8] = {};
  ASSERT_EQ(std::sscanf(last_row.c_str(), "%lf %lf %lf %lf %lf %lf %lf %lf", &row[0], &row[1], &row[2],
                        &row[3], &row[4], &row[5], &row[6], &row[7]),
            8);
  EXPECT_GE(t["count"].get<size_t>(), n);
  const json& last = t["last"];
  const double t_s =
      last["header"]["stamp"]["sec"].get<double>() + last["header"]["stamp"]["nanosec"].get<double>() * 1e-9;
  EXPECT_NEAR(t_s, row[0], 1e-6);
  const json& p = last["pose"]["pose"];
  // TUM rows are printed with fewer digits than the doubles carry.
  EXPECT_NEAR(p["position"]["x"].get<double>(), row[1], 1e-6);
  EXPECT_NEAR(p["position"]["y"].get<double>(), row[2], 1e-6);
  EXPECT_NEAR(p["position"]["z"].get<double>(), row[3], 1e-6);
  EXPECT_NEAR(std::abs(p["orientation"]["w"].get<double>()), std::abs(row[7]), 1e-6);
  EXPECT_EQ(t["first"]["header"]["frame_id"], "odom");
  EXPECT_EQ(t["first"]["child_frame_id"], "base_link");

  // /tf: map -> odom -> base_link with every pose, decoded by @foxglove/rosmsg2-serialization.
  const json& tf = j["topics"]["/tf"];
  EXPECT_EQ(tf["type"], "tf2_msgs/msg/TFMessage");
  EXPECT_EQ(tf["count"], t["count"]);
  EXPECT_EQ(tf["trailing"], 0);
  EXPECT_EQ(tf["reencodedDiffers"], 0);
  const json& tl = tf["last"]["transforms"];
  ASSERT_EQ(tl.size(), 2u) << tf.dump();
  EXPECT_EQ(tl[0]["header"]["frame_id"], "map");
  EXPECT_EQ(tl[0]["child_frame_id"], "odom");
  EXPECT_EQ(tl[1]["header"]["frame_id"], "odom");
  EXPECT_EQ(tl[1]["child_frame_id"], "base_link");
  EXPECT_NEAR(tl[1]["transform"]["translation"]["x"].get<double>(), row[1], 1e-6);
  EXPECT_NEAR(tl[1]["transform"]["translation"]["z"].get<double>(), row[3], 1e-6);
  // /diagnostics: about once a second of the 4 s flight (and on every change), the last one tracking.
  const json& dg = j["topics"]["/diagnostics"];
  EXPECT_EQ(dg["type"], "diagnostic_msgs/msg/DiagnosticArray");
  EXPECT_GE(dg["count"].get<int>(), 4);
  EXPECT_LE(dg["count"].get<int>(), 20);
  EXPECT_EQ(dg["trailing"], 0);
  EXPECT_EQ(dg["reencodedDiffers"], 0);
  const json& st = dg["last"]["status"];
  ASSERT_EQ(st.size(), 1u) << dg.dump();
  EXPECT_EQ(st[0]["level"], 0);
  EXPECT_EQ(st[0]["message"], "tracking");
  EXPECT_EQ(st[0]["values"][0]["key"], "quality");
  EXPECT_EQ(st[0]["values"][1]["key"], "reset_counter");

  // The map: the local map's points at most 1 Hz of log time (ros2.map_points_rate_hz's default) after a
  // keyframe, in the map frame; an arrow per keyframe with ids 0, 1, 2, ...; at the end the map's keyframe
  // path.
  const json& pc = j["topics"]["/kestrel/map_points"];
  EXPECT_EQ(pc["type"], "sensor_msgs/msg/PointCloud2");
  EXPECT_GE(pc["count"].get<int>(), 2) << pc.dump();
  EXPECT_LE(pc["count"].get<int>(), 5);
  EXPECT_EQ(pc["trailing"], 0);
  EXPECT_EQ(pc["reencodedDiffers"], 0);
  EXPECT_EQ(pc["sizeMismatches"], 0);
  EXPECT_EQ(pc["last"]["header"]["frame_id"], "map");
  EXPECT_GT(pc["last"]["width"].get<int>(), 50);
  EXPECT_LE(pc["last"]["width"].get<int>(), 8192);
  for (const json& q : pc["lastPoints"])
    for (int c = 0; c < 3; ++c) EXPECT_LT(std::abs(q[c].get<double>()), 50.0) << q.dump();
  const json& mk = j["topics"]["/kestrel/map_markers"];
  EXPECT_EQ(mk["type"], "visualization_msgs/msg/MarkerArray");
  EXPECT_EQ(mk["trailing"], 0);
  EXPECT_EQ(mk["reencodedDiffers"], 0);
  int arrows = 0;
  bool deleted = false, path = false;
  for (const json& m : mk["markers"]) {
    EXPECT_EQ(m["frame"], "map");
    if (m["ns"] == "keyframes") {
      EXPECT_FALSE(deleted) << "an arrow after the final markers";
      EXPECT_EQ(m["id"], arrows) << "keyframe arrows are numbered in order";
      EXPECT_EQ(m["type"], 0);
      ++arrows;
    } else if (m["action"] == 3) {
      deleted = true;
    } else if (m["ns"] == "keyframe_path") {
      EXPECT_TRUE(deleted);
      EXPECT_EQ(m["type"], 4);
      EXPECT_GE(m["points"].get<int>(), 2);
      path = true;
    }
  }
  EXPECT_GE(arrows, 3);
  EXPECT_TRUE(deleted && path) << mk.dump();
  EXPECT_FALSE(j["topics"].contains("/kestrel/dense_map")) << "a dense cloud without the dense map";
}

// With the dense map on, --mcap-out ends with its surface: one coloured PointCloud2 in odom (W), the very
// points --dense-out writes, in the same order.
TEST(Rosbag2Cli, TheDenseMapsSurfaceEndsTheMcapWithItsColours) {
  REQUIRE_NODE();
  const std::string klog = dir() + "/dense.klog", ply = dir() + "/dense.ply", mcap = dir() + "/dense.mcap";
  CmdResult r = run_kestrel("sim --scenario figure8 --duration 4 --width 320 --height 240 --out " + klog);
  ASSERT_EQ(r.code, 0) << r.out;
  r = run_kestrel("replay " + klog + " --quiet --dense-out " + ply + " --mcap-out " + mcap);
  ASSERT_EQ(r.code, 0) << r.out;
  // The PLY's vertex count and first vertices (binary little-endian: float x y z, uchar r g b).
  std::ifstream in(ply, std::ios::binary);
  std::string line;
  long vertices = -1;
  while (std::getline(in, line) && line != "end_header")
    if (line.rfind("element vertex ", 0) == 0) vertices = std::stol(line.substr(15));
  ASSERT_GT(vertices, 1000) << "the flight's surface is too small to test";
  float first[4][3];
  uint8_t colour[4][3];
  for (int i = 0; i < 4; ++i) {
    in.read(reinterpret_cast<char*>(first[i]), 12);
    in.read(reinterpret_cast<char*>(colour[i]), 3);
  }
  ASSERT_TRUE(in.good());
  const json j = node_read(mcap);
  ASSERT_TRUE(j["topics"].contains("/kestrel/dense_map")) << j["topics"].dump();
  const json& d = j["topics"]["/kestrel/dense_map"];
  EXPECT_EQ(d["type"], "sensor_msgs/msg/PointCloud2");
  EXPECT_EQ(d["count"], 1);
  EXPECT_EQ(d["trailing"], 0);
  EXPECT_EQ(d["reencodedDiffers"], 0);
  EXPECT_EQ(d["sizeMismatches"], 0);
  EXPECT_EQ(d["last"]["header"]["frame_id"], "odom");
  EXPECT_EQ(d["last"]["width"].get<long>(), vertices);
  const json& o = j["topics"]["/kestrel/odometry"]["last"]["header"]["stamp"];
  EXPECT_EQ(d["last"]["header"]["stamp"], o) << "stamped with the last pose";
  for (int i = 0; i < 4; ++i)
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(d["lastPoints"][i][k].get<double>(), static_cast<double>(first[i][k]));
      EXPECT_EQ(d["lastColours"][i][k].get<int>(), colour[i][k]);
    }
}

// --foxglove: @foxglove/ws-protocol's client connects while a realtime replay runs, sees the advertised
// topics (the --mcap-out ones, ros2msg schemas, cdr), subscribes to odometry and decodes 3 messages with
// @foxglove/rosmsg2-serialization from the advertised schema; a message the server does not offer is refused
// with a named status and counted.
TEST(Rosbag2Cli, FoxgloveLiveWithTheNpmClient) {
  REQUIRE_NODE();
  const std::string klog = dir() + "/fox.klog";
  CmdResult r = run_kestrel("sim --scenario figure8 --duration 4 --width 320 --height 240 --out " + klog);
  ASSERT_EQ(r.code, 0) << r.out;
  const int port = 20000 + static_cast<int>(getpid() % 20000);
  const std::string url = "ws://127.0.0.1:" + std::to_string(port);
  const std::string log = dir() + "/fox_kestrel.txt";
  const std::string out = dir() + "/fox_client.json";
  // kestrel in the background, the client in the foreground; then wait for kestrel's summary.
  r = run_command("sh -c '" + built_program("kestrel") + " replay " + klog +
                  " --pace realtime --foxglove 127.0.0.1:" + std::to_string(port) + " --foxglove-wait 30 > " +
                  log + " 2>&1 & NODE_PATH=" + std::string(KESTREL_BUILD_DIR) +
                  "/npm-cache-mcap/node_modules node " + std::string(KESTREL_SOURCE_DIR) +
                  "/tests/rosbag2/foxglove_check.js " + url + " > " + out + "; c=$?; wait; exit $c'");
  std::ifstream lf(log), cf(out);
  const std::string kout((std::istreambuf_iterator<char>(lf)), {}),
      cout((std::istreambuf_iterator<char>(cf)), {});
  ASSERT_EQ(r.code, 0) << r.out << "\nclient:\n" << cout << "\nkestrel:\n" << kout;
  const json j = json::parse(cout);
  EXPECT_EQ(j["subprotocol"], "foxglove.websocket.v1");
  EXPECT_EQ(j["serverInfo"]["name"], "kestrel");
  std::map<std::string, std::string> types;
  for (const json& c : j["channels"]) {
    types[c["topic"]] = c["schemaName"];
    EXPECT_EQ(c["encoding"], "cdr");
    EXPECT_EQ(c["schemaEncoding"], "ros2msg");
  }
  EXPECT_EQ(types["/kestrel/odometry"], "nav_msgs/msg/Odometry");
  EXPECT_EQ(types["/tf"], "tf2_msgs/msg/TFMessage");
  EXPECT_EQ(types["/diagnostics"], "diagnostic_msgs/msg/DiagnosticArray");
  EXPECT_EQ(types["/kestrel/map_points"], "sensor_msgs/msg/PointCloud2");
  EXPECT_EQ(types["/kestrel/map_markers"], "visualization_msgs/msg/MarkerArray");
  EXPECT_EQ(types["/kestrel/dense_map"], "sensor_msgs/msg/PointCloud2");
  ASSERT_EQ(j["messages"].size(), 3u);
  int64_t last_ns = -1;
  for (const json& m : j["messages"]) {
    EXPECT_EQ(m["trailing"], false);
    EXPECT_EQ(m["frame_id"], "odom");
    EXPECT_EQ(m["child_frame_id"], "base_link");
    const int64_t t_ns = m["stamp"]["sec"].get<int64_t>() * 1000000000 + m["stamp"]["nanosec"].get<int64_t>();
    EXPECT_EQ(std::to_string(t_ns), m["timestamp"].get<std::string>()) << "the frame's time is the stamp";
    EXPECT_GT(t_ns, last_ns);
    last_ns = t_ns;
  }
  ASSERT_GE(j["statuses"].size(), 1u);
  EXPECT_EQ(j["statuses"][0]["level"], 2);
  EXPECT_NE(j["statuses"][0]["message"].get<std::string>().find("clientPublish"), std::string::npos);
  EXPECT_NE(kout.find("foxglove: 1 client(s)"), std::string::npos) << kout;
  EXPECT_NE(kout.find("1 bad message(s)"), std::string::npos) << kout;
}

// `kestrel run` (live sensor threads playing a log): --mcap-out and --foxglove side by side, and the config's
// ros2: section (map_points_rate_hz: 0 writes no point clouds; a rate out of range is refused by name).
TEST(Rosbag2Cli, RunWithMcapOutFoxgloveAndTheRos2Section) {
  REQUIRE_NODE();
  const std::string d = dir() + "/run";
  fs::create_directories(d);
  CmdResult r =
      run_kestrel("sim --scenario figure8 --duration 4 --width 160 --height 120 --out " + d + "/src.klog");
  ASSERT_EQ(r.code, 0) << r.out;
  const std::string sensors =
      "drivers:\n"
      "  camera: {type: log, width_px: 160, height_px: 120, rate_hz: 30}\n"
      "  imu: {type: log}\n"
      "  log: {path: src.klog}\n"
      "estimator:\n"
      "  backend: window\n";
  std::ofstream(d + "/bad.yaml") << sensors << "ros2:\n  map_points_rate_hz: 99\n";
  r = run_kestrel("run --config " + d + "/bad.yaml --duration 1 --mcap-out " + d + "/x.mcap");
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.out.find("ros2.map_points_rate_hz: expected a number in [0, 30]"), std::string::npos) << r.out;

  std::ofstream(d + "/live.yaml") << sensors << "ros2:\n  map_points_rate_hz: 0\n";
  const std::string mcap = d + "/run.mcap";
  r = run_kestrel("run --config " + d + "/live.yaml --duration 3.5 --mcap-out " + mcap +
                  " --foxglove 127.0.0.1:0");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("foxglove: ws://127.0.0.1:"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("foxglove: 0 client(s), 0 messages sent"), std::string::npos) << r.out;
  const json j = node_read(mcap);
  EXPECT_GT(j["topics"]["/kestrel/odometry"]["count"].get<int>(), 30);
  EXPECT_FALSE(j["topics"].contains("/kestrel/map_points")) << "map_points_rate_hz: 0 wrote point clouds";
  ASSERT_TRUE(j["topics"].contains("/kestrel/map_markers"));
  EXPECT_GE(j["topics"]["/kestrel/map_markers"]["count"].get<int>(), 2);
  EXPECT_EQ(j["topics"]["/kestrel/map_markers"]["trailing"], 0);
}

}  // namespace
}  // namespace kestrel::test

// The TUM-VI reader on folders the test writes: the layout, the Kalibr chain
// with the equidistant model, 16-bit images, mocap ground truth, and each kind
// of bad input (missing right image, mismatched stamps, missing or malformed
// calibration) named and survived.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>

#include "dataset_fixtures.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/open_log.hpp"

namespace kestrel::test {
namespace {

namespace fs = std::filesystem;

constexpr int kW = 64, kH = 48, kFrames = 5;
constexpr int64_t kCamDt = 50'000'000;  // 20 Hz
constexpr int64_t kImuDt = 5'000'000;   // 200 Hz

// Left camera 4 cm ahead of the IMU, looking along its x; right camera 10 cm to its right.
const char* kChain = R"(cam0:
  T_cam_imu:
  - [0.0, -1.0, 0.0, 0.01]
  - [0.0, 0.0, -1.0, 0.02]
  - [1.0, 0.0, 0.0, -0.04]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: pinhole
  distortion_coeffs: [0.0034, 0.0007, -0.0020, 0.0002]
  distortion_model: equidistant
  intrinsics: [24.0, 24.5, 31.5, 23.5]
  resolution: [64, 48]
  rostopic: /cam0/image_raw
cam1:
  T_cam_imu:
  - [0.0, -1.0, 0.0, -0.09]
  - [0.0, 0.0, -1.0, 0.02]
  - [1.0, 0.0, 0.0, -0.04]
  - [0.0, 0.0, 0.0, 1.0]
  T_cn_cnm1:
  - [1.0, 0.0, 0.0, -0.1]
  - [0.0, 1.0, 0.0, 0.0]
  - [0.0, 0.0, 1.0, 0.0]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: pinhole
  distortion_coeffs: [0.0035, 0.0006, -0.0021, 0.0003]
  distortion_model: equidistant
  intrinsics: [24.1, 24.4, 31.0, 23.0]
  resolution: [64, 48]
  rostopic: /cam1/image_raw
)";

const char* kImuConfig = R"(accelerometer_noise_density: 0.0028
accelerometer_random_walk: 0.00086
gyroscope_noise_density: 0.00016
gyroscope_random_walk: 0.000022
rostopic: /imu0
update_rate: 200.0
)";

constexpr int64_t kT0 = 1'520'530'308'199'447'626;  // as TUM-VI's stamps: ns since the epoch

// Pixel (u, v) of image i: a 16-bit ramp whose top byte is known.
uint16_t pixel16(int i, int u, int v) {
  return static_cast<uint16_t>(((u * 3 + v * 5 + i * 7) % 256) * 256 + 77);
}

void write_image(const std::string& path, int i) {
  cv::Mat m(kH, kW, CV_16UC1);
  for (int v = 0; v < kH; ++v)
    for (int u = 0; u < kW; ++u) m.at<uint16_t>(v, u) = pixel16(i, u, v);
  ASSERT_TRUE(cv::imwrite(path, m)) << path;
}

// A complete, consistent folder.
std::string write_folder(const std::string& name) {
  const std::string dir = temp_dir(name) + "/dataset-room9_512_16";
  const std::string m = dir + "/mav0";
  for (const char* d : {"/cam0/data", "/cam1/data", "/imu0", "/mocap0"}) fs::create_directories(m + d);
  fs::create_directories(dir + "/dso");
  write_text(dir + "/dso/camchain.yaml", kChain);
  write_text(dir + "/dso/imu_config.yaml", kImuConfig);
  std::string imu =
      "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y,w_RS_S_z,a_RS_S_x [m s^-2],a_RS_S_y,a_RS_S_z\n";
  for (int i = 0; i < kFrames * 10 + 10; ++i)
    imu += std::to_string(kT0 + i * kImuDt) + ",0.01,-0.02,0.03,0.1,0.2,9.81\n";
  write_text(m + "/imu0/data.csv", imu);
  std::string gt =
      "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z "
      "[]\n";
  for (int i = 0; i < 30; ++i)
    gt += std::to_string(kT0 + i * 8'333'333) + "," + std::to_string(0.01 * i) + ",0.5,1.25,1,0,0,0\n";
  write_text(m + "/mocap0/data.csv", gt);
  std::string c0 = "#timestamp [ns],filename\n", c1 = c0;
  for (int i = 0; i < kFrames; ++i) {
    const int64_t t = kT0 + 20'000'000 + i * kCamDt;
    const std::string f = std::to_string(t) + ".png";
    write_image(m + "/cam0/data/" + f, i);
    write_image(m + "/cam1/data/" + f, i + 100);
    c0 += std::to_string(t) + "," + f + "\n";
    c1 += std::to_string(t) + "," + f + "\n";
  }
  write_text(m + "/cam0/data.csv", c0);
  write_text(m + "/cam1/data.csv", c1);
  return dir;
}

TEST(Tumvi, DetectedAndReadWithTheEquidistantStereoChain) {
  const std::string dir = write_folder("tumvi_ok");
  EXPECT_TRUE(drivers::is_tumvi_folder(dir));
  auto src = drivers::open_log(dir);
  ASSERT_EQ(src->format_name(), "tumvi");
  EXPECT_TRUE(src->problems().empty()) << problems_text(*src);
  const Rig& rig = src->rig();
  EXPECT_EQ(rig.name, "dataset-room9_512_16");
  EXPECT_EQ(rig.rgb.distortion, DistortionModel::kEquidistant);
  EXPECT_DOUBLE_EQ(rig.rgb.fx, 24.0);
  EXPECT_DOUBLE_EQ(rig.rgb.dist[2], -0.0020);
  EXPECT_EQ(rig.rgb.width, kW);
  ASSERT_TRUE(rig.stereo.present);
  EXPECT_EQ(rig.stereo.intrinsics.distortion, DistortionModel::kEquidistant);
  EXPECT_DOUBLE_EQ(rig.stereo.intrinsics.cx, 31.0);
  // T_BC = T_cam_imu^-1: the left camera sits at (0.04, 0.01, 0.02) in the body, the right 0.1 m further
  // along -y.
  EXPECT_NEAR(rig.T_BC[3], 0.04, 1e-12);
  EXPECT_NEAR(rig.T_BC[7], 0.01, 1e-12);
  EXPECT_NEAR(rig.T_BC[11], 0.02, 1e-12);
  EXPECT_NEAR(rig.stereo.T_BC1[7], -0.09, 1e-12);
  EXPECT_DOUBLE_EQ(rig.imu.gyro_noise_density_rad_s_sqrthz, 0.00016);
  EXPECT_DOUBLE_EQ(rig.imu_rate_hz, 200.0);

  const auto all = read_all(*src);
  EXPECT_EQ(of_type(all, drivers::RecordType::kImu).size(), size_t{kFrames * 10 + 10});
  EXPECT_EQ(of_type(all, drivers::RecordType::kGroundTruth).size(), 30u);
  const auto left = of_type(all, drivers::RecordType::kRgb);
  const auto right = of_type(all, drivers::RecordType::kRight);
  ASSERT_EQ(left.size(), size_t{kFrames});
  ASSERT_EQ(right.size(), size_t{kFrames});
  // 16-bit grey arrives as 8-bit grey: the top byte (+77/256 rounds away).
  for (int i = 0; i < kFrames; ++i) {
    const auto& L = left[i].image;
    ASSERT_EQ(L.format, PixelFormat::kGray8);
    ASSERT_EQ(L.width, kW);
    EXPECT_EQ(L.t_ns, kT0 + 20'000'000 + i * kCamDt);
    EXPECT_EQ(right[i].image.t_ns, L.t_ns);
    for (int v : {0, 17, kH - 1})
      for (int u : {0, 33, kW - 1}) {
        EXPECT_EQ(L.pixels[v * kW + u], pixel16(i, u, v) >> 8) << i << " " << u << " " << v;
        EXPECT_EQ(right[i].image.pixels[v * kW + u], pixel16(i + 100, u, v) >> 8);
      }
  }
  const auto gt = of_type(all, drivers::RecordType::kGroundTruth);
  EXPECT_NEAR(gt[3].gt.p_WB[0], 0.03, 1e-12);
  EXPECT_DOUBLE_EQ(gt[3].gt.p_WB[2], 1.25);
  EXPECT_EQ(drivers::parse_log_format("tumvi"), drivers::LogFormat::kTumvi);
  EXPECT_EQ(drivers::open_log(dir, drivers::LogFormat::kTumvi)->format_name(), "tumvi");
}

TEST(Tumvi, EurocFolderIsNotTakenForTumvi) {
  // mav0/ alone (no dso/camchain.yaml, no mocap0/) is EuRoC; mocap0/ alone is TUM-VI.
  const std::string dir = write_folder("tumvi_vs_euroc");
  fs::remove_all(dir + "/dso");
  fs::rename(dir + "/mav0/mocap0", dir + "/mav0/state_groundtruth_estimate0");
  EXPECT_FALSE(drivers::is_tumvi_folder(dir));
  EXPECT_EQ(drivers::open_log(dir)->format_name(), "euroc");
  fs::create_directories(dir + "/mav0/mocap0");
  EXPECT_EQ(drivers::open_log(dir)->format_name(), "tumvi");
}

TEST(Tumvi, MissingRightImageIsNamedAndTheRestReplays) {
  const std::string dir = write_folder("tumvi_noright");
  const std::string f = std::to_string(kT0 + 20'000'000 + 2 * kCamDt) + ".png";
  fs::remove(dir + "/mav0/cam1/data/" + f);
  drivers::TumviReader r(dir);
  EXPECT_TRUE(has_problem(r, "missing-file", "cam1/data.csv:4")) << problems_text(r);
  EXPECT_TRUE(has_problem(r, "missing-right", "cam0/data.csv:4")) << problems_text(r);
  EXPECT_EQ(r.rgb_count(), size_t{kFrames});
  EXPECT_EQ(r.right_count(), size_t{kFrames - 1});
  const auto all = read_all(r);
  EXPECT_EQ(of_type(all, drivers::RecordType::kRgb).size(), size_t{kFrames});
  EXPECT_EQ(of_type(all, drivers::RecordType::kRight).size(), size_t{kFrames - 1});
}

TEST(Tumvi, MismatchedStampIsNamed) {
  const std::string dir = write_folder("tumvi_stamp");
  // The right image of frame 1 stamped 3 ms late (beyond the 1 ms pairing tolerance).
  std::string c1 = "#timestamp [ns],filename\n";
  for (int i = 0; i < kFrames; ++i) {
    const int64_t t = kT0 + 20'000'000 + i * kCamDt;
    c1 += std::to_string(i == 1 ? t + 3'000'000 : t) + "," + std::to_string(t) + ".png\n";
  }
  write_text(dir + "/mav0/cam1/data.csv", c1);
  drivers::TumviReader r(dir);
  EXPECT_TRUE(has_problem(r, "stamp-mismatch", "cam1/data.csv:3")) << problems_text(r);
  EXPECT_TRUE(has_problem(r, "missing-right", "cam0/data.csv:3")) << problems_text(r);
  EXPECT_EQ(r.right_count(), size_t{kFrames});  // kept: the replay counts and drops it (right_unpaired)
}

TEST(Tumvi, MissingCalibrationReplaysWithoutStereo) {
  const std::string dir = write_folder("tumvi_nocalib");
  fs::remove(dir + "/dso/camchain.yaml");
  drivers::TumviReader r(dir);
  EXPECT_TRUE(has_problem(r, "missing-file", "dso/camchain.yaml")) << problems_text(r);
  EXPECT_FALSE(r.rig().stereo.present);
  EXPECT_EQ(r.rgb_count(), size_t{kFrames});
  EXPECT_EQ(r.right_count(), 0u);
  EXPECT_EQ(r.ground_truth_count(), 30u);
}

TEST(Tumvi, MissingImuConfigKeepsTheBmi160Figures) {
  const std::string dir = write_folder("tumvi_noimu");
  // Other figures in the file that is then removed: the defaults must not come from it.
  std::string cfg = kImuConfig;
  cfg.replace(cfg.find("0.00016"), 7, "0.00099");
  write_text(dir + "/dso/imu_config.yaml", cfg);
  EXPECT_DOUBLE_EQ(drivers::TumviReader(dir).rig().imu.gyro_noise_density_rad_s_sqrthz, 0.00099);
  fs::remove(dir + "/dso/imu_config.yaml");
  drivers::TumviReader r(dir);
  EXPECT_TRUE(has_problem(r, "missing-file", "dso/imu_config.yaml")) << problems_text(r);
  EXPECT_TRUE(r.rig().stereo.present);
  EXPECT_DOUBLE_EQ(r.rig().imu.gyro_noise_density_rad_s_sqrthz, 0.00016);
  EXPECT_DOUBLE_EQ(r.rig().imu.acc_random_walk_mps3_sqrthz, 0.00086);
}

TEST(Tumvi, MalformedChainThrowsNamingFileAndField) {
  const std::string dir = write_folder("tumvi_badchain");
  std::string chain = kChain;
  const std::string good = "intrinsics: [24.1, 24.4, 31.0, 23.0]";
  chain.replace(chain.find(good), good.size(), "intrinsics: [24.1, x, 31.0, 23.0]");
  write_text(dir + "/dso/camchain.yaml", chain);
  try {
    drivers::TumviReader r(dir);
    FAIL() << "a malformed chain was accepted";
  } catch (const std::runtime_error& e) {
    const std::string w = e.what();
    EXPECT_NE(w.find("dso/camchain.yaml"), std::string::npos) << w;
    EXPECT_NE(w.find("cam1.intrinsics"), std::string::npos) << w;
  }
}

TEST(Tumvi, NoImuTableThrowsNamingIt) {
  const std::string dir = write_folder("tumvi_noimutable");
  fs::remove(dir + "/mav0/imu0/data.csv");
  try {
    drivers::TumviReader r(dir);
    FAIL();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("imu0/data.csv"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace kestrel::test

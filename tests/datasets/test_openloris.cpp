// OpenLORIS-Scene folders: the OpenCV-YAML calibration, the accelerometer /
// gyroscope merge, the export round trip, malformed input.
#include <gtest/gtest.h>

#include <cstring>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>

#include "dataset_fixtures.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_export.hpp"
#include "kestrel/drivers/open_log.hpp"

namespace kestrel::test {
namespace {

using drivers::RecordType;

// As the dataset ships it: OpenCV YAML with !!opencv-matrix, intrinsics in the order fx cx fy cy.
const char* kSensors = R"(%YAML:1.0
d400_color_optical_frame:
   sensor_type: camera
   sensor_name: d400_color_optical_frame
   fps: 30
   width: 8
   height: 6
   model: pinhole
   intrinsics: !!opencv-matrix
      rows: 1
      cols: 4
      dt: d
      data: [ 6.1145098876953125e+02, 4.3320397949218750e+02,
          6.1148571777343750e+02, 2.4947302246093750e+02 ]
   distortion_model: radial-tangential
   distortion_coefficients: !!opencv-matrix
      rows: 1
      cols: 5
      dt: d
      data: [ 0.01, -0.02, 0., 0., 0. ]
d400_accelerometer:
   sensor_type: imu
   fps: 250
d400_gyroscope:
   sensor_type: imu
   fps: 400
)";

// base_link -> d400_link (translation), d400_link -> colour (optical rotation), d400_link -> IMU frames.
const char* kTrans = R"(%YAML:1.0
trans_matrix:
   - parent_frame: base_link
     child_frame: d400_link
     matrix: !!opencv-matrix
        rows: 4
        cols: 4
        dt: f
        data: [ 1., 0., 0., 0.2, 0., 1., 0., 0., 0., 0., 1., 0.5, 0., 0., 0., 1. ]
   - parent_frame: d400_link
     child_frame: d400_color_optical_frame
     matrix: !!opencv-matrix
        rows: 4
        cols: 4
        dt: f
        data: [ 0., 0., 1., 0., -1., 0., 0., 0.015, 0., -1., 0., 0., 0., 0., 0., 1. ]
   - parent_frame: d400_link
     child_frame: d400_gyroscope
     matrix: !!opencv-matrix
        rows: 4
        cols: 4
        dt: f
        data: [ 1., 0., 0., -0.01, 0., 1., 0., 0.005, 0., 0., 1., 0., 0., 0., 0., 1. ]
   - parent_frame: d400_link
     child_frame: d400_accelerometer
     matrix: !!opencv-matrix
        rows: 4
        cols: 4
        dt: f
        data: [ 1., 0., 0., -0.01, 0., 1., 0., 0.005, 0., 0., 1., 0., 0., 0., 0., 1. ]
)";

// Accelerometer at 250 Hz, linear in time (so interpolation is exact); gyroscope at 400 Hz starting earlier.
double acc_x(int64_t t_ns) { return 0.5 + 2.0 * static_cast<double>(t_ns - 20'000'000'000) * 1e-9; }

std::string write_openloris_fixture(const std::string& name) {
  const std::string dir = temp_dir(name);
  std::filesystem::create_directories(dir + "/color");
  std::filesystem::create_directories(dir + "/aligned_depth");
  write_text(dir + "/sensors.yaml", kSensors);
  write_text(dir + "/trans_matrix.yaml", kTrans);
  std::string color = "#timestamp filename\n", depth = color;
  for (int k = 0; k < 3; ++k) {
    const std::string t = "20.0" + std::to_string(k + 1) + "0000";
    cv::imwrite(dir + "/color/" + t + ".png", cv::Mat(6, 8, CV_8UC3, cv::Scalar(1, 2, 3 + k)));
    cv::imwrite(dir + "/aligned_depth/" + t + ".png", cv::Mat(6, 8, CV_16UC1, cv::Scalar(1200 + k)));
    color += t + " color/" + t + ".png\n";
    depth += t + " aligned_depth/" + t + ".png\n";
  }
  write_text(dir + "/color.txt", color);
  write_text(dir + "/aligned_depth.txt", depth);
  std::string acc = "#timestamp ax ay az\n", gyr = "#timestamp gx gy gz\n";
  for (int i = 0; i < 25; ++i) {  // 20.000 .. 20.096 s
    const int64_t t = 20'000'000'000 + int64_t{i} * 4'000'000;
    acc += text_seconds(t) + " " + std::to_string(acc_x(t)) + " 0.1 9.8\n";
  }
  for (int i = 0; i < 44; ++i) {  // 19.995 .. 20.1025 s
    const int64_t t = 19'995'000'000 + int64_t{i} * 2'500'000;
    gyr += text_seconds(t) + " 0.01 0.02 " + std::to_string(i) + "\n";
  }
  write_text(dir + "/d400_accelerometer.txt", acc);
  write_text(dir + "/d400_gyroscope.txt", gyr);
  write_text(dir + "/groundtruth.txt",
             "#timestamp tx ty tz qx qy qz qw\n20.000 1 2 0 0 0 0 1\n20.050 1.5 2 0 0 0 0 1\n");
  return dir;
}

TEST(OpenLorisReader, ReadsCalibrationFramesAndMergesImuRates) {
  const std::string dir = write_openloris_fixture("openloris_layout");
  auto log = drivers::open_log(dir);
  ASSERT_EQ(log->format_name(), "openloris");
  const Rig& r = log->rig();
  EXPECT_EQ(r.rgb.fx, 6.1145098876953125e+02);
  EXPECT_EQ(r.rgb.cx, 4.3320397949218750e+02) << "OpenLORIS stores fx cx fy cy";
  EXPECT_EQ(r.rgb.fy, 6.1148571777343750e+02);
  EXPECT_EQ(r.rgb.cy, 2.4947302246093750e+02);
  EXPECT_EQ(r.rgb.distortion, DistortionModel::kRadTan);
  EXPECT_EQ(r.rgb.dist[1], -0.02);
  EXPECT_EQ(r.rgb.width, 8);
  EXPECT_EQ(r.camera_rate_hz, 30);
  EXPECT_EQ(r.imu_rate_hz, 400) << "the merged stream runs at the faster (gyroscope) rate";
  EXPECT_EQ(r.depth.scale_m_per_unit, 0.001);
  EXPECT_TRUE(has_problem(*log, "assumed", "sensors.yaml"))
      << "the 1 mm depth unit is an assumption, said so";
  // T_BC = T_gyro,colour = inv(T_link,gyro) * T_link,colour.
  const Mat4d expect = {0, 0, 1, 0.01, -1, 0, 0, 0.015 - 0.005, 0, -1, 0, 0, 0, 0, 0, 1};
  for (int i = 0; i < 16; ++i) EXPECT_NEAR(r.T_BC[i], expect[i], 1e-15) << i;

  const auto all = read_all(*log);
  const auto imu = of_type(all, RecordType::kImu);
  // Gyroscope stamps inside [20.000, 20.096]: 19.995 and 19.9975 before, 20.0975 and later after.
  ASSERT_EQ(imu.size(), 39u) << problems_text(*log);
  EXPECT_TRUE(has_problem(*log, "imu-merge", "d400_gyroscope.txt")) << problems_text(*log);
  for (const auto& m : imu) {
    EXPECT_GE(m.imu.t_ns, 20'000'000'000);
    EXPECT_LE(m.imu.t_ns, 20'096'000'000);
    EXPECT_NEAR(m.imu.acc_mps2[0], acc_x(m.imu.t_ns), 1e-6) << "interpolated accelerometer at the gyro stamp";
    EXPECT_EQ(m.imu.acc_mps2[2], 9.8);
    EXPECT_EQ(m.imu.gyro_rps[1], 0.02);
  }
  EXPECT_EQ(imu.front().imu.gyro_rps[2], 2.0) << "the gyro rows are used as they are (row 2 = 20.000 s)";
  const auto rgb = of_type(all, RecordType::kRgb), depth = of_type(all, RecordType::kDepth);
  ASSERT_EQ(rgb.size(), 3u);
  ASSERT_EQ(depth.size(), 3u);
  EXPECT_EQ(depth[2].image.t_ns, rgb[2].image.t_ns);
  EXPECT_DOUBLE_EQ(depth_m(depth[2].image, 5, r.depth.scale_m_per_unit), 1.202);
  // Ground truth: base_link's pose moved to the IMU: p_WB = p_W,base + R * t_base,gyro (R = I here).
  const auto gt = of_type(all, RecordType::kGroundTruth);
  ASSERT_EQ(gt.size(), 2u);
  EXPECT_NEAR(gt[0].gt.p_WB[0], 1.0 + 0.2 - 0.01, 1e-12);
  EXPECT_NEAR(gt[0].gt.p_WB[1], 2.0 + 0.005, 1e-12);
  EXPECT_NEAR(gt[0].gt.p_WB[2], 0.5, 1e-12);
}

TEST(OpenLorisReader, MissingCalibrationNamesTheField) {
  const std::string dir = write_openloris_fixture("openloris_nocalib");
  std::filesystem::remove(dir + "/sensors.yaml");
  try {
    drivers::OpenLorisReader log(dir);
    FAIL() << "expected an error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("d400_color_optical_frame.intrinsics"), std::string::npos)
        << e.what();
  }
  std::filesystem::remove(dir + "/trans_matrix.yaml");
  write_text(dir + "/sensors.yaml", kSensors);
  try {
    drivers::OpenLorisReader log(dir);
    FAIL() << "expected an error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("T_BC"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("trans_matrix.yaml"), std::string::npos) << e.what();
  }
  const Rig rig = small_rig();
  drivers::OpenLorisReader log(dir, &rig);
  EXPECT_EQ(log.rig().T_BC, rig.T_BC);
  EXPECT_EQ(log.rig().rgb.fx, 6.1145098876953125e+02) << "the dataset's intrinsics win over the rig's";
}

TEST(OpenLorisReader, MalformedInputIsReportedNeverACrash) {
  const std::string dir = write_openloris_fixture("openloris_malformed");
  write_text(dir + "/sensors.yaml", std::string(kSensors) + "   broken: [ 1, 2\n");
  EXPECT_THROW(drivers::OpenLorisReader log(dir), std::runtime_error);
  write_text(dir + "/sensors.yaml", kSensors);
  std::string acc;
  {
    std::ifstream f(dir + "/d400_accelerometer.txt");
    std::string l;
    while (std::getline(f, l)) acc += l + "\n";
  }
  write_text(dir + "/d400_accelerometer.txt", acc + "20.100 1 2\n20.096 1 2 3\n");
  write_text(dir + "/color.txt", "20.010000 color/20.010000.png\n20.020000 color/missing.png\n20.030000\n");
  drivers::OpenLorisReader log(dir);
  read_all(log);
  EXPECT_TRUE(has_problem(log, "bad-row", "d400_accelerometer.txt:27")) << problems_text(log);
  EXPECT_TRUE(has_problem(log, "duplicate", "d400_accelerometer.txt:28")) << problems_text(log);
  EXPECT_TRUE(has_problem(log, "missing-file", "color.txt:2")) << problems_text(log);
  EXPECT_TRUE(has_problem(log, "bad-row", "color.txt:3")) << problems_text(log);
  EXPECT_EQ(log.rgb_count(), 1u);
}

TEST(OpenLorisExport, KlogToOpenLorisToKlogIsExact) {
  const std::string dir = temp_dir("openloris_roundtrip");
  write_small_klog(dir + "/a.klog");
  drivers::KlogReader a(dir + "/a.klog");
  const auto st = drivers::export_openloris(a, dir + "/ol");
  EXPECT_EQ(st.imu, 200u);
  drivers::OpenLorisReader b(dir + "/ol");
  EXPECT_TRUE(drivers::is_openloris_folder(dir + "/ol"));
  const Rig& ra = a.rig();
  const Rig& rb = b.rig();
  EXPECT_EQ(rb.rgb.fx, ra.rgb.fx);
  EXPECT_EQ(rb.rgb.cy, ra.rgb.cy);
  EXPECT_EQ(rb.rgb.dist, ra.rgb.dist);
  EXPECT_EQ(rb.T_BC, ra.T_BC);
  EXPECT_EQ(rb.depth.scale_m_per_unit, ra.depth.scale_m_per_unit);
  EXPECT_EQ(rb.imu_rate_hz, ra.imu_rate_hz);
  EXPECT_EQ(rb.camera_rate_hz, ra.camera_rate_hz);
  const auto x = read_all(a), y = read_all(b);
  ASSERT_EQ(x.size(), y.size()) << problems_text(b);
  for (size_t i = 0; i < x.size(); ++i) {
    ASSERT_EQ(x[i].type, y[i].type) << i;
    switch (x[i].type) {
      case RecordType::kImu:
        EXPECT_EQ(x[i].imu.t_ns, y[i].imu.t_ns);
        EXPECT_EQ(x[i].imu.gyro_rps, y[i].imu.gyro_rps);
        EXPECT_EQ(x[i].imu.acc_mps2, y[i].imu.acc_mps2);
        break;
      case RecordType::kGroundTruth:
        EXPECT_EQ(x[i].gt.t_ns, y[i].gt.t_ns);
        EXPECT_EQ(x[i].gt.p_WB, y[i].gt.p_WB);
        EXPECT_EQ(x[i].gt.q_WB, y[i].gt.q_WB);
        break;
      default:
        EXPECT_EQ(x[i].image.t_ns, y[i].image.t_ns);
        EXPECT_EQ(x[i].image.format, y[i].image.format);
        EXPECT_EQ(x[i].image.pixels, y[i].image.pixels);
    }
  }
}

}  // namespace
}  // namespace kestrel::test

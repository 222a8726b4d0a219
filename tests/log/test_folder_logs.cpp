// EuRoC and TUM RGB-D folder readers, on the real data in ../shared/data and
// on fixture folders the tests write themselves.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <sstream>

#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

using drivers::LogRecord;
using drivers::RecordType;

size_t data_lines(const std::string& path) {
  std::ifstream f(path);
  std::string l;
  size_t n = 0;
  while (std::getline(f, l))
    if (!l.empty() && l[0] != '#' && l != "\r") ++n;
  return n;
}

std::string first_data_line(const std::string& path) {
  std::ifstream f(path);
  std::string l;
  while (std::getline(f, l))
    if (!l.empty() && l[0] != '#') return l;
  return "";
}

struct Counts {
  size_t imu = 0, rgb = 0, depth = 0, gt = 0, events = 0, right = 0;
  bool time_ordered = true;
};

Counts replay(drivers::LogSource& src) {
  Counts c;
  LogRecord r;
  int64_t last = INT64_MIN;
  while (src.next(r)) {
    int64_t t = 0;
    switch (r.type) {
      case RecordType::kImu:
        ++c.imu, t = r.imu.t_ns;
        break;
      case RecordType::kRgb:
        ++c.rgb, t = r.image.t_ns;
        break;
      case RecordType::kDepth:
        ++c.depth, t = r.image.t_ns;
        break;
      case RecordType::kGroundTruth:
        ++c.gt, t = r.gt.t_ns;
        break;
      case RecordType::kEvent:
        ++c.events, t = r.event.t_ns;
        break;
      case RecordType::kRight:
        ++c.right, t = r.image.t_ns;
        break;
    }
    if (t < last) c.time_ordered = false;
    last = t;
  }
  return c;
}

size_t count_kind(const drivers::LogSource& src, const std::string& kind) {
  size_t n = 0;
  for (const auto& p : src.problems()) n += p.kind == kind;
  return n;
}

TEST(EurocReader, AslFolderWithRealImages) {
  KESTREL_REQUIRE_SHARED("euroc/V1_01_easy_first95/mav0");
  const std::string seq = shared_path("euroc/V1_01_easy_first95");
  auto src = drivers::open_log(seq);
  ASSERT_EQ(src->format_name(), "euroc");
  const size_t imu_rows = data_lines(seq + "/mav0/imu0/data.csv");
  ASSERT_GT(imu_rows, 1000u);

  LogRecord r;
  Counts c;
  int64_t last = INT64_MIN;
  while (src->next(r)) {
    const int64_t t = r.type == RecordType::kImu ? r.imu.t_ns : r.image.t_ns;
    EXPECT_GE(t, last);
    last = t;
    if (r.type == RecordType::kImu) {
      ++c.imu;
    } else {
      // cam1 is the right camera of a stereo pair (docs/stereo.md).
      ASSERT_TRUE(r.type == RecordType::kRgb || r.type == RecordType::kRight);
      ++(r.type == RecordType::kRgb ? c.rgb : c.right);
      EXPECT_EQ(r.image.format, PixelFormat::kGray8);
      EXPECT_EQ(r.image.width, 752);
      EXPECT_EQ(r.image.height, 480);
      EXPECT_EQ(r.image.pixels.size(), 752u * 480u);
    }
  }
  EXPECT_EQ(c.rgb, 95u);
  EXPECT_EQ(c.right, 95u);
  EXPECT_EQ(c.imu, imu_rows);
  // cam1/data.csv lists 4 images more than the folder holds: each named, nothing else wrong.
  ASSERT_EQ(src->problems().size(), 4u);
  for (const auto& p : src->problems()) {
    EXPECT_EQ(p.kind, "missing-file");
    EXPECT_NE(p.where.find("cam1/data.csv:"), std::string::npos) << p.where;
  }
  EXPECT_TRUE(src->rig().stereo.present);

  // The rig comes from the ASL sensor files.
  const Rig& rig = src->rig();
  EXPECT_EQ(rig.name, "V1_01_easy_first95");
  EXPECT_EQ(rig.rgb.width, 752);
  EXPECT_DOUBLE_EQ(rig.rgb.fx, 458.654);
  EXPECT_DOUBLE_EQ(rig.rgb.cy, 248.375);
  EXPECT_EQ(rig.rgb.distortion, DistortionModel::kRadTan);
  EXPECT_DOUBLE_EQ(rig.rgb.dist[0], -0.28340811);
  EXPECT_EQ(rig.rgb.dist[4], 0.0);
  EXPECT_DOUBLE_EQ(rig.T_BC[3], -0.0216401454975);
  EXPECT_DOUBLE_EQ(rig.imu.gyro_noise_density_rad_s_sqrthz, 1.6968e-04);
  EXPECT_DOUBLE_EQ(rig.imu.acc_random_walk_mps3_sqrthz, 3.0e-3);
  EXPECT_EQ(rig.imu_rate_hz, 200);
  EXPECT_EQ(rig.camera_rate_hz, 20);
}

TEST(EurocReader, FlatFolderGivesImuAndGroundTruth) {
  KESTREL_REQUIRE_SHARED("euroc/V1_02_medium");
  const std::string seq = shared_path("euroc/V1_02_medium");
  drivers::EurocReader src(seq);
  EXPECT_TRUE(src.flat_layout());
  EXPECT_EQ(src.ground_truth_file(), seq + "/gt_official_200hz.csv");
  const Counts c = replay(src);
  EXPECT_EQ(c.imu, data_lines(seq + "/imu0.csv"));
  EXPECT_EQ(c.gt, data_lines(seq + "/gt_official_200hz.csv"));
  EXPECT_EQ(c.rgb, 0u);
  EXPECT_TRUE(c.time_ordered);
  EXPECT_TRUE(src.problems().empty());

  // First ground-truth row, parsed independently: t, p, q (w x y z), v.
  src.rewind();
  LogRecord r;
  while (src.next(r) && r.type != RecordType::kGroundTruth) {
  }
  std::istringstream row(first_data_line(seq + "/gt_official_200hz.csv"));
  long long t;
  char comma;
  double v[10];
  row >> t;
  for (double& x : v) row >> comma >> x;
  EXPECT_EQ(r.gt.t_ns, t);
  EXPECT_EQ(r.gt.p_WB[0], v[0]);
  EXPECT_EQ(r.gt.q_WB[0], v[3]);
  EXPECT_EQ(r.gt.q_WB[3], v[6]);
  EXPECT_TRUE(r.gt.has_velocity);
  EXPECT_EQ(r.gt.v_WB[2], v[9]);
  EXPECT_DOUBLE_EQ(src.rig().rgb.fx, 458.654);
}

void write_file(const std::string& path, const std::string& text) {
  std::ofstream(path, std::ios::binary) << text;
}

// A hand-made ASL folder: malformed rows, a NaN, a row without its PNG.
TEST(EurocReader, ReportsBadRowsAndMissingImagesWithFileAndLine) {
  const std::string dir = temp_dir("euroc_fixture");
  const std::string mav = dir + "/mav0";
  std::filesystem::create_directories(mav + "/imu0");
  std::filesystem::create_directories(mav + "/cam0/data");
  write_file(mav + "/imu0/data.csv",
             "#timestamp [ns],wx,wy,wz,ax,ay,az\n"
             "1000,0.1,0.2,0.3,1,2,3\n"
             "abc,0.1,0.2,0.3,1,2,3\n"     // line 3: bad timestamp
             "3000,0.1,0.2,0.3,1,2,3\r\n"  // CRLF is fine
             "4000,0.1,0.2\n"              // line 5: too few fields
             "5000,nan,0.2,0.3,1,2,3\n"    // line 6: kept, flagged
             "6000,0.1,0.2,0.3,1,2,x\n"    // line 7: bad number
             "\n"
             "2000,0.1,0.2,0.3,1,2,3\n");  // line 9: out of order, replayed sorted
  write_file(mav + "/cam0/data.csv",
             "#timestamp [ns],filename\n1500,1500.png\n2500,2500.png\n3500,3500.png\n");
  cv::imwrite(mav + "/cam0/data/1500.png", cv::Mat(4, 6, CV_8UC1, cv::Scalar(7)));
  cv::imwrite(mav + "/cam0/data/3500.png", cv::Mat(4, 6, CV_8UC1, cv::Scalar(9)));
  drivers::EurocReader src(dir);
  const Counts c = replay(src);
  EXPECT_EQ(c.imu, 4u);  // lines 2, 4, 6 (flagged) and 9
  EXPECT_EQ(c.rgb, 2u);
  EXPECT_TRUE(c.time_ordered);
  auto has = [&](const std::string& where, const std::string& kind) {
    for (const auto& p : src.problems())
      if (p.where == where && p.kind == kind) return true;
    return false;
  };
  const std::string imu = mav + "/imu0/data.csv";
  EXPECT_TRUE(has(imu + ":3", "bad-row"));
  EXPECT_TRUE(has(imu + ":5", "bad-row"));
  EXPECT_TRUE(has(imu + ":6", "non-finite"));
  EXPECT_TRUE(has(imu + ":7", "bad-row"));
  EXPECT_TRUE(has(imu + ":9", "time-order"));
  EXPECT_TRUE(has(mav + "/cam0/data.csv:3", "missing-file"));
  EXPECT_TRUE(has(mav + "/cam0/sensor.yaml", "missing-file"));
  EXPECT_EQ(count_kind(src, "missing-file"), 3u);  // the PNG and both sensor.yaml
  src.rewind();
  LogRecord r;
  size_t flagged = 0;
  while (src.next(r))
    if (r.type == RecordType::kImu && (r.imu.flags & kImuNonFinite)) {
      ++flagged;
      EXPECT_TRUE(std::isnan(r.imu.gyro_rps[0]));
    }
  EXPECT_EQ(flagged, 1u);
}

TEST(EurocReader, MalformedSensorYamlNamesFileAndField) {
  const std::string dir = temp_dir("euroc_badyaml");
  write_file(dir + "/imu0.csv", "1000,0,0,0,0,0,9.8\n");
  write_file(dir + "/cam0_sensor.yaml",
             "%YAML:1.0\nresolution: [752, 480]\nintrinsics: [458.6, abc, 367.2, 248.3]\n"
             "T_BS: {rows: 4, cols: 4, data: [1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1]}\n");
  try {
    drivers::EurocReader src(dir);
    ADD_FAILURE();
  } catch (const std::runtime_error& e) {
    EXPECT_EQ(std::string(e.what()), dir + "/cam0_sensor.yaml: intrinsics[1]: expected a finite number");
  }
  EXPECT_THROW(drivers::EurocReader(dir + "/absent"), std::runtime_error);
}

// The one reader of EuRoC sensor files, which the EuRoC reader and the
// simulator's hybrid mode both go through.
TEST(EurocSensorYaml, ReadsTheRealCameraAndImuFiles) {
  KESTREL_REQUIRE_SHARED("euroc/V1_02_medium/cam0_sensor.yaml");
  const auto cam = drivers::read_euroc_sensor_yaml(shared_path("euroc/V1_02_medium/cam0_sensor.yaml"));
  ASSERT_TRUE(cam.resolution_px && cam.intrinsics_px);
  EXPECT_EQ((*cam.resolution_px)[0], 752);
  EXPECT_EQ((*cam.resolution_px)[1], 480);
  EXPECT_DOUBLE_EQ((*cam.intrinsics_px)[0], 458.654);
  EXPECT_EQ(cam.distortion, DistortionModel::kRadTan);
  ASSERT_EQ(cam.distortion_coefficients.size(), 4u);
  EXPECT_DOUBLE_EQ(cam.distortion_coefficients[0], -0.28340811);
  EXPECT_DOUBLE_EQ(cam.T_BS[3], -0.0216401454975);
  EXPECT_EQ(cam.T_BS[15], 1.0);
  EXPECT_EQ(cam.rate_hz, 20.0);
  EXPECT_FALSE(cam.gyro_noise_density_rad_s_sqrthz);

  const auto imu = drivers::read_euroc_sensor_yaml(shared_path("euroc/V1_02_medium/imu0_sensor.yaml"));
  EXPECT_FALSE(imu.resolution_px);
  EXPECT_EQ(imu.rate_hz, 200.0);
  EXPECT_EQ(imu.gyro_noise_density_rad_s_sqrthz, 1.6968e-04);
  EXPECT_EQ(imu.gyro_random_walk_rad_s2_sqrthz, 1.9393e-05);
  EXPECT_EQ(imu.acc_noise_density_mps2_sqrthz, 2.0e-3);
  EXPECT_EQ(imu.acc_random_walk_mps3_sqrthz, 3.0e-3);
  for (size_t i = 0; i < 16; ++i) EXPECT_EQ(imu.T_BS[i], i % 5 == 0 ? 1.0 : 0.0) << i;  // the IMU is the body
}

TEST(EurocSensorYaml, OptionalKeysStayAbsentAndBadOnesAreNamed) {
  const std::string dir = temp_dir("euroc_sensor_yaml");
  const std::string path = dir + "/sensor.yaml";
  // A bare list of 16 is taken for T_BS as well as OpenCV's matrix map.
  write_file(path, "%YAML:1.0\r\nsensor_type: imu\r\nT_BS: [1,0,0,0.5, 0,1,0,0, 0,0,1,0, 0,0,0,1]\r\n");
  const auto y = drivers::read_euroc_sensor_yaml(path);
  EXPECT_EQ(y.T_BS[3], 0.5);
  EXPECT_FALSE(y.rate_hz);
  EXPECT_FALSE(y.intrinsics_px);
  EXPECT_EQ(y.distortion, DistortionModel::kNone);
  EXPECT_TRUE(y.distortion_coefficients.empty());
  EXPECT_FALSE(y.acc_random_walk_mps3_sqrthz);

  auto error_of = [&](const std::string& body) -> std::string {
    write_file(path, body);
    try {
      drivers::read_euroc_sensor_yaml(path);
    } catch (const std::runtime_error& e) {
      return e.what();
    }
    return "no error";
  };
  const std::string T = "T_BS: {rows: 4, cols: 4, data: [1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1]}\n";
  EXPECT_EQ(error_of("%YAML:1.0\nrate_hz: 200\n"), path + ": T_BS: missing (expected rows, cols, data)");
  EXPECT_EQ(error_of("T_BS: {data: [1, 2, 3]}\n"), path + ": T_BS.data: expected a list of 16 numbers");
  EXPECT_EQ(error_of(T + "gyroscope_noise_density: .nan\n"),
            path + ": gyroscope_noise_density: expected a finite number");
  EXPECT_EQ(error_of(T + "rate_hz: fast\n"), path + ": rate_hz: expected a finite number");
  EXPECT_EQ(error_of(T + "resolution: [752.5, 480]\n"),
            path + ": resolution: expected two positive integers");
  EXPECT_EQ(error_of(T + "intrinsics: [0, 1, 2, 3]\n"), path + ": intrinsics: focal lengths must be > 0");
  EXPECT_EQ(error_of(T + "distortion_model: fisheye\n"),
            path + ": distortion_model: expected radial-tangential, equidistant or none, got \"fisheye\"");
  EXPECT_EQ(error_of("%YAML:1.0\nT_BS: [1, 2\n"),
            path + ":3: YAML syntax error: end of sequence flow not found");
  EXPECT_EQ(error_of("- 1\n- 2\n"), path + ": expected a mapping");
}

TEST(TumReader, Freiburg1XyzTextFiles) {
  KESTREL_REQUIRE_SHARED("tum-rgbd/rgbd_dataset_freiburg1_xyz");
  const std::string seq = shared_path("tum-rgbd/rgbd_dataset_freiburg1_xyz");
  auto src = drivers::open_log(seq);
  ASSERT_EQ(src->format_name(), "tum");
  const Counts c = replay(*src);
  EXPECT_EQ(c.gt, data_lines(seq + "/groundtruth.txt"));
  EXPECT_EQ(c.imu, 0u);
  EXPECT_EQ(c.rgb, 0u);  // the images are not in ../shared/data
  EXPECT_TRUE(c.time_ordered);
  EXPECT_EQ(count_kind(*src, "no-gyro"), 1u);
  EXPECT_EQ(count_kind(*src, "missing-file"), 2u);  // rgb/ and depth/, one problem each

  auto* tum = dynamic_cast<drivers::TumReader*>(src.get());
  ASSERT_NE(tum, nullptr);
  const size_t n_rgb = data_lines(seq + "/rgb.txt");
  EXPECT_LE(tum->associated_pairs(), std::min(n_rgb, data_lines(seq + "/depth.txt")));
  EXPECT_GT(tum->associated_pairs(), n_rgb * 9 / 10);

  // TUM stores qx qy qz qw; ours is w x y z.
  src->rewind();
  LogRecord r;
  ASSERT_TRUE(src->next(r));
  ASSERT_EQ(r.type, RecordType::kGroundTruth);
  std::istringstream row(first_data_line(seq + "/groundtruth.txt"));
  std::string ts;
  double v[7];
  row >> ts;
  for (double& x : v) row >> x;
  const size_t dot = ts.find('.');
  std::string frac = ts.substr(dot + 1);
  frac.resize(9, '0');
  EXPECT_EQ(r.gt.t_ns, std::stoll(ts.substr(0, dot)) * 1000000000LL + std::stoll(frac));
  EXPECT_EQ(r.gt.p_WB[2], v[2]);
  EXPECT_EQ(r.gt.q_WB[0], v[6]);
  EXPECT_EQ(r.gt.q_WB[1], v[3]);
  EXPECT_EQ(r.gt.q_WB[3], v[5]);
  EXPECT_EQ(src->rig().rgb.fx, 517.3);
  EXPECT_EQ(src->rig().depth.scale_m_per_unit, 1.0 / 5000.0);
}

TEST(TumReader, FixtureWithImagesAssociatesRgbAndDepth) {
  const std::string dir = temp_dir("tum_fixture");
  std::filesystem::create_directories(dir + "/rgb");
  std::filesystem::create_directories(dir + "/depth");
  // BGR on disk (OpenCV), RGB in the record.
  const char* rgb_t[] = {"100.000000", "100.033000", "100.066000"};
  const char* depth_t[] = {"100.005000", "100.040000", "100.200000"};  // the last has no partner
  std::string rgb_txt = "# color images\n# timestamp filename\n", depth_txt = "# depth maps\n";
  for (int i = 0; i < 3; ++i) {
    cv::Mat bgr(3, 4, CV_8UC3, cv::Scalar(10 + i, 20, 30));
    cv::imwrite(dir + "/rgb/" + rgb_t[i] + ".png", bgr);
    cv::Mat d(3, 4, CV_16UC1, cv::Scalar(5000 + i));
    cv::imwrite(dir + "/depth/" + depth_t[i] + ".png", d);
    rgb_txt += std::string(rgb_t[i]) + " rgb/" + rgb_t[i] + ".png\n";
    depth_txt += std::string(depth_t[i]) + " depth/" + depth_t[i] + ".png\n";
  }
  rgb_txt += "100.1 rgb/absent.png\n";
  write_file(dir + "/rgb.txt", rgb_txt);
  write_file(dir + "/depth.txt", depth_txt);
  write_file(dir + "/groundtruth.txt",
             "# t tx ty tz qx qy qz qw\n100.01 1 2 3 0 0 0.6 0.8\n100.02 1 2 3 0 0 0.6\n");
  write_file(dir + "/accelerometer.txt", "100.0 0 0 9.8\n");

  drivers::TumReader src(dir);
  EXPECT_EQ(src.associated_pairs(), 2u);
  LogRecord r;
  std::vector<LogRecord> recs;
  while (src.next(r)) recs.push_back(r);
  size_t n_rgb = 0, n_depth = 0, n_gt = 0;
  for (size_t i = 0; i < recs.size(); ++i) {
    const auto& x = recs[i];
    if (x.type == RecordType::kRgb) {
      ++n_rgb;
      EXPECT_EQ(x.image.format, PixelFormat::kRgb8);
      ASSERT_EQ(x.image.pixels.size(), 36u);
      EXPECT_EQ(x.image.pixels[0], 30);  // R
      EXPECT_EQ(x.image.pixels[2], 10 + x.image.seq);
    } else if (x.type == RecordType::kDepth) {
      ++n_depth;
      EXPECT_EQ(x.image.format, PixelFormat::kDepthU16);
      // Paired depth carries the colour frame's stamp and follows it.
      ASSERT_GT(i, 0u);
      EXPECT_EQ(recs[i - 1].type, RecordType::kRgb);
      EXPECT_EQ(x.image.t_ns, recs[i - 1].image.t_ns);
      uint16_t d;
      std::memcpy(&d, x.image.pixels.data(), 2);
      EXPECT_EQ(d, 5000 + x.image.seq);
    } else if (x.type == RecordType::kGroundTruth) {
      ++n_gt;
      EXPECT_EQ(x.gt.t_ns, 100'010'000'000);
      EXPECT_EQ(x.gt.q_WB, (Quatd{0.8, 0, 0, 0.6}));
    }
  }
  EXPECT_EQ(n_rgb, 3u);
  EXPECT_EQ(n_depth, 2u);
  EXPECT_EQ(n_gt, 1u);
  auto has = [&](const std::string& where, const std::string& kind) {
    for (const auto& p : src.problems())
      if (p.where == where && p.kind == kind) return true;
    return false;
  };
  EXPECT_TRUE(has(dir + "/depth.txt:4", "unassociated"));
  EXPECT_TRUE(has(dir + "/rgb.txt:6", "missing-file"));
  EXPECT_TRUE(has(dir + "/rgb.txt:5", "no-depth"));
  EXPECT_TRUE(has(dir + "/groundtruth.txt:3", "bad-row"));
  EXPECT_TRUE(has(dir + "/accelerometer.txt", "no-gyro"));
  EXPECT_EQ(src.rig().rgb.fx, 517.3);
}

TEST(OpenLog, DetectsFormatsAndRejectsUnknownOnes) {
  EXPECT_EQ(drivers::parse_log_format("auto"), drivers::LogFormat::kAuto);
  EXPECT_EQ(drivers::parse_log_format("klog"), drivers::LogFormat::kKlog);
  EXPECT_EQ(drivers::parse_log_format("euroc"), drivers::LogFormat::kEuroc);
  EXPECT_EQ(drivers::parse_log_format("tum"), drivers::LogFormat::kTum);
  EXPECT_EQ(drivers::parse_log_format("rosbag2"), drivers::LogFormat::kRosbag2);
  EXPECT_THROW(drivers::parse_log_format("hdf5"), std::runtime_error);
  const std::string dir = temp_dir("open_log");
  try {
    drivers::open_log(dir);
    ADD_FAILURE();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(dir), std::string::npos);
  }
  EXPECT_THROW(drivers::open_log(dir + "/absent"), std::runtime_error);
  write_file(dir + "/x.txt", "not a log");
  EXPECT_THROW(drivers::open_log(dir + "/x.txt"), std::runtime_error);
}

}  // namespace
}  // namespace kestrel::test

// 7-Scenes reader: a hand-made folder with every kind of bad input, and the
// real sequence in ../shared/data when it is there.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

constexpr int kW = 64, kH = 48;

std::string stem(const std::string& dir, int i) {
  char b[32];
  std::snprintf(b, sizeof b, "/frame-%06d", i);
  return dir + b;
}

// T_WD of frame i: a slow turn about the camera's y axis and a walk along x.
Eigen::Isometry3d pose_of(int i) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::AngleAxisd(0.05 * i, Eigen::Vector3d::UnitY()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(0.1 * i, 2.0, -0.5);
  return T;
}

void write_pose(const std::string& path, const Eigen::Isometry3d& T) {
  std::ofstream f(path);
  f.precision(17);
  const Eigen::Matrix4d m = T.matrix();
  for (int r = 0; r < 4; ++r) f << m(r, 0) << " " << m(r, 1) << " " << m(r, 2) << " " << m(r, 3) << "\n";
}

cv::Mat colour_of(int i) {
  cv::Mat c(kH, kW, CV_8UC3);
  for (int y = 0; y < kH; ++y)
    for (int x = 0; x < kW; ++x)
      c.at<cv::Vec3b>(y, x) = cv::Vec3b(uint8_t(x * 4 + i), uint8_t(y * 5), uint8_t(i * 20));
  return c;
}

// A plane at 1.5 m (+ 1 mm per frame), a 65535 corner (7-Scenes' "no reading") and a 0 one.
cv::Mat depth_of(int i) {
  cv::Mat d(kH, kW, CV_16UC1, cv::Scalar(1500 + i));
  d(cv::Rect(0, 0, 4, 4)).setTo(65535);
  d(cv::Rect(kW - 4, kH - 4, 4, 4)).setTo(0);
  return d;
}

// A rig whose depth camera is the colour camera: registration must change nothing.
Rig identity_rig() {
  Rig r;
  r.name = "7scenes-test";
  r.rgb.width = kW, r.rgb.height = kH;
  r.rgb.fx = r.rgb.fy = 60.0;
  r.rgb.cx = 31.5, r.rgb.cy = 23.5;
  r.depth_camera.present = true;
  r.depth_camera.intrinsics = r.rgb;
  return r;
}

// Frames 0..n-1 with everything; the caller breaks what it wants broken.
std::string write_folder(const std::string& name, int n, bool intrinsics = true) {
  const std::string dir = temp_dir(name);
  for (int i = 0; i < n; ++i) {
    cv::imwrite(stem(dir, i) + ".color.png", colour_of(i));
    cv::imwrite(stem(dir, i) + ".depth.png", depth_of(i));
    write_pose(stem(dir, i) + ".pose.txt", pose_of(i));
  }
  if (intrinsics) std::ofstream(dir + "/camera-intrinsics.txt") << "60 0 31.5\n0 60 23.5\n0 0 1\n";
  // Gravity along the camera's +y (down in the image), as in 7-Scenes.
  std::ofstream(dir + "/gravity-direction.txt") << "0\n1\n0\n";
  return dir;
}

struct Read {
  std::vector<drivers::LogImage> rgb, depth;
  std::vector<GroundTruthPose> gt;
};

Read read_all(drivers::LogSource& s) {
  Read r;
  drivers::LogRecord rec;
  while (s.next(rec)) {
    if (rec.type == drivers::RecordType::kRgb) r.rgb.push_back(rec.image);
    if (rec.type == drivers::RecordType::kDepth) r.depth.push_back(rec.image);
    if (rec.type == drivers::RecordType::kGroundTruth) r.gt.push_back(rec.gt);
  }
  return r;
}

std::map<std::string, std::vector<std::string>> problems_by_kind(const drivers::LogSource& s) {
  std::map<std::string, std::vector<std::string>> m;
  for (const auto& p : s.problems()) m[p.kind].push_back(p.where);
  return m;
}

TEST(SevenScenes, ReadsFramesTimesDepthAndLevelledGroundTruth) {
  const std::string dir = write_folder("7s_ok", 5);
  ASSERT_TRUE(drivers::is_sevenscenes_folder(dir));
  const Rig rig = identity_rig();
  drivers::SevenScenesReader::Options o;
  o.fps = 15.0;
  drivers::SevenScenesReader reader(dir + "/", &rig, o);
  EXPECT_EQ(reader.format_name(), "7scenes");
  EXPECT_EQ(reader.rig().camera_rate_hz, 15.0);
  const Read r = read_all(reader);
  ASSERT_EQ(r.rgb.size(), 5u);
  ASSERT_EQ(r.depth.size(), 5u);
  ASSERT_EQ(r.gt.size(), 5u);
  for (int i = 0; i < 5; ++i) {
    const int64_t t = static_cast<int64_t>(std::llround(i * 1e9 / 15.0));
    EXPECT_EQ(r.rgb[i].t_ns, t);
    EXPECT_EQ(r.depth[i].t_ns, t);
    EXPECT_EQ(r.gt[i].t_ns, t);
    EXPECT_EQ(r.rgb[i].format, PixelFormat::kRgb8);
    // BGR on disk, RGB in the log: red is the third channel on disk.
    EXPECT_EQ(r.rgb[i].pixels[0], static_cast<uint8_t>(i * 20));
    EXPECT_EQ(r.rgb[i].pixels[2], static_cast<uint8_t>(i));
  }
  // 65535 and 0 are both "no reading"; the rest passes the identity registration unchanged.
  const auto* d = reinterpret_cast<const uint16_t*>(r.depth[2].pixels.data());
  ASSERT_EQ(r.depth[2].width, kW);
  ASSERT_EQ(r.depth[2].format, PixelFormat::kDepthU16);
  EXPECT_EQ(d[0], 0);
  EXPECT_EQ(d[kW * kH - 1], 0);
  EXPECT_EQ(d[20 * kW + 30], 1502);
  EXPECT_GT(reader.last_registration().valid_out, kW * kH * 9 / 10);
  // Gravity was +y in the poses' world: levelled, it is -z, so the world y
  // (2 m "down") becomes z = -2; x stays (the levelling turns about x).
  for (int i = 0; i < 5; ++i) {
    EXPECT_NEAR(r.gt[i].p_WB[0], 0.1 * i, 1e-12);
    EXPECT_NEAR(r.gt[i].p_WB[2], -2.0, 1e-12);
    EXPECT_NEAR(r.gt[i].p_WB[1], -0.5, 1e-12);
  }
  EXPECT_TRUE(problems_by_kind(reader).count("repeated-depth") == 0);
}

TEST(SevenScenesAuto, OpenLogDetectsTheFolderAndTheFormatName) {
  const std::string dir = write_folder("7s_auto", 3);
  EXPECT_EQ(drivers::parse_log_format("7scenes"), drivers::LogFormat::kSevenScenes);
  drivers::LogOpenOptions o;
  o.fps = 10;
  const auto log = drivers::open_log(dir, o);
  EXPECT_EQ(log->format_name(), "7scenes");
  EXPECT_EQ(log->rig().camera_rate_hz, 10.0);
  // No rig: the assumed Kinect calibration, said so; the depth camera from camera-intrinsics.txt.
  EXPECT_TRUE(log->rig().depth_camera.present);
  EXPECT_EQ(log->rig().depth_camera.intrinsics.fx, 60.0);
  EXPECT_EQ(log->rig().rgb.fx, 525.0);
  const auto kinds = problems_by_kind(*log);
  ASSERT_TRUE(kinds.count("assumed"));
  EXPECT_EQ(kinds.at("assumed")[0], dir + "/camera-intrinsics.txt");
  // The body is the colour camera: the ground truth moved by T_DC.
  const Read r = read_all(*log);
  ASSERT_EQ(r.gt.size(), 3u);
  EXPECT_GT(std::abs(r.gt[0].p_WB[0] - 0.0), 0.02);
  // The default rig survives its own YAML.
  EXPECT_TRUE(drivers::rig_equal(drivers::rig_from_yaml(drivers::rig_to_yaml(log->rig()), "x"), log->rig()));
}

TEST(SevenScenes, RepeatedMissingAndBadInputBecomeProblemsAtFileAndLine) {
  const std::string dir = write_folder("7s_bad", 8);
  // Frame 3 repeats frame 2's depth and colour byte for byte (the recorder
  // wrote the previous capture again).
  std::filesystem::copy_file(stem(dir, 2) + ".depth.png", stem(dir, 3) + ".depth.png",
                             std::filesystem::copy_options::overwrite_existing);
  std::filesystem::copy_file(stem(dir, 2) + ".color.png", stem(dir, 3) + ".color.png",
                             std::filesystem::copy_options::overwrite_existing);
  // Frame 4 absent altogether; frame 5 without depth.
  for (const char* k : {".color.png", ".depth.png", ".pose.txt"}) std::filesystem::remove(stem(dir, 4) + k);
  std::filesystem::remove(stem(dir, 5) + ".depth.png");
  // Frame 1's depth is an 8-bit image.
  cv::imwrite(stem(dir, 1) + ".depth.png", cv::Mat(kH, kW, CV_8UC1, cv::Scalar(7)));
  // Frame 6's pose is scaled (not rigid), frame 7's has a short third row.
  {
    Eigen::Isometry3d T = pose_of(6);
    Eigen::Matrix4d m = T.matrix();
    m.topLeftCorner<3, 3>() *= 1.01;
    std::ofstream f(stem(dir, 6) + ".pose.txt");
    for (int r = 0; r < 4; ++r) f << m(r, 0) << " " << m(r, 1) << " " << m(r, 2) << " " << m(r, 3) << "\n";
    std::ofstream(stem(dir, 7) + ".pose.txt") << "1 0 0 0\n0 1 0 0\n0 0 1\n0 0 0 1\n";
  }
  const Rig rig = identity_rig();
  drivers::SevenScenesReader reader(dir, &rig);
  const Read r = read_all(reader);
  const auto k = problems_by_kind(reader);
  ASSERT_TRUE(k.count("repeated-depth"));
  EXPECT_EQ(k.at("repeated-depth"), std::vector<std::string>{stem(dir, 3) + ".depth.png"});
  EXPECT_EQ(k.at("repeated-colour"), std::vector<std::string>{stem(dir, 3) + ".color.png"});
  EXPECT_EQ(reader.repeated_depth(), 1u);
  EXPECT_EQ(reader.repeated_colour(), 1u);
  EXPECT_EQ(k.at("missing-frame"), std::vector<std::string>{stem(dir, 4) + ".*"});
  EXPECT_EQ(k.at("missing-file"), std::vector<std::string>{stem(dir, 5) + ".depth.png"});
  ASSERT_TRUE(k.count("bad-image"));
  EXPECT_EQ(k.at("bad-image")[0], stem(dir, 1) + ".depth.png");
  ASSERT_EQ(k.at("bad-pose").size(), 2u);
  EXPECT_EQ(k.at("bad-pose")[0], stem(dir, 6) + ".pose.txt:1");
  EXPECT_EQ(k.at("bad-pose")[1], stem(dir, 7) + ".pose.txt:3");
  // Colour: 0 1 2 5 6 7 (3 repeated, 4 absent); depth: 0 2 6 7 (1 bad, 3 repeated, 5 absent);
  // ground truth: 0 1 2 5 (3 withheld with its stale depth, 6 and 7 bad).
  EXPECT_EQ(r.rgb.size(), 6u);
  EXPECT_EQ(r.depth.size(), 4u);
  ASSERT_EQ(r.gt.size(), 4u);
  EXPECT_EQ(r.gt[3].t_ns, static_cast<int64_t>(std::llround(5e9 / 30.0)));
  // Reported once, however often the log is replayed.
  const size_t n = reader.problems().size();
  reader.rewind();
  read_all(reader);
  EXPECT_EQ(reader.problems().size(), n);
}

TEST(SevenScenes, BadCalibrationFilesNameFileAndLine) {
  const std::string dir = write_folder("7s_calib", 2);
  std::ofstream(dir + "/camera-intrinsics.txt") << "585 0 320\n0 585\n0 0 1\n";
  try {
    drivers::SevenScenesReader r(dir);
    ADD_FAILURE() << "no error";
  } catch (const std::runtime_error& e) {
    EXPECT_EQ(std::string(e.what()),
              dir + "/camera-intrinsics.txt:2: expected 3 numbers per row of the 3x3 camera matrix");
  }
  std::ofstream(dir + "/camera-intrinsics.txt") << "585 0 320\n0 585 240\n0 0 1\n";
  std::ofstream(dir + "/gravity-direction.txt") << "0 1\n";
  drivers::SevenScenesReader r(dir);
  bool named = false;
  for (const auto& p : r.problems())
    named |= p.where == dir + "/gravity-direction.txt" && p.kind == "bad-row";
  EXPECT_TRUE(named);
  EXPECT_THROW(drivers::SevenScenesReader(dir + "/absent"), std::runtime_error);
}

// The real sequence: 500 frames, of which the recorder repeated some.
TEST(SevenScenesReal, First500ReadsWithRepeatsFoundAndDepthRegistered) {
  KESTREL_REQUIRE_SHARED("real-rgbd/7scenes_first500");
  const std::string dir = shared_path("real-rgbd/7scenes_first500");
  const auto log = drivers::open_log(dir);
  ASSERT_EQ(log->format_name(), "7scenes");
  auto& reader = dynamic_cast<drivers::SevenScenesReader&>(*log);
  size_t rgb = 0, depth = 0, gt = 0, d65535 = 0;
  drivers::LogRecord rec;
  while (log->next(rec)) {
    rgb += rec.type == drivers::RecordType::kRgb;
    gt += rec.type == drivers::RecordType::kGroundTruth;
    if (rec.type == drivers::RecordType::kDepth) {
      ++depth;
      const auto* d = reinterpret_cast<const uint16_t*>(rec.image.pixels.data());
      for (int k = 0; k < rec.image.width * rec.image.height; ++k) d65535 += d[k] == 65535;
      EXPECT_EQ(rec.image.width, 640);
    }
  }
  EXPECT_EQ(reader.repeated_colour(), 43u);
  EXPECT_EQ(reader.repeated_depth(), 43u);
  EXPECT_EQ(rgb, 500u - 43u);
  EXPECT_EQ(depth + 43u, 500u);
  EXPECT_EQ(gt + 43u, 500u);
  EXPECT_EQ(d65535, 0u);
}

// Where the depth jumps, the nearer surface's outline should be a colour
// edge. The foreground pixels of the raw depth image's jumps (valid
// neighbours more than 5 % apart) are moved into the colour image with a
// candidate calibration; the score is the mean colour gradient there
// (bilinear) over the image's mean gradient. Sub-pixel and free of the
// registration's rounding, so calibrations can be compared.
double edge_score(const cv::Mat& grad, const cv::Mat& depth, const Rig& rig) {
  const CameraIntrinsics& d = rig.depth_camera.intrinsics;
  const CameraIntrinsics& c = rig.rgb;
  const Mat4d& T = rig.depth_camera.T_CD;
  double on = 0;
  int n = 0;
  auto sample = [&](double u, double v) {
    const int x = static_cast<int>(std::floor(u)), y = static_cast<int>(std::floor(v));
    if (x < 1 || y < 1 || x >= grad.cols - 2 || y >= grad.rows - 2) return -1.0;
    const double a = u - x, b = v - y;
    return (1 - a) * (1 - b) * grad.at<float>(y, x) + a * (1 - b) * grad.at<float>(y, x + 1) +
           (1 - a) * b * grad.at<float>(y + 1, x) + a * b * grad.at<float>(y + 1, x + 1);
  };
  for (int y = 1; y < depth.rows - 1; ++y)
    for (int x = 1; x < depth.cols - 1; ++x) {
      const int z = depth.at<uint16_t>(y, x);
      if (z == 0) continue;
      bool fg = false;
      for (const auto& [dx, dy] : {std::pair{1, 0}, std::pair{-1, 0}, std::pair{0, 1}, std::pair{0, -1}}) {
        const int o = depth.at<uint16_t>(y + dy, x + dx);
        fg |= o != 0 && o > 1.05 * z;
      }
      if (!fg) continue;
      const double zm = 1e-3 * z, px = (x - d.cx) / d.fx * zm, py = (y - d.cy) / d.fy * zm;
      const double qx = T[0] * px + T[1] * py + T[2] * zm + T[3],
                   qy = T[4] * px + T[5] * py + T[6] * zm + T[7],
                   qz = T[8] * px + T[9] * py + T[10] * zm + T[11];
      const double g = sample(c.fx * qx / qz + c.cx, c.fy * qy / qz + c.cy);
      if (g < 0) continue;
      on += g;
      ++n;
    }
  return n > 0 ? on / n / cv::mean(grad)[0] : 0.0;
}

TEST(SevenScenesReal, AssumedCalibrationPutsDepthEdgesOnColourEdges) {
  KESTREL_REQUIRE_SHARED("real-rgbd/7scenes_first500");
  const std::string dir = shared_path("real-rgbd/7scenes_first500");
  CameraIntrinsics depth_k;
  depth_k.width = 640, depth_k.height = 480;
  depth_k.fx = depth_k.fy = 585, depth_k.cx = 320, depth_k.cy = 240;
  const Rig assumed = drivers::SevenScenesReader::default_rig(depth_k);
  struct Candidate {
    std::string name;
    Rig rig;
    double score = 0;
  };
  std::vector<Candidate> cands;
  {
    Rig none = assumed;
    none.rgb.fx = none.rgb.fy = 585;
    none.depth_camera.T_CD = kIdentity4;
    cands.push_back({"unregistered (f 585, no offset)", none});
    none.rgb.fx = none.rgb.fy = 525;
    cands.push_back({"colour f 525, no offset", none});
  }
  for (double f : {505.0, 515.0, 525.0, 545.0, 565.0}) {
    Rig r = assumed;
    r.rgb.fx = r.rgb.fy = f;
    char b[64];
    std::snprintf(b, sizeof b, "colour f %.0f + T_CD%s", f, f == 525 ? " (assumed)" : "");
    cands.push_back({b, r});
  }
  int frames = 0;
  for (int i = 0; i < 500; i += 10, ++frames) {
    char stem[32];
    std::snprintf(stem, sizeof stem, "/frame-%06d", i);
    cv::Mat gray = cv::imread(dir + stem + ".color.jpg", cv::IMREAD_GRAYSCALE), gx, gy, grad;
    cv::Mat depth = cv::imread(dir + stem + ".depth.png", cv::IMREAD_UNCHANGED);
    ASSERT_FALSE(gray.empty());
    ASSERT_EQ(depth.type(), CV_16UC1);
    depth.setTo(0, depth == 65535);
    cv::Sobel(gray, gx, CV_32F, 1, 0);
    cv::Sobel(gray, gy, CV_32F, 0, 1);
    cv::magnitude(gx, gy, grad);
    // Blurred: repeated texture (the chess board) would otherwise reward a wrong offset.
    cv::GaussianBlur(grad, grad, cv::Size(0, 0), 1.5);
    for (Candidate& c : cands) c.score += edge_score(grad, depth, c.rig);
  }
  for (const Candidate& c : cands) std::printf("  %-34s edge score %.3f\n", c.name.c_str(), c.score / frames);
  // Measured: none 1.19, the assumed calibration 1.65, its neighbours lower on both sides of 515-525
  // (docs/datasets.md). The principal point is not refined here: a fit of it and of the focal length
  // raised this score to 2.05 but not the tracking accuracy (docs/real-imagery.md).
  EXPECT_GT(cands[4].score, 1.25 * cands[0].score) << "the assumed registration must beat none";
  EXPECT_GT(cands[4].score, cands[2].score) << "the colour focal length 525 must beat 505";
  EXPECT_GT(cands[4].score, cands[6].score) << "the colour focal length 525 must beat 565";
}

}  // namespace
}  // namespace kestrel::test

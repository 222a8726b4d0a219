// `kestrel sim --images`: real images with an IMU synthesised along their
// ground truth. A 7-Scenes-style folder rendered from a known flight (in a
// world turned away from gravity, as 7-Scenes' is) must give back that
// flight's IMU; the real 7-Scenes sequence, when present, gets a whole log.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/tools/simulator.hpp"
#include "test_data.hpp"

namespace kt = kestrel::tools;
using kestrel::drivers::RecordType;

namespace kestrel::test {
namespace {

class Sink final : public kt::SimSink {
 public:
  Rig rig;
  std::vector<ImuSample> samples;
  std::vector<GroundTruthPose> gt;
  int rgb = 0, depth = 0;
  std::vector<int64_t> times;
  void begin(const Rig& r) override { rig = r; }
  void imu(const ImuSample& s) override {
    samples.push_back(s);
    times.push_back(s.t_ns);
  }
  void image(RecordType type, int64_t t_ns, uint32_t, const ImageView&) override {
    (type == RecordType::kRgb ? rgb : depth) += 1;
    times.push_back(t_ns);
  }
  void ground_truth(const GroundTruthPose& g) override {
    gt.push_back(g);
    times.push_back(g.t_ns);
  }
  void event(const Event& e) override { times.push_back(e.t_ns); }
  void end() override {}
};

// A figure-8 rendered at 30 Hz into 7-Scenes files, its poses written in a
// world W' = R_WpW W whose "down" is gravity-direction.txt.
std::string write_sevenscenes_flight(const Eigen::Matrix3d& R_WpW, int frames) {
  const std::string dir = temp_dir("sim_images_7s");
  auto traj = kt::make_scenario("figure8", frames / 30.0 + 0.5);
  Rig rig = kt::default_sim_rig(160, 120);
  rig.rgb.distortion = DistortionModel::kNone;
  rig.T_BC = kIdentity4;  // the ground truth is the camera's, as 7-Scenes' is
  const kt::Scene scene = kt::Scene::build(*traj, Eigen::Isometry3d::Identity(), 5);
  kt::RenderOptions ro;
  ro.depth_noise = false;
  ro.image_noise_sigma = 0;
  const kt::Renderer renderer(scene, rig.rgb, rig.depth, ro);
  std::vector<uint8_t> rgb(160 * 120 * 3);
  std::vector<uint16_t> depth(160 * 120);
  for (int i = 0; i < frames; ++i) {
    const kt::TrajectoryState s = traj->state(i / 30.0);
    Eigen::Isometry3d T = Eigen::Translation3d(s.p_WB) * s.q_WB;
    renderer.render(T, static_cast<uint64_t>(i), rgb.data(), depth.data());
    char stem[64];
    std::snprintf(stem, sizeof stem, "/frame-%06d", i);
    cv::Mat c(120, 160, CV_8UC3, rgb.data()), bgr;
    cv::cvtColor(c, bgr, cv::COLOR_RGB2BGR);
    cv::imwrite(dir + stem + ".color.png", bgr);
    cv::imwrite(dir + stem + ".depth.png", cv::Mat(120, 160, CV_16UC1, depth.data()));
    const Eigen::Isometry3d Tp = Eigen::Isometry3d(R_WpW) * T;
    std::ofstream f(dir + stem + ".pose.txt");
    f.precision(17);
    for (int r = 0; r < 4; ++r)
      f << Tp.matrix()(r, 0) << " " << Tp.matrix()(r, 1) << " " << Tp.matrix()(r, 2) << " "
        << Tp.matrix()(r, 3) << "\n";
  }
  const Eigen::Vector3d g = R_WpW * Eigen::Vector3d(0, 0, -1);
  std::ofstream(dir + "/gravity-direction.txt") << g.x() << " " << g.y() << " " << g.z() << "\n";
  std::ofstream(dir + "/kestrel_rig.yaml") << drivers::rig_to_yaml(rig);
  return dir;
}

TEST(SimImages, SynthesisedImuFollowsTheRecordingsGroundTruth) {
  const Eigen::Matrix3d R_WpW =
      Eigen::AngleAxisd(1.2, Eigen::Vector3d(1, 0.3, 0).normalized()).toRotationMatrix();
  const std::string dir = write_sevenscenes_flight(R_WpW, 150);
  kt::SimOptions o;
  o.images_path = dir;
  o.noise = false;
  o.knot_spacing_s = 0.05;
  Sink sink;
  const kt::SimSummary sum = kt::run_simulation(o, sink);
  EXPECT_TRUE(sum.real_images);
  EXPECT_EQ(sink.rgb, 150);
  EXPECT_EQ(sink.depth, 150);
  EXPECT_EQ(sink.gt.size(), 150u);
  EXPECT_NEAR(static_cast<double>(sink.samples.size()), 149 / 30.0 * 400, 2);
  EXPECT_EQ(sink.rig.imu_rate_hz, 400.0);
  // The rig carries the model the IMU was written with: ideal here, as the built-in scenarios' --no-noise.
  EXPECT_EQ(sink.rig.imu.gyro_noise_density_rad_s_sqrthz, 0);
  EXPECT_TRUE(std::is_sorted(sink.times.begin(), sink.times.end()));
  EXPECT_LT(sum.spline_rms_position_residual_m, 0.002);
  // The levelled ground truth is the flight itself, and the IMU is the flight's.
  auto truth = kt::make_scenario("figure8", 150 / 30.0 + 0.5);
  double se_g = 0, se_a = 0;
  int n = 0;
  for (const ImuSample& s : sink.samples) {
    const double t = 1e-9 * static_cast<double>(s.t_ns);
    if (t < 0.3 || t > 4.6) continue;  // the spline's ends are less constrained
    Eigen::Vector3d g, a;
    kt::true_imu(truth->state(t), sink.rig.gravity_mps2, g, a);
    se_g += (Eigen::Vector3d(s.gyro_rps.data()) - g).squaredNorm();
    se_a += (Eigen::Vector3d(s.acc_mps2.data()) - a).squaredNorm();
    ++n;
  }
  const double rms_g = std::sqrt(se_g / n), rms_a = std::sqrt(se_a / n);
  std::printf("synthesised vs true IMU over %d samples: gyro %.4f rad/s, acc %.3f m/s^2 RMS\n", n, rms_g,
              rms_a);
  EXPECT_LT(rms_g, 0.02);
  EXPECT_LT(rms_a, 0.15);
}

TEST(SimImages, BadInputIsAUsageError) {
  kt::SimOptions o;
  o.images_path = "/nonexistent/folder";
  Sink sink;
  EXPECT_THROW(kt::run_simulation(o, sink), kt::SimOptionError);
  const std::string dir = temp_dir("sim_images_nogt");
  o.images_path = dir;
  cv::imwrite(dir + "/frame-000000.color.png", cv::Mat(8, 8, CV_8UC3, cv::Scalar(1, 2, 3)));
  std::ofstream(dir + "/frame-000000.pose.txt") << "not a pose\n";
  try {
    kt::run_simulation(o, sink);
    ADD_FAILURE() << "no error";
  } catch (const kt::SimOptionError& e) {
    EXPECT_NE(std::string(e.what()).find("ground-truth poses"), std::string::npos) << e.what();
  }
}

TEST(SimImagesReal, SevenScenesGetsAnImuAlongItsGroundTruth) {
  KESTREL_REQUIRE_SHARED("real-rgbd/7scenes_first500");
  kt::SimOptions o;
  o.images_path = shared_path("real-rgbd/7scenes_first500");
  Sink sink;
  const kt::SimSummary sum = kt::run_simulation(o, sink);
  std::printf("%s", kt::format_summary(sum).c_str());
  EXPECT_EQ(sink.rgb, 457);
  EXPECT_EQ(sink.gt.size(), 457u);
  EXPECT_GT(sink.samples.size(), 6500u);
  // KinectFusion's poses are good to millimetres; the spline stays within that.
  EXPECT_LT(sum.spline_rms_position_residual_m, 0.005);
  EXPECT_EQ(sum.imu_saturated, 0u);
  EXPECT_GT(sink.rig.imu.gyro_noise_density_rad_s_sqrthz, 0);  // the BMX055's, as written
}

}  // namespace
}  // namespace kestrel::test

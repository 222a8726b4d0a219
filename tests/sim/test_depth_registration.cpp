// Depth registration (drivers/depth) against a simulated two-camera rig: the
// simulator renders the depth camera's view and, as the truth, the colour
// camera's own depth; registering the first must give the second.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "kestrel/drivers/depth_registration.hpp"
#include "kestrel/tools/simulator.hpp"

namespace kestrel::test {
namespace {

using tools::to_isometry;

// A Kinect v1-like pair: the colour camera of the simulator's rig (mild
// radtan distortion) and an IR camera with a longer focal length, 2.5 cm to
// the side, turned by half a degree.
struct TwoCameraRig {
  Rig rig;
  Eigen::Isometry3d T_CD = Eigen::Isometry3d::Identity();
};

TwoCameraRig kinect_like(double depth_fx = 585.0) {
  TwoCameraRig t;
  t.rig = tools::default_sim_rig(320, 240, 30.0, 400.0);
  CameraIntrinsics d;
  d.width = 320, d.height = 240;
  d.fx = d.fy = depth_fx / 2;
  d.cx = 159.5, d.cy = 119.5;
  d.distortion = DistortionModel::kRadTan;
  d.dist = {-0.02, 0.01, 0, 0, 0};
  t.T_CD.linear() = Eigen::AngleAxisd(0.009, Eigen::Vector3d(0.3, 1, 0.2).normalized()).toRotationMatrix();
  t.T_CD.translation() = Eigen::Vector3d(-0.025, 0.001, 0.002);
  t.rig.depth_camera.present = true;
  t.rig.depth_camera.intrinsics = d;
  t.rig.depth_camera.T_CD = tools::to_mat4(t.T_CD);
  return t;
}

struct Agreement {
  double agree = 0;     // share of truth pixels (both valid) within max(5 mm, 1 %)
  double coverage = 0;  // share of valid truth pixels that got a depth
};

Agreement compare(const std::vector<uint16_t>& got, const std::vector<uint16_t>& truth) {
  int both = 0, ok = 0, valid_truth = 0, covered = 0;
  for (size_t k = 0; k < truth.size(); ++k) {
    if (truth[k] == 0) continue;
    ++valid_truth;
    if (got[k] == 0) continue;
    ++covered;
    ++both;
    const double tol = std::max(5.0, 0.01 * truth[k]);
    ok += std::abs(static_cast<double>(got[k]) - truth[k]) <= tol;
  }
  return {both > 0 ? static_cast<double>(ok) / both : 0.0,
          valid_truth > 0 ? static_cast<double>(covered) / valid_truth : 0.0};
}

class DepthRegistrationSim : public ::testing::Test {
 protected:
  void run(const TwoCameraRig& t, Agreement* registered, Agreement* raw) {
    auto traj = tools::make_scenario("figure8", 20.0);
    const tools::Scene scene = tools::Scene::build(*traj, to_isometry(t.rig.T_BC), 3);
    tools::RenderOptions ro;
    ro.depth_noise = false;
    ro.dropout_fraction = 0.0;
    ro.image_noise_sigma = 0.0;
    const tools::Renderer colour(scene, t.rig.rgb, t.rig.depth, ro);
    const tools::Renderer depth_cam(scene, t.rig.depth_camera.intrinsics, t.rig.depth, ro);
    const drivers::DepthRegistration reg(t.rig.depth_camera, t.rig.rgb, t.rig.depth.scale_m_per_unit);
    const int W = t.rig.rgb.width, H = t.rig.rgb.height;
    const int dW = t.rig.depth_camera.intrinsics.width, dH = t.rig.depth_camera.intrinsics.height;
    std::vector<uint8_t> rgb(static_cast<size_t>(std::max(W * H, dW * dH)) * 3);
    std::vector<uint16_t> truth(static_cast<size_t>(W) * H), raw_d(static_cast<size_t>(dW) * dH),
        out(static_cast<size_t>(W) * H);
    double agree = 0, cover = 0, raw_agree = 0;
    int n = 0;
    for (double ts = 1.0; ts < 20.0; ts += 3.0, ++n) {
      const tools::TrajectoryState s = traj->state(ts);
      const Eigen::Isometry3d T_WC = Eigen::Translation3d(s.p_WB) * s.q_WB * to_isometry(t.rig.T_BC);
      colour.render(T_WC, static_cast<uint64_t>(n), rgb.data(), truth.data());
      depth_cam.render(T_WC * t.T_CD, static_cast<uint64_t>(n), rgb.data(), raw_d.data());
      drivers::RegistrationStats st;
      ASSERT_TRUE(reg.register_into(
          ImageView{dW, dH, dW * 2, PixelFormat::kDepthU16, reinterpret_cast<const uint8_t*>(raw_d.data())},
          out.data(), W * 2, &st));
      EXPECT_GT(st.projected, st.valid_in / 2);
      const Agreement a = compare(out, truth);
      agree += a.agree;
      cover += a.coverage;
      if (dW == W && dH == H) raw_agree += compare(raw_d, truth).agree;
    }
    *registered = {agree / n, cover / n};
    *raw = {raw_agree / n, 0};
  }
};

TEST_F(DepthRegistrationSim, RegisteredDepthMatchesTheColourCamerasOwnDepth) {
  const TwoCameraRig t = kinect_like();
  Agreement reg, raw;
  run(t, &reg, &raw);
  // Forward projection lands every point within half a pixel: the depth
  // agrees except on the silhouettes, where half a pixel is a surface away.
  EXPECT_GT(reg.agree, 0.97);
  // The colour camera's wider view has a border the depth camera never sees.
  EXPECT_GT(reg.coverage, 0.80);
  // Taking the depth camera's image as registered (what an unregistered
  // reader does) disagrees on a large share of the image.
  EXPECT_LT(raw.agree, 0.80);
  std::printf("registered: %.1f %% agree, %.1f %% covered; unregistered: %.1f %% agree\n", 100 * reg.agree,
              100 * reg.coverage, 100 * raw.agree);
}

TEST_F(DepthRegistrationSim, AFinerColourGridIsFilledWithoutHoles) {
  // Depth focal length below colour's: one depth pixel covers two colour pixels.
  const TwoCameraRig t = kinect_like(420.0);
  const drivers::DepthRegistration reg(t.rig.depth_camera, t.rig.rgb, t.rig.depth.scale_m_per_unit);
  EXPECT_EQ(reg.footprint_px(), 2);
  Agreement a, raw;
  run(t, &a, &raw);
  EXPECT_GT(a.agree, 0.93);
  EXPECT_GT(a.coverage, 0.90);
}

// Analytic: a fronto-parallel wall at 2 m seen by a depth camera 10 cm to the
// colour camera's left: the wall stays at 2 m and shifts by f * b / z pixels.
TEST(DepthRegistration, PlaneShiftsByTheDisparityAndNearerPointsWin) {
  DepthCamera dc;
  dc.present = true;
  dc.intrinsics.width = 40, dc.intrinsics.height = 30;
  dc.intrinsics.fx = dc.intrinsics.fy = 40;
  dc.intrinsics.cx = 19.5, dc.intrinsics.cy = 14.5;
  dc.T_CD[3] = -0.1;  // p_C = p_D - 0.1 x
  const drivers::DepthRegistration reg(dc, dc.intrinsics, 0.001);
  std::vector<uint16_t> d(40 * 30, 2000), out(40 * 30, 7);
  // A post at 1 m in columns 20..21 of the depth image.
  for (int y = 0; y < 30; ++y) d[y * 40 + 20] = d[y * 40 + 21] = 1000;
  drivers::RegistrationStats st;
  ASSERT_TRUE(reg.register_into(
      ImageView{40, 30, 80, PixelFormat::kDepthU16, reinterpret_cast<const uint8_t*>(d.data())}, out.data(),
      80, &st));
  EXPECT_EQ(st.valid_in, 1200);
  // The wall moves 40 * 0.1 / 2 = 2 px to the left: the last two columns see no depth.
  const int y = 15;
  EXPECT_EQ(out[y * 40 + 39], 0);
  EXPECT_EQ(out[y * 40 + 38], 0);
  EXPECT_EQ(out[y * 40 + 10], 2000);
  // The post at 1 m moves 4 px (columns 16, 17) and hides the wall there.
  EXPECT_EQ(out[y * 40 + 16], 1000);
  EXPECT_EQ(out[y * 40 + 17], 1000);
  EXPECT_GT(st.occluded, 0);
  // Mismatched input is refused and leaves the output alone.
  std::vector<uint16_t> keep = out;
  EXPECT_FALSE(reg.register_into(
      ImageView{30, 30, 60, PixelFormat::kDepthU16, reinterpret_cast<const uint8_t*>(d.data())}, out.data(),
      80));
  EXPECT_EQ(out, keep);
  dc.present = false;
  EXPECT_THROW(drivers::DepthRegistration(dc, dc.intrinsics, 0.001), std::invalid_argument);
}

}  // namespace
}  // namespace kestrel::test

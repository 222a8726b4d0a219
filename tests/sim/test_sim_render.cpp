// The scene and the ray caster: exact depth, full coverage, texture corners,
// clearance from the path, the depth error model and thread independence.
#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

#include "kestrel/tools/simulator.hpp"

namespace kt = kestrel::tools;
using Eigen::Isometry3d;
using Eigen::Vector3d;

namespace {

kestrel::CameraIntrinsics camera(int w, int h) { return kt::default_sim_rig(w, h).rgb; }

// Camera at p looking along `forward` (horizontal unless pitched), image y down.
Isometry3d look(const Vector3d& p, double yaw, double pitch_down = 0.0) {
  const Eigen::Matrix3d R_WB =
      (Eigen::AngleAxisd(yaw, Vector3d::UnitZ()) * Eigen::AngleAxisd(pitch_down, Vector3d::UnitY()))
          .toRotationMatrix();
  Eigen::Matrix3d R_BC;
  R_BC << 0, 0, 1, -1, 0, 0, 0, -1, 0;  // camera z forward = body x
  Isometry3d T = Isometry3d::Identity();
  T.linear() = R_WB * R_BC;
  T.translation() = p;
  return T;
}

kt::RenderOptions clean(int threads = 2) {
  kt::RenderOptions o;
  o.threads = threads;
  o.depth_noise = false;
  o.dropout_fraction = 0.0;
  o.image_noise_sigma = 0.0;
  return o;
}

struct Images {
  std::vector<uint8_t> rgb;
  std::vector<uint16_t> depth;
};

Images render(const kt::Renderer& r, const Isometry3d& T_WC, uint64_t frame = 0) {
  const auto& c = r.camera();
  Images im;
  im.rgb.resize(static_cast<size_t>(c.width) * c.height * 3);
  im.depth.resize(static_cast<size_t>(c.width) * c.height);
  r.render(T_WC, frame, im.rgb.data(), im.depth.data());
  return im;
}

kestrel::DepthModel depth_model() { return kestrel::DepthModel{}; }

}  // namespace

TEST(SimRender, DistortionRoundTripsThroughThePixelRayTable) {
  const auto cam = camera(160, 120);
  const kt::Scene scene;
  const kt::Renderer r(scene, cam, depth_model(), clean());
  double worst = 0;
  for (int v = 0; v < cam.height; v += 3)
    for (int u = 0; u < cam.width; u += 3)
      worst = std::max(worst, (kt::project(cam, r.pixel_ray(u, v)) - Eigen::Vector2d(u, v)).norm());
  EXPECT_LT(worst, 1e-3);
  // The principal point looks straight ahead.
  const auto c = kt::undistort_normalized(cam, Eigen::Vector2d::Zero());
  EXPECT_LT(c.norm(), 1e-12);
}

TEST(SimRender, WallAtKnownDistanceReadsExactDepthEverywhere) {
  kt::Scene scene;
  scene.room = Eigen::AlignedBox3d(Vector3d(-3, -3, 0), Vector3d(3, 3, 3));
  const auto cam = camera(640, 480);
  const kt::Renderer r(scene, cam, depth_model(), clean());
  // From (0, 0, 1.5) looking at the x = 3 wall: the whole view is that wall,
  // and registered depth (z in the camera) is 3 m at every pixel.
  const Images im = render(r, look(Vector3d(0, 0, 1.5), 0.0));
  const size_t centre =
      static_cast<size_t>(std::lround(cam.cy)) * cam.width + static_cast<size_t>(std::lround(cam.cx));
  EXPECT_NEAR(im.depth[centre], 3000, 1);
  int off = 0;
  for (uint16_t d : im.depth) off += std::abs(static_cast<int>(d) - 3000) > 1;
  EXPECT_EQ(off, 0);
  // 1.2 m from the wall, turned 20 degrees: the centre ray's depth is still
  // the wall distance along the optical axis, 1.2 / cos(20 deg).
  const Images im2 = render(r, look(Vector3d(1.8, 0, 1.5), 20.0 * M_PI / 180.0));
  EXPECT_NEAR(im2.depth[centre], 1200.0 / std::cos(20.0 * M_PI / 180.0), 1.0);
  EXPECT_NEAR(r.cast(Vector3d(0, 0, 1.5), Vector3d(1, 0, 0)), 3.0, 1e-5);
}

TEST(SimRender, GrazingAndOutOfRangeSurfacesHaveNoDepth) {
  kt::Scene scene;
  scene.room = Eigen::AlignedBox3d(Vector3d(-8, -8, 0), Vector3d(8, 8, 3));
  const auto cam = camera(160, 120);
  const kt::Renderer r(scene, cam, depth_model(), clean());
  const size_t centre =
      static_cast<size_t>(std::lround(cam.cy)) * cam.width + static_cast<size_t>(std::lround(cam.cx));
  // Floor 0.5 m below, seen 30 degrees down: incidence 60 deg, depth about
  // 1 m (exactly: where the centre pixel's own ray meets the floor).
  const Isometry3d down30 = look(Vector3d(0, 0, 0.5), 0, 30 * M_PI / 180);
  const Vector3d ray_C =
      r.pixel_ray(static_cast<int>(std::lround(cam.cx)), static_cast<int>(std::lround(cam.cy)));
  const double expect_z = -0.5 / (down30.linear() * ray_C).z();  // ray has z = 1: t is depth
  EXPECT_NEAR(expect_z, 1.0, 0.02);
  EXPECT_NEAR(render(r, down30).depth[centre], 1000 * expect_z, 1);
  // 10 degrees down: incidence 80 deg > 75: no depth.
  EXPECT_EQ(render(r, look(Vector3d(0, 0, 0.5), 0, 10 * M_PI / 180)).depth[centre], 0);
  // Wall 7 m away: beyond the 6 m range.
  EXPECT_EQ(render(r, look(Vector3d(1, 0, 1.5), 0)).depth[centre], 0);
}

TEST(SimRender, SceneKeepsClearOfEveryScenarioPath) {
  const Isometry3d T_BC = kt::to_isometry(kt::default_sim_rig().T_BC);
  for (const std::string& name : kt::scenario_names()) {
    const auto tr = kt::make_scenario(name, 60);
    const kt::Scene scene = kt::Scene::build(*tr, T_BC, 9);
    EXPECT_GE(scene.boxes.size() + scene.cylinders.size(), 4u) << name;
    double closest = 1e9, wall = 1e9;
    for (double t = 0; t <= tr->duration_s(); t += 0.005) {
      const auto s = tr->state(t);
      const Isometry3d T_WB = Eigen::Translation3d(s.p_WB) * s.q_WB;
      for (const Vector3d& p : {s.p_WB, Vector3d(T_WB * T_BC.translation())}) {
        closest = std::min(closest, scene.clutter_distance(p));
        const Vector3d lo = p - scene.room.min(), hi = scene.room.max() - p;
        wall = std::min(wall, std::min(lo.minCoeff(), hi.minCoeff()));
        // Every wall within 5 m horizontally, so the camera sees texture in range.
        // (The room is sized from 50 Hz samples, these are at 200 Hz.)
        // (`hard` sweeps 6 m through a hall on purpose: walls beyond the depth range.)
        if (name == "hard") continue;
        EXPECT_LE(std::max(lo.x(), hi.x()), 5.01) << name;
        EXPECT_LE(std::max(lo.y(), hi.y()), 5.01) << name;
      }
    }
    EXPECT_GE(closest, 0.5) << name;
    EXPECT_GT(wall, 0.2) << name;
  }
}

TEST(SimRender, FullDepthCoverageAndCornerRichTexture) {
  const auto tr = kt::make_scenario("hover", 20);
  const auto rig = kt::default_sim_rig(640, 480);
  const Isometry3d T_BC = kt::to_isometry(rig.T_BC);
  const kt::Scene scene = kt::Scene::build(*tr, T_BC, 1);
  kt::Scene empty_room = scene;
  empty_room.boxes.clear();
  empty_room.cylinders.clear();
  const kt::Renderer bare(empty_room, rig.rgb, rig.depth, clean());
  const kt::Renderer full(scene, rig.rgb, rig.depth, clean());
  for (double t : {0.0, 7.0, 15.0}) {
    const auto s = tr->state(t);
    const Isometry3d T_WC = Eigen::Translation3d(s.p_WB) * s.q_WB * T_BC;
    // The room alone: every pixel in range with valid depth.
    const Images im = render(bare, T_WC);
    EXPECT_EQ(std::count(im.depth.begin(), im.depth.end(), 0), 0) << "t=" << t;
    // With clutter only surfaces seen edge-on lose depth.
    const Images im2 = render(full, T_WC);
    EXPECT_LT(std::count(im2.depth.begin(), im2.depth.end(), 0), static_cast<long>(im2.depth.size() / 50));

    cv::Mat rgb(rig.rgb.height, rig.rgb.width, CV_8UC3, const_cast<uint8_t*>(im2.rgb.data())), gray;
    cv::cvtColor(rgb, gray, cv::COLOR_RGB2GRAY);
    std::vector<cv::KeyPoint> kps;
    cv::FAST(gray, kps, 20, true);
    EXPECT_GT(kps.size(), 200u) << "t=" << t;
    std::printf("t=%.0f: %zu FAST corners\n", t, kps.size());
  }
}

TEST(SimRender, DepthNoiseAndDropoutsFollowTheModel) {
  kt::Scene scene;
  scene.room = Eigen::AlignedBox3d(Vector3d(-3, -3, 0), Vector3d(3, 3, 3));
  const auto cam = camera(320, 240);
  kt::RenderOptions o = clean();
  o.depth_noise = true;
  o.dropout_fraction = 0.01;
  const kestrel::DepthModel dm = depth_model();
  const kt::Renderer r(scene, cam, dm, o);
  const Images im = render(r, look(Vector3d(0, 0, 1.5), 0.0), 3);
  double n = 0, sum = 0, sum2 = 0;
  size_t zeros = 0;
  for (uint16_t d : im.depth) {
    if (d == 0) {
      ++zeros;
      continue;
    }
    n += 1;
    sum += d;
    sum2 += static_cast<double>(d) * d;
  }
  const double mean = sum / n, sd = std::sqrt(sum2 / n - mean * mean);
  EXPECT_NEAR(mean, 3000.0, 1.0);
  EXPECT_NEAR(sd, 1000.0 * dm.sigma_coeff_per_m * 9.0, 0.1 * 1000.0 * dm.sigma_coeff_per_m * 9.0);
  const double lost = static_cast<double>(zeros) / im.depth.size();
  EXPECT_GT(lost, 0.005);
  EXPECT_LT(lost, 0.02);
}

TEST(SimRender, SameImageWhateverTheThreadCount) {
  const auto tr = kt::make_scenario("figure8", 20);
  const auto rig = kt::default_sim_rig(160, 120);
  const Isometry3d T_BC = kt::to_isometry(rig.T_BC);
  const kt::Scene scene = kt::Scene::build(*tr, T_BC, 4);
  kt::RenderOptions o;
  o.seed = 4;
  o.threads = 1;
  const kt::Renderer one(scene, rig.rgb, rig.depth, o);
  o.threads = 3;
  const kt::Renderer three(scene, rig.rgb, rig.depth, o);
  const auto s = tr->state(9.0);
  const Isometry3d T_WC = Eigen::Translation3d(s.p_WB) * s.q_WB * T_BC;
  const Images a = render(one, T_WC, 17), b = render(three, T_WC, 17), c = render(one, T_WC, 18);
  EXPECT_EQ(a.rgb, b.rgb);
  EXPECT_EQ(a.depth, b.depth);
  EXPECT_NE(a.depth, c.depth);  // the next frame has fresh noise
}

#include <gtest/gtest.h>

#include "kestrel/core/camera.hpp"

using kestrel::core::PinholeCamera;

namespace {
kestrel::CameraIntrinsics sim_like() {
  kestrel::CameraIntrinsics in;
  in.width = 640;
  in.height = 480;
  in.fx = in.fy = 525;
  in.cx = 319.5;
  in.cy = 239.5;
  in.distortion = kestrel::DistortionModel::kRadTan;
  in.dist = {0.04, -0.03, 0.0005, -0.0003, 0};
  return in;
}
}  // namespace

TEST(PinholeCamera, UndistortInvertsDistortAcrossTheImage) {
  const PinholeCamera cam(sim_like());
  double worst = 0;
  for (double u = 0; u <= 640; u += 40) {
    for (double v = 0; v <= 480; v += 40) {
      const Eigen::Vector2d xn = cam.pixel_to_normalized({u, v});
      const Eigen::Vector2d back = cam.distort_normalized_to_pixel(xn);
      worst = std::max(worst, (back - Eigen::Vector2d(u, v)).norm());
    }
  }
  EXPECT_LT(worst, 1e-6);
}

TEST(PinholeCamera, BackProjectionLandsOnTheRayAtTheDepth) {
  const PinholeCamera cam(sim_like());
  const Eigen::Vector3d p_C(0.7, -0.4, 2.5);
  const Eigen::Vector2d uv = cam.distort_normalized_to_pixel(p_C.head<2>() / p_C.z());
  EXPECT_LT((cam.back_project(uv, 2.5) - p_C).norm(), 1e-9);
  EXPECT_LT((cam.undistort_pixel(uv) - cam.project_undistorted(p_C)).norm(), 1e-8);
}

TEST(PinholeCamera, DistortionMovesCornersOutward) {
  // k1 > 0: a point near the corner lands further out than the ideal pinhole says.
  const PinholeCamera cam(sim_like());
  const Eigen::Vector2d xn(0.55, 0.42);
  const Eigen::Vector2d d = cam.distort_normalized_to_pixel(xn);
  const Eigen::Vector2d ideal(525 * 0.55 + 319.5, 525 * 0.42 + 239.5);
  EXPECT_GT((d - Eigen::Vector2d(319.5, 239.5)).norm(), (ideal - Eigen::Vector2d(319.5, 239.5)).norm());
}

TEST(PinholeCamera, RejectsFisheye) {
  auto in = sim_like();
  in.distortion = kestrel::DistortionModel::kEquidistant;
  EXPECT_THROW(PinholeCamera{in}, std::invalid_argument);
}

// Surface verification of loop candidates (core/loop/surface_alignment.hpp)
// and the depth grid it works on (core/geometry/depth_grid.hpp): grids
// ray-cast from a box room with a crate in it, seen from two poses whose map
// poses differ from the truth by a known drift.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <limits>
#include <vector>

#include "depth_render.hpp"
#include "kestrel/core/depth_grid.hpp"
#include "kestrel/core/surface_alignment.hpp"

namespace {

using kestrel::core::DepthGridSampler;
using kestrel::core::DepthGridShape;
using kestrel::core::PinholeK;
using kestrel::core::SurfaceAligner;
using kestrel::core::SurfaceAlignOptions;
using kestrel::core::SurfaceFit;

using kestrel::map_test::Box;
using kestrel::map_test::camera;
using kestrel::map_test::render;

DepthGridShape shape() { return DepthGridShape::make(64, PinholeK{525, 525, 319.5, 239.5}, 640, 480); }

Eigen::Isometry3d drift(double yaw, const Eigen::Vector3d& t) {
  Eigen::Isometry3d D = Eigen::Isometry3d::Identity();
  D.linear() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  D.translation() = t;
  return D;
}

SurfaceAligner aligner() {
  SurfaceAligner al;
  al.set_shape(shape(), 0.0025);
  return al;
}

const Box kRoom{{-3, -2.5, 0}, {3.5, 3, 3}};
const std::vector<Box> kCrates{{{1.5, -0.5, 0}, {2.2, 0.4, 0.8}}, {{2.0, 1.2, 0}, {2.6, 1.8, 1.6}}};
// The two views of most cases: the query a metre closer than the candidate, turned 14 degrees.
const Eigen::Isometry3d kCandidate = camera({-1.0, 0.2, 1.4}, 0.1);
const Eigen::Isometry3d kQuery = camera({0.2, -0.3, 1.2}, 0.35);

TEST(SurfaceAlignment, RecoversTheDriftBetweenTwoViewsOfARoom) {
  const DepthGridShape s = shape();
  SurfaceAligner al = aligner();
  const Eigen::Isometry3d &T_c = kCandidate, &T_q = kQuery;
  const std::vector<uint16_t> zc = render(s, T_c, kRoom, kCrates), zq = render(s, T_q, kRoom, kCrates);
  const Eigen::Isometry3d D = drift(0.02, {0.06, -0.04, 0.02});
  const SurfaceFit f = al.align(zq.data(), D * T_q, zc.data(), T_c, SurfaceAlignOptions{});
  ASSERT_TRUE(f.ok) << f.failed << " overlap " << f.overlap << " inliers " << f.inlier_share << " obs "
                    << f.observability;
  const Eigen::Isometry3d E = f.correction * D;  // identity when the correction undoes the drift
  std::printf("landed %.2f of %d cells, inliers %.2f, rms %.1f mm, observability %.3f, left %.2f mm\n",
              f.overlap, f.query_cells, f.inlier_share, 1e3 * f.rms_m, f.observability,
              1e3 * E.translation().norm());
  EXPECT_LT(E.translation().norm(), 0.005);
  EXPECT_LT(std::abs(Eigen::AngleAxisd(E.linear()).angle()), 0.002);
  EXPECT_GT(f.overlap, 0.5);
  EXPECT_GT(f.observability, 0.02);
  // The covariance is a covariance, and it is not the noise of thousands of independent cells.
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix4d> eig(f.cov);
  EXPECT_GT(eig.eigenvalues()(0), 0.0);
  EXPECT_GT(std::sqrt(f.cov(1, 1)), 1e-4);
}

TEST(SurfaceAlignment, OneWallLeavesADirectionFreeAndIsRefused) {
  const DepthGridShape s = shape();
  SurfaceAligner al = aligner();
  // Close to a wall, looking at it: nothing but the wall in view.
  const Eigen::Isometry3d T_c = camera({2.5, 0.0, 1.5}, 0.0);
  const Eigen::Isometry3d T_q = camera({2.3, 0.1, 1.5}, 0.05);
  const std::vector<uint16_t> zc = render(s, T_c, kRoom, {}), zq = render(s, T_q, kRoom, {});
  const SurfaceFit f =
      al.align(zq.data(), drift(0.0, {0, 0.05, 0}) * T_q, zc.data(), T_c, SurfaceAlignOptions{});
  EXPECT_FALSE(f.ok);
  EXPECT_STREQ(f.failed, "observability");
  EXPECT_LT(f.observability, 0.02);
}

// The query keyframe sees one wall only (refused alone, as above); its
// neighbour and the candidate's see the crates. Moved together, the views
// constrain every direction, and the drift the two query views share comes out.
TEST(SurfaceAlignment, NeighbouringKeyframesConstrainWhatOneWallLeavesFree) {
  const DepthGridShape s = shape();
  SurfaceAligner al = aligner();
  const Eigen::Isometry3d T_q0 = camera({2.3, 0.1, 1.5}, 0.05), T_c0 = camera({2.5, 0.0, 1.5}, 0.0);
  const Eigen::Isometry3d &T_q1 = kQuery, &T_c1 = kCandidate;
  const std::vector<uint16_t> zq0 = render(s, T_q0, kRoom, kCrates), zq1 = render(s, T_q1, kRoom, kCrates);
  const std::vector<uint16_t> zc0 = render(s, T_c0, kRoom, kCrates), zc1 = render(s, T_c1, kRoom, kCrates);
  const Eigen::Isometry3d D = drift(0.015, {0.05, 0.06, -0.02});
  const SurfaceFit alone = al.align(zq0.data(), D * T_q0, zc0.data(), T_c0, SurfaceAlignOptions{});
  EXPECT_FALSE(alone.ok);
  EXPECT_STREQ(alone.failed, "observability");

  kestrel::core::SurfaceView q[2], c[2];
  q[0].z_mm = zq0.data();
  q[0].T_MC = D * T_q0;
  q[1].z_mm = zq1.data();
  q[1].T_MC = D * T_q1;
  c[0].z_mm = zc0.data();
  c[0].T_MC = T_c0;
  c[1].z_mm = zc1.data();
  c[1].T_MC = T_c1;
  const SurfaceFit f = al.align(q, 2, c, 2, SurfaceAlignOptions{});
  ASSERT_TRUE(f.ok) << f.failed << " overlap " << f.overlap << " inliers " << f.inlier_share << " obs "
                    << f.observability;
  const Eigen::Isometry3d E = f.correction * D;
  std::printf("two views a side: observability %.3f (one: %.4f), left %.2f mm\n", f.observability,
              alone.observability, 1e3 * E.translation().norm());
  EXPECT_LT(E.translation().norm(), 0.005);
  EXPECT_LT(std::abs(Eigen::AngleAxisd(E.linear()).angle()), 0.002);
  EXPECT_GT(f.observability, 0.02);
  // Alone, the query sees the crates only through its neighbour: the
  // candidate's wall view does not need to.
  const SurfaceFit one_side = al.align(q, 2, c, 1, SurfaceAlignOptions{});
  EXPECT_GT(f.overlap, one_side.overlap);
}

TEST(SurfaceAlignment, AnotherPlaceWithTheSameShapeIsNotPaired) {
  const DepthGridShape s = shape();
  SurfaceAligner al = aligner();
  const Eigen::Isometry3d &T_c = kCandidate, &T_q = kQuery;
  // The query's room is the same room moved 1.5 m along x: where the map puts
  // the query, its surfaces are not the candidate's.
  Box room = kRoom;
  std::vector<Box> crates = kCrates;
  const Eigen::Vector3d shift(1.5, 0, 0);
  room.lo += shift;
  room.hi += shift;
  for (Box& b : crates) {
    b.lo += shift;
    b.hi += shift;
  }
  const std::vector<uint16_t> zc = render(s, T_c, kRoom, kCrates), zq = render(s, T_q, room, crates);
  const SurfaceFit f = al.align(zq.data(), T_q, zc.data(), T_c, SurfaceAlignOptions{});
  EXPECT_FALSE(f.ok) << "correction " << f.correction.translation().transpose();
}

TEST(SurfaceAlignment, ADriftBeyondTheAssociationBoundIsNotFollowed) {
  const DepthGridShape s = shape();
  SurfaceAligner al = aligner();
  const Eigen::Isometry3d &T_c = kCandidate, &T_q = kQuery;
  const std::vector<uint16_t> zc = render(s, T_c, kRoom, kCrates), zq = render(s, T_q, kRoom, kCrates);
  // 0.8 m off: the alignment must not claim a correction it cannot have found.
  const Eigen::Isometry3d D = drift(0.0, {0.8, 0.0, 0.0});
  const SurfaceFit f = al.align(zq.data(), D * T_q, zc.data(), T_c, SurfaceAlignOptions{});
  if (f.ok) {
    const Eigen::Isometry3d E = f.correction * D;
    EXPECT_LT(E.translation().norm(), 0.01) << "a wrong correction was verified";
  }
}

TEST(DepthGrid, SamplesTheDepthImageThroughTheDistortion) {
  kestrel::CameraIntrinsics cam;
  cam.width = 640;
  cam.height = 480;
  cam.fx = cam.fy = 525;
  cam.cx = 319.5;
  cam.cy = 239.5;
  cam.distortion = kestrel::DistortionModel::kRadTan;
  cam.dist = {0.1, -0.05, 0.001, -0.001, 0.0};
  kestrel::DepthModel dm;
  dm.scale_m_per_unit = 0.001;
  const DepthGridShape s = DepthGridShape::make(64, PinholeK{cam.fx, cam.fy, cam.cx, cam.cy}, 640, 480);
  ASSERT_EQ(s.rows, 48);
  // A wall at 2 m, square to the optical axis: every pixel reads 2000.
  std::vector<uint16_t> img(640 * 480, 2000);
  // A hole and a depth step: cells there stay empty.
  for (int y = 100; y < 140; ++y)
    for (int x = 100; x < 140; ++x) img[static_cast<size_t>(y) * 640 + x] = 0;
  for (int y = 0; y < 480; ++y) img[static_cast<size_t>(y) * 640 + 400] = 1000;
  kestrel::ImageView v;
  v.width = 640;
  v.height = 480;
  v.stride_bytes = 640 * 2;
  v.format = kestrel::PixelFormat::kDepthU16;
  v.data = reinterpret_cast<const uint8_t*>(img.data());
  const DepthGridSampler sampler(s, cam, dm, 0.05);
  std::vector<uint16_t> z(static_cast<size_t>(s.cells()));
  const int n = sampler.sample(v, z.data());
  EXPECT_GT(n, s.cells() * 8 / 10);
  EXPECT_LT(n, s.cells());
  int wall = 0;
  for (int c = 0; c < s.cells(); ++c) {
    if (z[static_cast<size_t>(c)] == 0) continue;
    EXPECT_EQ(z[static_cast<size_t>(c)], 2000) << "cell " << c;
    ++wall;
    // Its point lies on the wall, on the ray through the cell's undistorted centre.
    EXPECT_NEAR(s.point_C(c, z[static_cast<size_t>(c)]).z(), 2.0, 1e-9);
  }
  EXPECT_EQ(wall, n);
  // A depth image of another size or format gives no grid, not a wrong one.
  v.width = 320;
  EXPECT_EQ(sampler.sample(v, z.data()), 0);
}

}  // namespace

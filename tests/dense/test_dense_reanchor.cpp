// Surfaces follow the map's corrected poses (issue 44 item 2): a rendered room
// flown twice round a circle, the odometry drifting by a known, growing
// transform; the TSDF fused along the odometry smears every wall over the
// drift, and re-integrating the keyframe archive along the corrected (here:
// true) poses must put the surfaces back on the true geometry. Without the
// re-integration the surface error stays at the drift's size, so the test
// fails. Also: the archive's ring, its downsampled camera, and no allocation in
// store(). The figures are in docs/dense.md.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <vector>

#include "dense_room.hpp"
#include "kestrel/core/keyframe_archive.hpp"
#include "kestrel/core/tsdf_map.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/tools/sim_render.hpp"

namespace kestrel {
namespace {

using namespace dense_test;

// The odometry's error after frame f: 4 mm and 0.06 deg of yaw a frame, so
// 0.72 m and 11 deg after the second lap (a flight's drift before its loop).
Eigen::Isometry3d drift(int f) {
  Eigen::Isometry3d D = Eigen::Isometry3d::Identity();
  D.linear() = Eigen::AngleAxisd(f * 0.06 * M_PI / 180.0, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  D.translation() = Eigen::Vector3d(0.004 * f, -0.002 * f, 0.0005 * f);
  return D;
}

CameraIntrinsics camera() {
  CameraIntrinsics cam;
  cam.width = 320;
  cam.height = 240;
  cam.fx = cam.fy = 262.5;
  cam.cx = 159.5;
  cam.cy = 119.5;
  return cam;
}

struct Errors {
  double median = 0, p95 = 0;
  std::size_t points = 0;
};

Errors surface_errors(const tools::Scene& s, const core::TsdfMap& map) {
  std::vector<core::SurfacePoint> pts;
  map.extract_surface(pts);
  std::vector<double> e;
  for (const core::SurfacePoint& p : pts) e.push_back(scene_distance(s, p.p.cast<double>()));
  return {quantile(e, 0.5), quantile(e, 0.95), pts.size()};
}

TEST(DenseReanchor, SurfacesFollowTheCorrectedKeyframePoses) {
  const tools::Scene scene = room_with_boxes();
  const CameraIntrinsics cam = camera();
  DepthModel dm;
  tools::RenderOptions ro;
  ro.seed = 11;
  tools::Renderer render(scene, cam, dm, ro);

  core::TsdfOptions o;  // the defaults: 5 cm voxels
  core::TsdfMap map(o);
  core::KeyframeArchiveOptions ao;  // the defaults: stride 2
  core::KeyframeArchive archive(ao, cam);
  ASSERT_GE(archive.capacity(), 180);

  const auto n = static_cast<std::size_t>(cam.width * cam.height);
  std::vector<uint8_t> rgb(3 * n);
  std::vector<uint16_t> depth(n);
  constexpr int kFrames = 180;  // two laps: the second sees the first's walls again, drifted
  std::vector<Eigen::Isometry3d> T_WC_true(kFrames);
  for (int f = 0; f < kFrames; ++f) {
    T_WC_true[f] = pose_on_circle(2 * M_PI * f / 90.0);
    const Eigen::Isometry3d T_WC_odom = drift(f) * T_WC_true[f];
    render.render(T_WC_true[f], static_cast<uint64_t>(f), rgb.data(), depth.data());
    const ImageView dv{cam.width, cam.height, 2 * cam.width, PixelFormat::kDepthU16,
                       reinterpret_cast<const uint8_t*>(depth.data())};
    const ImageView cv{cam.width, cam.height, 3 * cam.width, PixelFormat::kRgb8, rgb.data()};
    map.integrate(dv, cv, cam, dm, T_WC_odom);
    ASSERT_TRUE(archive.store(1'000'000'000LL + f * 33'000'000LL, T_WC_odom, dv, cv));
  }
  const Errors drifted = surface_errors(scene, map);

  // The loop closed: the map's poses are the true ones. Keyframes are found by time.
  const core::ReintegrationReport r = core::reintegrate(
      archive, dm, map, [&](int64_t t_ns, const Eigen::Isometry3d& T_WC_fused, Eigen::Isometry3d& T_MC) {
        const int f = static_cast<int>((t_ns - 1'000'000'000LL) / 33'000'000LL);
        EXPECT_TRUE(T_WC_fused.isApprox(drift(f) * T_WC_true[f]));  // the pose it was fused with is kept
        T_MC = T_WC_true[f];
        return true;
      });
  const Errors corrected = surface_errors(scene, map);
  std::printf(
      "dense re-anchoring: along the drifted odometry median %.4f m, 95%% %.4f m (%zu points); re-integrated "
      "along the corrected poses median %.4f m, 95%% %.4f m (%zu points); %d keyframes in %.1f ms (archive "
      "%.1f "
      "MiB, %d slots)\n",
      drifted.median, drifted.p95, drifted.points, corrected.median, corrected.p95, corrected.points, r.fused,
      1e-6 * static_cast<double>(r.cpu_ns), static_cast<double>(archive.memory_bytes()) / 1048576.0,
      archive.capacity());
  EXPECT_EQ(r.fused, kFrames);
  EXPECT_EQ(r.no_pose, 0);
  // The drift smears the walls (this is what the re-integration must undo) ...
  EXPECT_GT(drifted.p95, 0.10);
  // ... and after it the surface is on the true geometry, at the accuracy goals.
  EXPECT_LE(corrected.median, 0.015);
  EXPECT_LE(corrected.p95, 0.04);
  EXPECT_GT(corrected.points, 5000u);
}

TEST(DenseReanchor, KeyframesWithoutAPoseAreLeftOutAndCounted) {
  const tools::Scene scene = room_with_boxes();
  const CameraIntrinsics cam = camera();
  DepthModel dm;
  tools::Renderer render(scene, cam, dm, tools::RenderOptions{});
  core::KeyframeArchive archive(core::KeyframeArchiveOptions{}, cam);
  core::TsdfOptions o;
  o.memory_budget_mb = 8;
  core::TsdfMap map(o);
  const auto n = static_cast<std::size_t>(cam.width * cam.height);
  std::vector<uint8_t> rgb(3 * n);
  std::vector<uint16_t> depth(n);
  for (int f = 0; f < 4; ++f) {
    render.render(pose_on_circle(f), static_cast<uint64_t>(f), rgb.data(), depth.data());
    const ImageView dv{cam.width, cam.height, 2 * cam.width, PixelFormat::kDepthU16,
                       reinterpret_cast<const uint8_t*>(depth.data())};
    ASSERT_TRUE(archive.store(f, pose_on_circle(f), dv, ImageView{}));
  }
  const core::ReintegrationReport r = core::reintegrate(
      archive, dm, map, [&](int64_t t_ns, const Eigen::Isometry3d& T_WC, Eigen::Isometry3d& T_MC) {
        T_MC = T_WC;
        return t_ns % 2 == 0;
      });
  EXPECT_EQ(r.fused, 2);
  EXPECT_EQ(r.no_pose, 2);
  EXPECT_GT(map.blocks_in_use(), 0);
}

TEST(KeyframeArchive, RingOverwritesTheOldestCountsItAndDoesNotAllocate) {
  CameraIntrinsics cam;
  cam.width = 64;
  cam.height = 48;
  cam.fx = cam.fy = 50;
  cam.cx = 31.5;
  cam.cy = 23.5;
  core::KeyframeArchiveOptions ao;
  ao.stride_px = 2;
  ao.budget_mb = 3.0 * 32 * 24 * 5 / 1048576.0 + 1e-9;  // exactly three keyframes
  core::KeyframeArchive a(ao, cam);
  ASSERT_EQ(a.capacity(), 3);
  EXPECT_EQ(a.camera().width, 32);
  EXPECT_EQ(a.camera().height, 24);
  EXPECT_DOUBLE_EQ(a.camera().fx, 25.0);
  EXPECT_DOUBLE_EQ(a.camera().cx, 15.75);
  std::vector<uint16_t> depth(64 * 48);
  std::vector<uint8_t> rgb(3 * 64 * 48);
  const uint64_t before = rt::alloc_count_this_thread();
  for (int k = 0; k < 5; ++k) {
    for (int v = 0; v < 48; ++v)
      for (int u = 0; u < 64; ++u) depth[v * 64 + u] = static_cast<uint16_t>(1000 * k + 10 * v + u);
    const ImageView dv{64, 48, 128, PixelFormat::kDepthU16, reinterpret_cast<const uint8_t*>(depth.data())};
    const ImageView cv{64, 48, 192, PixelFormat::kBgr8, rgb.data()};
    EXPECT_TRUE(a.store(100 + k, Eigen::Isometry3d::Identity(), dv, cv));
  }
  EXPECT_EQ(rt::alloc_count_this_thread() - before, 0u);
  EXPECT_EQ(a.size(), 3);
  EXPECT_EQ(a.counters().stored, 5u);
  EXPECT_EQ(a.counters().overwritten, 2u);
  EXPECT_EQ(a.t_ns(0), 102);  // the two oldest went
  EXPECT_EQ(a.t_ns(2), 104);
  // Pixel (u', v') of the archive is pixel (2u', 2v') of the image: the point, not an average.
  const ImageView d = a.depth(1);
  uint16_t z;
  std::memcpy(&z, d.data + 5 * d.stride_bytes + 2 * 7, 2);
  EXPECT_EQ(z, 1000 * 3 + 10 * 10 + 14);
  EXPECT_EQ(a.rgb(1).format, PixelFormat::kBgr8);
  // Wrong size: refused, nothing kept.
  const ImageView small{32, 24, 64, PixelFormat::kDepthU16, reinterpret_cast<const uint8_t*>(depth.data())};
  EXPECT_FALSE(a.store(200, Eigen::Isometry3d::Identity(), small, ImageView{}));
  EXPECT_EQ(a.counters().stored, 5u);
}

TEST(KeyframeArchive, RefusesBadOptionsNamingTheKey) {
  core::KeyframeArchiveOptions ao;
  ao.stride_px = 0;
  try {
    ao.validate();
    FAIL() << "stride 0 accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("dense.archive_stride_px"), std::string::npos);
  }
  ao = {};
  ao.budget_mb = NAN;
  EXPECT_THROW(ao.validate(), std::invalid_argument);
}

}  // namespace
}  // namespace kestrel

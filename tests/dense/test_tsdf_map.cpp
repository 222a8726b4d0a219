// core/dense's TSDF on synthetic depth: a plane seen head-on (surface within
// a centimetre, free in front, unknown behind), the planner's queries, the
// noise weighting, eviction in a fixed budget and no allocation after start-up.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <vector>

#include "kestrel/core/tsdf_map.hpp"
#include "kestrel/rt/alloc_counter.hpp"

namespace kestrel::core {
namespace {

CameraIntrinsics camera() {
  CameraIntrinsics c;
  c.width = 160;
  c.height = 120;
  c.fx = c.fy = 150.0;
  c.cx = 79.5;
  c.cy = 59.5;
  return c;
}

DepthModel depth_model() {
  DepthModel d;
  d.scale_m_per_unit = 0.001;
  d.min_range_m = 0.3;
  d.max_range_m = 6.0;
  d.sigma_coeff_per_m = 0.0025;
  return d;
}

// Depth of a plane z = plane_z_m (camera frame), every pixel.
struct PlaneImage {
  std::vector<uint16_t> depth;
  std::vector<uint8_t> rgb;
  ImageView depth_view, rgb_view;
  explicit PlaneImage(double plane_z_m, uint16_t hole_value = 0, bool hole = false) {
    const CameraIntrinsics c = camera();
    depth.assign(static_cast<std::size_t>(c.width * c.height),
                 static_cast<uint16_t>(std::lround(plane_z_m * 1000)));
    if (hole)
      for (int v = 50; v < 70; ++v)
        for (int u = 70; u < 90; ++u) depth[static_cast<std::size_t>(v * c.width + u)] = hole_value;
    rgb.assign(static_cast<std::size_t>(3 * c.width * c.height), 200);
    depth_view = {c.width, c.height, 2 * c.width, PixelFormat::kDepthU16,
                  reinterpret_cast<const uint8_t*>(depth.data())};
    rgb_view = {c.width, c.height, 3 * c.width, PixelFormat::kRgb8, rgb.data()};
  }
};

// Camera at p looking along +x of M (z_C = x_M, x_C = -y_M, y_C = -z_M).
Eigen::Isometry3d looking_along_x(const Eigen::Vector3d& p) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() << 0, 0, 1, -1, 0, 0, 0, -1, 0;
  T.translation() = p;
  return T;
}

TEST(TsdfMap, PlaneSurfaceFreeSpaceAndUnknownBehind) {
  TsdfOptions o;
  o.memory_budget_mb = 8;
  TsdfMap map(o);
  const PlaneImage img(2.0);
  for (int i = 0; i < 3; ++i)
    map.integrate(img.depth_view, img.rgb_view, camera(), depth_model(), looking_along_x({0, 0, 0}));
  std::vector<SurfacePoint> pts;
  map.extract_surface(pts);
  ASSERT_GT(pts.size(), 100u);
  double worst = 0;
  for (const SurfacePoint& s : pts) {
    // Zero crossings lie on the plane x = 2, coloured as it was.
    worst = std::max(worst, std::fabs(s.p.x() - 2.0));
    EXPECT_EQ(s.rgb[0], 200);
  }
  EXPECT_LT(worst, 0.01);
  EXPECT_EQ(map.occupancy({1.0, 0.0, 0.0}), Occupancy::kFree);
  EXPECT_EQ(map.occupancy({2.0, 0.0, 0.0}), Occupancy::kOccupied);
  EXPECT_EQ(map.occupancy({2.6, 0.0, 0.0}), Occupancy::kUnknown);   // behind the band
  EXPECT_EQ(map.occupancy({-1.0, 0.0, 0.0}), Occupancy::kUnknown);  // behind the camera
  EXPECT_EQ(map.segment({0.5, 0, 0}, {1.7, 0.1, 0.05}), Occupancy::kFree);
  EXPECT_EQ(map.segment({0.5, 0, 0}, {2.5, 0, 0}), Occupancy::kOccupied);
  EXPECT_EQ(map.segment({-1.0, 0, 0}, {1.0, 0, 0}), Occupancy::kUnknown);
  float d = 0;
  ASSERT_TRUE(map.distance({1.9, 0, 0}, d));
  EXPECT_NEAR(d, 0.1, 0.03);
  EXPECT_FALSE(map.distance({5.0, 0, 0}, d));
}

TEST(TsdfMap, CarvesAnObjectThatMovedAway) {
  TsdfOptions o;
  o.memory_budget_mb = 8;
  TsdfMap map(o);
  const PlaneImage near_plane(1.0), far_plane(2.0);
  for (int i = 0; i < 2; ++i)
    map.integrate(near_plane.depth_view, near_plane.rgb_view, camera(), depth_model(),
                  looking_along_x({0, 0, 0}));
  EXPECT_EQ(map.occupancy({1.0, 0, 0}), Occupancy::kOccupied);
  // The wall at 1 m is gone: rays to 2 m pass through it and carve it free.
  for (int i = 0; i < 40; ++i)
    map.integrate(far_plane.depth_view, far_plane.rgb_view, camera(), depth_model(),
                  looking_along_x({0, 0, 0}));
  EXPECT_EQ(map.occupancy({1.0, 0, 0}), Occupancy::kFree);
  EXPECT_EQ(map.occupancy({2.0, 0, 0}), Occupancy::kOccupied);
}

TEST(TsdfMap, NearObservationsOutweighFarOnes) {
  TsdfOptions o;
  o.memory_budget_mb = 8;
  TsdfMap map(o);
  // The same wall seen at 1 m (x = 2 from x = 1) and, wrongly, 10 cm off from 3 m away.
  const PlaneImage near_view(1.0), far_view(3.1);
  map.integrate(near_view.depth_view, near_view.rgb_view, camera(), depth_model(),
                looking_along_x({1, 0, 0}));
  map.integrate(far_view.depth_view, far_view.rgb_view, camera(), depth_model(), looking_along_x({-1, 0, 0}));
  std::vector<SurfacePoint> pts;
  map.extract_surface(pts);
  ASSERT_FALSE(pts.empty());
  double mean_x = 0;
  for (const SurfacePoint& s : pts) mean_x += s.p.x();
  mean_x /= static_cast<double>(pts.size());
  // Weights (3.1/1)^4 ~ 92 : 1: the near view decides within a few millimetres.
  EXPECT_NEAR(mean_x, 2.0, 0.005);
}

TEST(TsdfMap, InvalidDepthIsCountedAndNotFused) {
  TsdfOptions o;
  o.memory_budget_mb = 8;
  TsdfMap map(o);
  const PlaneImage img(2.0, 0, true);
  map.integrate(img.depth_view, img.rgb_view, camera(), depth_model(), looking_along_x({0, 0, 0}));
  EXPECT_GT(map.counters().pixels_invalid, 0u);
  // A wrong-sized image is refused whole.
  ImageView small = img.depth_view;
  small.width = 10;
  const uint64_t frames = map.counters().frames;
  map.integrate(small, img.rgb_view, camera(), depth_model(), looking_along_x({0, 0, 0}));
  EXPECT_EQ(map.counters().frames, frames);
  EXPECT_EQ(map.occupancy({std::nan(""), 0, 0}), Occupancy::kUnknown);
}

TEST(TsdfMap, FixedBudgetEvictsFarBlocksAndAllocatesNothing) {
  TsdfOptions o;
  o.memory_budget_mb = 2;
  o.evict_distance_m = 2.5;
  TsdfMap map(o);
  const std::size_t bytes = map.memory_bytes();
  const PlaneImage img(2.0);
  // Warm-up: the first frame may touch lazily committed pages, not the heap.
  map.integrate(img.depth_view, img.rgb_view, camera(), depth_model(), looking_along_x({0, 0, 0}));
  const uint64_t before = rt::alloc_count_this_thread();
  // A 60 m corridor flown sideways: the budget fills, far blocks go.
  for (int i = 0; i < 300; ++i) {
    Eigen::Isometry3d T = looking_along_x({0, 0.2 * i, 0});
    map.integrate(img.depth_view, img.rgb_view, camera(), depth_model(), T);
    ASSERT_LE(map.blocks_in_use(), map.block_capacity());
  }
  EXPECT_EQ(rt::alloc_count_this_thread() - before, 0u);
  EXPECT_EQ(map.memory_bytes(), bytes);
  EXPECT_GT(map.counters().blocks_evicted, 0u);
  // What is near the camera is still there, what was far is gone.
  EXPECT_EQ(map.occupancy({2.0, 59.8, 0.0}), Occupancy::kOccupied);
  EXPECT_EQ(map.occupancy({2.0, 0.0, 0.0}), Occupancy::kUnknown);
  // The hash table stays consistent through the deletions: every block in use is found.
  std::vector<Eigen::Vector3f> occ;
  map.occupied_voxels(occ);
  ASSERT_FALSE(occ.empty());
  for (const Eigen::Vector3f& p : occ) ASSERT_EQ(map.occupancy(p.cast<double>()), Occupancy::kOccupied);
}

TEST(TsdfMap, FullPoolWithNothingFarRefusesAndCounts) {
  TsdfOptions o;
  o.memory_budget_mb = 1;
  o.evict_distance_m = 100.0;
  TsdfMap map(o);
  const PlaneImage img(3.0);
  for (int i = 0; i < 40; ++i)
    map.integrate(img.depth_view, img.rgb_view, camera(), depth_model(), looking_along_x({0, 0.5 * i, 0}));
  EXPECT_EQ(map.blocks_in_use(), map.block_capacity());
  EXPECT_GT(map.counters().blocks_refused, 0u);
  EXPECT_EQ(map.counters().blocks_evicted, 0u);
}

TEST(TsdfOptions, BadValuesNameTheKey) {
  TsdfOptions o;
  o.voxel_size_m = 0;
  try {
    o.validate();
    FAIL() << "accepted voxel_size_m = 0";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("dense.voxel_size_m"), std::string::npos);
  }
  o = TsdfOptions{};
  o.min_weight = 1000;
  EXPECT_THROW(o.validate(), std::invalid_argument);
}

}  // namespace
}  // namespace kestrel::core

// A planner's queries on the dense map in flight (issue 44 item 3,
// docs/dense.md "Live queries"): while kst-dense fuses keyframes and, after a
// loop's correction (T_map_odom, and the map's keyframe list handed over by a
// third thread), takes old ones out and fuses them again, another thread
// asks occupancy, segments, distances and the whole surface. Every answer must
// agree with the rendered room's true geometry (a torn read would put
// occupied space in mid-air or free space inside a box), the estimator
// thread's hand-off still allocates nothing, and a query waits at most for one
// keyframe's work. In the tsan suite (tests/CMakeLists.txt, KESTREL_TSAN_TESTS).
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <random>
#include <thread>
#include <vector>

#include "dense_room.hpp"
#include "kestrel/dense/dense_mapper.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/tools/sim_render.hpp"
#include "room_flight.hpp"

namespace kestrel {
namespace {

using namespace dense_test;

constexpr int kFrames = 90;  // one lap
constexpr int kLoopFrame = 70;
int64_t t_of(int f) { return room_frame_t_ns(f); }

// The odometry drifts 1 mm and 0.02 deg of yaw a frame until the loop; the
// correction then moves the keyframes back (enough to re-fuse most of them).
Eigen::Isometry3d correction(int f) {
  return linear_drift_correction(f, kLoopFrame, 0.02, Eigen::Vector3d(0.001, -0.0005, 0.0));
}

struct Answer {
  Eigen::Vector3d p;
  core::Occupancy occ;
};

TEST(DenseQuery, APlannerQueriesTheMapInFlightAndEveryAnswerIsOnTheTrueGeometry) {
  const tools::Scene scene = room_with_boxes();
  const Rig r = room_rig();
  tools::RenderOptions ro;
  ro.seed = 5;
  tools::Renderer render(scene, r.rgb, r.depth, ro);
  dense::DenseOptions o;
  o.enabled = true;
  o.keyframe_interval_s = 0.001;  // every frame a keyframe: most fusion work to race with
  o.live_reanchor = true;
  o.reanchor_cpu_s_per_s = 1.0;  // re-fuse at once: the queries race with deintegrate too
  o.reanchor_burst_cpu_s = 10;
  dense::DenseMapper m(o, r, true);
  ASSERT_TRUE(m.enabled());
  EXPECT_TRUE(m.live_frame_is_map());

  // The planner: random points and segments in the room, the surface now and then.
  std::atomic<bool> flying{true};
  std::vector<Answer> answers;
  std::vector<double> wait_ms;
  std::vector<std::size_t> surface_sizes;
  int segments_occupied = 0, segments = 0, distances = 0;
  std::thread planner([&] {
    std::mt19937 rng(7);
    std::uniform_real_distribution<double> ux(-3.2, 2.7), uy(-2.7, 3.2), uz(-0.2, 3.2);
    int i = 0;
    while (flying.load(std::memory_order_acquire)) {
      const Eigen::Vector3d p(ux(rng), uy(rng), uz(rng));
      const int64_t t0 = rt::now_ns();
      const core::Occupancy occ = m.occupancy(p);
      wait_ms.push_back(1e-6 * static_cast<double>(rt::now_ns() - t0));
      if (occ != core::Occupancy::kUnknown) answers.push_back({p, occ});
      const Eigen::Vector3d q(ux(rng), uy(rng), uz(rng));
      segments_occupied += m.segment(p, q) == core::Occupancy::kOccupied;
      ++segments;
      float sdf = 0;
      distances += m.distance(p, sdf) && std::isfinite(sdf);
      if (++i % 50 == 0)
        m.read([&](const core::TsdfMap& map) {
          std::vector<core::SurfacePoint> pts;
          map.extract_surface(pts);
          surface_sizes.push_back(pts.size());
        });
    }
  });

  const auto n = static_cast<std::size_t>(r.rgb.width * r.rgb.height);
  std::vector<uint8_t> rgb(3 * n);
  std::vector<uint16_t> depth(n);
  uint64_t estimator_allocs = 0;
  for (int f = 0; f < kFrames; ++f) {
    const Eigen::Isometry3d T_true = pose_on_circle(2 * M_PI * f / kFrames);
    const Eigen::Isometry3d T_odom = correction(f).inverse() * T_true;
    estimator_allocs +=
        hand_frame(m, render, r, f, T_true, T_odom, f >= kLoopFrame, correction(kLoopFrame), rgb, depth);
    if (f == kLoopFrame) {
      // The map's loop thread hands over its keyframes, as after a global bundle adjustment.
      std::thread loop_thread([&m] {
        std::vector<dense::MapCorrection> kfs;
        for (int g = 0; g <= kLoopFrame; g += 5) kfs.push_back({t_of(g), correction(g)});
        m.note_map_keyframes(kfs);
      });
      loop_thread.join();
    }
  }
  m.wait_idle();
  const int64_t deadline = rt::now_ns() + 60'000'000'000LL;
  while ((m.corrections_applied() < 2 || m.reanchor_backlog() > 0) && rt::now_ns() < deadline)
    rt::sleep_for_ns(5'000'000);
  flying.store(false, std::memory_order_release);
  planner.join();
  const uint64_t queries = m.queries();
  m.stop();

  const dense::DenseStats& s = m.stats();
  EXPECT_EQ(s.map_moves, 1u);
  std::vector<double> w = wait_ms;
  const double p50 = quantile(w, 0.5), p99 = quantile(w, 0.99);
  const double worst = w.empty() ? 0 : *std::max_element(w.begin(), w.end());
  std::printf(
      "planner: %llu queries in flight (%zu point answers, %d segments, %d occupied, %d distances), "
      "occupancy wait p50 %.3f ms p99 %.2f ms max %.2f ms; integrate p99 %.2f ms; %llu keyframes re-fused\n",
      static_cast<unsigned long long>(queries), answers.size(), segments, segments_occupied, distances, p50,
      p99, worst, 1e-6 * static_cast<double>(s.integrate.p99()),
      static_cast<unsigned long long>(s.reanchored));

  EXPECT_EQ(estimator_allocs, 0u) << "the hand-off allocated while a planner queried";
  EXPECT_EQ(s.integrated, static_cast<uint64_t>(kFrames));
  EXPECT_GT(s.reanchored, 10u) << "the correction re-fused too little to race with the queries";
  ASSERT_GT(answers.size(), 100u) << "the planner got too few known answers in flight";
  EXPECT_GT(segments, 100);
  EXPECT_GT(segments_occupied, 0);
  EXPECT_GT(distances, 0);
  ASSERT_GE(surface_sizes.size(), 2u);
  EXPECT_GT(surface_sizes.back(), 1000u);
  // Every known answer is where the truth allows it. The drift before the
  // correction is at most 8 cm at the walls (the correction's re-fusion
  // brings them back, but a query may come first), the band is 3 voxels:
  // occupied lies within 25 cm of a true surface; free lies in open space or
  // within that of its edge, never deep inside a box or outside the room.
  int occupied = 0, occupied_off = 0, free = 0, free_inside = 0;
  for (const Answer& a : answers) {
    const double d = scene_distance(scene, a.p);
    const bool in_room = scene.room.contains(a.p);
    bool in_box = false;
    for (const tools::SceneBox& b : scene.boxes) {
      const Eigen::Matrix3d R = Eigen::AngleAxisd(b.yaw_rad, Eigen::Vector3d::UnitZ()).toRotationMatrix();
      in_box = in_box || ((R.transpose() * (a.p - b.center_W)).cwiseAbs() - b.half_m).maxCoeff() < 0;
    }
    if (a.occ == core::Occupancy::kOccupied) {
      ++occupied;
      occupied_off += d > 0.25;
    } else {
      ++free;
      free_inside += (!in_room || in_box) && d > 0.25;
    }
  }
  std::printf("answers: %d occupied (%d off a true surface), %d free (%d inside solid)\n", occupied,
              occupied_off, free, free_inside);
  EXPECT_GT(occupied, 0);
  EXPECT_GT(free, 0);
  EXPECT_EQ(occupied_off, 0);
  EXPECT_EQ(free_inside, 0);
  // A query waits at most for the keyframe kst-dense is fusing or moving; the
  // bound carries a loaded 2-core machine's margin (docs/dense.md has the figures).
  EXPECT_LT(worst, 1000.0);
}

}  // namespace
}  // namespace kestrel

// The map in fixed memory and the local mapper (core/map): storage, the
// landmark-id index, covisibility, culling, fusing, and local bundle
// adjustment on a synthetic room.
#include <gtest/gtest.h>

#include <algorithm>
#include <map>
#include <random>

#include "map_sim.hpp"

namespace kestrel::map_test {
namespace {

using core::KeyframeFeature;
using core::Map;
using core::MapOptions;

std::vector<KeyframeFeature> features(int n, uint32_t first_id) {
  std::vector<KeyframeFeature> f(static_cast<size_t>(n));
  for (int j = 0; j < n; ++j) {
    f[j].u_px = f[j].x_px = 10.0f + j;
    f[j].v_px = f[j].y_px = 20.0f;
    f[j].depth_m = 2.0f;
    f[j].landmark_id = first_id + static_cast<uint32_t>(j);
  }
  return f;
}

MapOptions small_options() {
  MapOptions o;
  o.max_keyframes = 8;
  o.max_points = 64;
  return o;
}

TEST(Map, OptionsValidate) {
  EXPECT_EQ(MapOptions{}.validate(), "");
  MapOptions o;
  o.max_keyframes = 1;
  o.cull_keyframe_redundancy = 1.5;
  const std::string e = o.validate();
  EXPECT_NE(e.find("max_keyframes"), std::string::npos);
  EXPECT_NE(e.find("cull_keyframe_redundancy"), std::string::npos);
  EXPECT_THROW(Map(o, 10), std::invalid_argument);
}

TEST(Map, KeyframesPointsAndObservationsStayWithinCapacity) {
  Map m(small_options(), 10);
  const auto f = features(10, 1);
  std::vector<int> kfs;
  for (int k = 0; k < 8; ++k)
    kfs.push_back(m.add_keyframe(k, Eigen::Isometry3d::Identity(), Eigen::Isometry3d::Identity(), f.data(),
                                 10, k > 0 ? kfs.back() : -1));
  for (int k : kfs) EXPECT_GE(k, 0);
  EXPECT_EQ(m.add_keyframe(9, Eigen::Isometry3d::Identity(), Eigen::Isometry3d::Identity(), f.data(), 10, -1),
            -1)
      << "full: refused, never grown";
  EXPECT_EQ(m.num_keyframes(), 8);
  // One point per feature of keyframe 0, observed by every keyframe.
  for (int j = 0; j < 10; ++j) {
    const int p = m.add_point(f[j].landmark_id, Eigen::Vector3d(j, 0, 2), f[j].desc, 0, kfs[0], j);
    ASSERT_GE(p, 0);
    for (size_t k = 1; k < kfs.size(); ++k) EXPECT_TRUE(m.add_observation(p, kfs[k], j));
    EXPECT_FALSE(m.add_observation(p, kfs[3], j)) << "a keyframe observes a point once";
    EXPECT_EQ(m.point(p).n_obs, 8);
  }
  EXPECT_EQ(m.add_point(5, Eigen::Vector3d::Zero(), {}, 0, kfs[0], 5), -1) << "the id is taken";
  int32_t nb[8], shared[8];
  ASSERT_EQ(m.covisible(kfs[2], 1, 8, nb, shared), 7);
  for (int i = 0; i < 7; ++i) EXPECT_EQ(shared[i], 10);
  // Erasing a keyframe removes its observations and relinks its children.
  m.erase_keyframe(kfs[3]);
  EXPECT_EQ(m.num_keyframes(), 7);
  EXPECT_EQ(m.keyframe(kfs[4]).parent, kfs[2]);
  EXPECT_EQ(m.point(m.find_point(1)).n_obs, 7);
  EXPECT_EQ(m.covisible(kfs[2], 1, 8, nb, shared), 6);
  // A point seen by nobody goes; its id can be taken again.
  for (int k : kfs)
    if (m.keyframe_used(k)) m.erase_observation(m.find_point(1), k);
  EXPECT_EQ(m.find_point(1), -1);
  EXPECT_EQ(m.num_points(), 9);
}

TEST(Map, LandmarkIndexAgreesWithAReferenceOverChurn) {
  MapOptions o;
  o.max_keyframes = 2;
  o.max_points = 500;
  Map m(o, 4);
  const auto f = features(4, 1);
  const int kf =
      m.add_keyframe(0, Eigen::Isometry3d::Identity(), Eigen::Isometry3d::Identity(), f.data(), 4, -1);
  ASSERT_GE(kf, 0);
  std::map<uint32_t, int> ref;
  std::mt19937_64 rng(3);
  for (int it = 0; it < 20000; ++it) {
    const uint32_t id = 1 + static_cast<uint32_t>(rng() % 1500);
    if (rng() % 2 == 0 && static_cast<int>(ref.size()) < o.max_points) {
      const int p = m.add_point(id, Eigen::Vector3d::Zero(), {}, 0, -1, 0);
      if (ref.count(id)) {
        EXPECT_EQ(p, -1);
      } else {
        ASSERT_GE(p, 0);
        ref[id] = p;
      }
    } else if (ref.count(id)) {
      m.erase_point(ref[id]);
      ref.erase(id);
    }
    if (it % 997 == 0) {
      for (const auto& [k, v] : ref) ASSERT_EQ(m.find_point(k), v);
    }
  }
  EXPECT_EQ(m.num_points(), static_cast<int>(ref.size()));
  for (uint32_t id = 1; id <= 1500; ++id) EXPECT_EQ(m.find_point(id) >= 0, ref.count(id) == 1);
}

TEST(Map, MergeMovesObservations) {
  Map m(small_options(), 10);
  const auto f = features(10, 1);
  const int a =
      m.add_keyframe(0, Eigen::Isometry3d::Identity(), Eigen::Isometry3d::Identity(), f.data(), 10, -1);
  const int b =
      m.add_keyframe(1, Eigen::Isometry3d::Identity(), Eigen::Isometry3d::Identity(), f.data(), 10, a);
  const int p = m.add_point(100, Eigen::Vector3d(1, 0, 2), {}, 0, a, 0);
  const int q = m.add_point(200, Eigen::Vector3d(1, 0, 2), {}, 0, b, 3);
  m.merge_point(q, p);
  EXPECT_EQ(m.find_point(200), -1);
  EXPECT_EQ(m.point(p).n_obs, 2);
  EXPECT_EQ(m.point_of(b, 3), p);
}

// Keyframes along a path with perturbed poses: the local bundle adjustment
// brings them back towards the truth.
TEST(LocalMapper, BundleAdjustmentRefinesPerturbedKeyframes) {
  SimRoom room(1500, 11);
  MapOptions o;
  o.max_keyframes = 32;
  o.max_points = 4000;
  o.ba_gravity_sigma_rad = 0.0;
  o.cull_keyframe_redundancy = 1.0;
  Map m(o, 300);
  core::LocalMapper mapper(m, sim_camera());
  std::mt19937_64 rng(5);
  double before = 0, after = 0;
  std::vector<int> slots;
  std::vector<Eigen::Isometry3d> truth;
  for (int k = 0; k < 8; ++k) {
    const Eigen::Isometry3d T = SimRoom::camera(Eigen::Vector3d(0.3 * k, 0.1 * k, 1.5), 0.2 + 0.05 * k);
    SimKeyframe s = room.observe(T, rng);
    core::KeyframePacket pk;
    pk.t_ns = k * 200'000'000;
    pk.T_WC = k == 0 ? T : perturbed(T, rng, 0.03, 0.01);
    before += k == 0 ? 0 : pos_err(pk.T_WC, T);
    pk.n = static_cast<int>(s.features.size());
    pk.features = s.features.data();
    slots.push_back(mapper.insert(pk, Eigen::Isometry3d::Identity(), slots.empty() ? -1 : slots.back()));
    ASSERT_GE(slots.back(), 0);
    truth.push_back(T);
  }
  for (int k = 1; k < 8; ++k) {
    after += pos_err(m.keyframe(slots[k]).T_MC, truth[k]);
  }
  std::printf("mean keyframe position error: %.1f mm before, %.1f mm after local BA (%llu runs)\n",
              1e3 * before / 7, 1e3 * after / 7, static_cast<unsigned long long>(mapper.stats().ba_runs));
  EXPECT_LT(after, 0.3 * before);
  EXPECT_EQ(mapper.stats().ba_failures, 0u);
  EXPECT_GT(m.num_points(), 150);
}

// The odometry's gravity direction holds the keyframes' roll and pitch
// against a bundle adjustment that would otherwise let them follow bad data.
TEST(LocalMapper, GravityPriorHoldsRollAndPitch) {
  SimRoom room(1500, 12);
  double tilt_free = 0;
  for (const double sigma : {0.0, 0.005}) {
    MapOptions o;
    o.max_keyframes = 32;
    o.max_points = 4000;
    o.ba_gravity_sigma_rad = sigma;
    Map m(o, 300);
    core::LocalMapper mapper(m, sim_camera());
    std::mt19937_64 rng(6);
    std::vector<int> slots;
    double tilt = 0;
    for (int k = 0; k < 6; ++k) {
      const Eigen::Isometry3d T = SimRoom::camera(Eigen::Vector3d(0.3 * k, 0.0, 1.5), 0.1 * k);
      SimKeyframe s = room.observe(T, rng, 1, 2.0);
      core::KeyframePacket pk;
      pk.t_ns = k * 200'000'000;
      pk.T_WC = T;  // exact odometry, noisy pixels
      pk.n = static_cast<int>(s.features.size());
      pk.features = s.features.data();
      slots.push_back(mapper.insert(pk, Eigen::Isometry3d::Identity(), slots.empty() ? -1 : slots.back()));
    }
    for (int k : slots) {
      const Eigen::Vector3d down_C = m.keyframe(k).T_MC.linear().transpose() * Eigen::Vector3d(0, 0, -1);
      tilt = std::max(tilt, std::acos(std::min(1.0, down_C.dot(m.keyframe(k).g_C))));
    }
    std::printf("gravity sigma %.3f rad: largest keyframe tilt %.4f rad\n", sigma, tilt);
    if (sigma > 0) {
      EXPECT_LT(tilt, 0.5 * tilt_free);
    } else {
      tilt_free = tilt;
    }
  }
}

TEST(LocalMapper, FusesAPointKnownUnderTwoIds) {
  SimRoom room(800, 13);
  MapOptions o;
  o.max_keyframes = 8;
  o.max_points = 2000;
  Map m(o, 300);
  core::LocalMapper mapper(m, sim_camera());
  std::mt19937_64 rng(7);
  const Eigen::Isometry3d T0 = SimRoom::camera(Eigen::Vector3d(0, 0, 1.5), 0.0);
  const Eigen::Isometry3d T1 = SimRoom::camera(Eigen::Vector3d(0.1, 0.0, 1.5), 0.02);
  SimKeyframe a = room.observe(T0, rng, 1);
  SimKeyframe b =
      room.observe(T1, rng, 100000);  // the tracker lost the ids: every point arrives under a new one
  core::KeyframePacket pa, pb;
  pa.T_WC = T0;
  pa.n = static_cast<int>(a.features.size());
  pa.features = a.features.data();
  pb.t_ns = 1;
  pb.T_WC = T1;
  pb.n = static_cast<int>(b.features.size());
  pb.features = b.features.data();
  const int ka = mapper.insert(pa, Eigen::Isometry3d::Identity(), -1);
  const int kb = mapper.insert(pb, Eigen::Isometry3d::Identity(), ka);
  ASSERT_GE(kb, 0);
  // Nothing linked them by id; the first keyframe is near and looks the same
  // way, so its points are projected into the second and found there again.
  int shared = 0;
  for (int i : b.point_index) shared += std::count(a.point_index.begin(), a.point_index.end(), i) > 0;
  std::printf("%d points seen by both; fused %llu, observations added %llu; %d points in the map\n", shared,
              static_cast<unsigned long long>(mapper.stats().points_fused),
              static_cast<unsigned long long>(mapper.stats().observations_added), m.num_points());
  EXPECT_GT(static_cast<double>(mapper.stats().points_fused), 0.8 * shared);
  int32_t nb[4], w[4];
  ASSERT_EQ(m.covisible(kb, 1, 4, nb, w), 1);
  EXPECT_EQ(nb[0], ka);
  EXPECT_GT(w[0], 0.8 * shared);
}

}  // namespace
}  // namespace kestrel::map_test

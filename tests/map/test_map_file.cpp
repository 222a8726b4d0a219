// The map file (core/map/map_file.hpp): a round trip keeps every keyframe,
// feature, observation and point; damaged, truncated, foreign, other-version,
// other-vocabulary, other-camera and too-large images are refused with a
// message that says which, and never crash the decoder.
#include <gtest/gtest.h>

#include <random>

#include "kestrel/core/bytes.hpp"
#include "kestrel/core/map_file.hpp"
#include "map_sim.hpp"

namespace kestrel::map_test {
namespace {

struct Fixture {
  SimRoom room{3000, 41};
  std::shared_ptr<const core::Vocabulary> vocab = room_vocabulary(room);
  DriftedMap dm{vocab};
  Fixture() {
    std::mt19937_64 rng(7);
    for (int k = 0; k < 12; ++k) {
      const double a = 2 * M_PI * k / 12;
      const Eigen::Isometry3d T = SimRoom::camera(Eigen::Vector3d(std::cos(a), std::sin(a), 1.5), a);
      dm.add(room, T, T, static_cast<int64_t>(k) * 300'000'000, 1 + 10000u * static_cast<uint32_t>(k / 2),
             rng);
    }
  }
  std::unique_ptr<core::Map> empty(int max_keyframes = 200, int max_points = 60000) const {
    core::MapOptions o;
    o.max_keyframes = max_keyframes;
    o.max_points = max_points;
    return std::make_unique<core::Map>(o, 300, vocab);
  }
};

std::string decode(const std::vector<uint8_t>& b, core::Map& m, const core::MapCamera& cam = sim_camera()) {
  return core::decode_map(b.data(), b.size(), cam, &m);
}

TEST(MapFile, RoundTripKeepsKeyframesPointsAndObservations) {
  Fixture f;
  const core::Map& a = f.dm.map;
  ASSERT_GT(a.num_points(), 500);
  const std::vector<uint8_t> bytes = core::encode_map(a, sim_camera());
  auto b = f.empty();
  core::MapFileInfo info;
  ASSERT_EQ(core::decode_map(bytes.data(), bytes.size(), sim_camera(), b.get(), &info), "");
  EXPECT_EQ(info.keyframes, a.num_keyframes());
  EXPECT_EQ(info.points, a.num_points());
  EXPECT_EQ(info.vocabulary_checksum, f.vocab->checksum());
  ASSERT_EQ(b->num_keyframes(), a.num_keyframes());
  ASSERT_EQ(b->num_points(), a.num_points());
  // Keyframe by keyframe in id order: poses, features, and the point each observes.
  std::vector<int> ka, kb;
  a.for_each_keyframe([&](int k) { ka.push_back(k); });
  b->for_each_keyframe([&](int k) { kb.push_back(k); });
  auto by_id = [](const core::Map& m) {
    return [&m](int x, int y) { return m.keyframe(x).id < m.keyframe(y).id; };
  };
  std::sort(ka.begin(), ka.end(), by_id(a));
  std::sort(kb.begin(), kb.end(), by_id(*b));
  size_t observations = 0;
  for (size_t i = 0; i < ka.size(); ++i) {
    const core::MapKeyframe& A = a.keyframe(ka[i]);
    const core::MapKeyframe& B = b->keyframe(kb[i]);
    EXPECT_EQ(A.t_ns, B.t_ns);
    EXPECT_TRUE(A.T_MC.isApprox(B.T_MC, 1e-12));
    EXPECT_TRUE(A.T_WC.isApprox(B.T_WC, 1e-12));
    EXPECT_EQ(B.session, 1u) << "a loaded keyframe is another session's";
    EXPECT_EQ(A.n_bow, B.n_bow) << "the BoW vector is made again from the same descriptors";
    ASSERT_EQ(A.n, B.n);
    for (int j = 0; j < A.n; ++j) {
      EXPECT_EQ(a.feature(ka[i], j).desc, b->feature(kb[i], j).desc);
      EXPECT_EQ(a.feature(ka[i], j).depth_m, b->feature(kb[i], j).depth_m);
      const int pa = a.point_of(ka[i], j), pb = b->point_of(kb[i], j);
      ASSERT_EQ(pa < 0, pb < 0);
      if (pa < 0) continue;
      ++observations;
      EXPECT_EQ(a.point(pa).p_M, b->point(pb).p_M);
      EXPECT_EQ(a.point(pa).desc, b->point(pb).desc);
      EXPECT_GE(b->point(pb).landmark_id, 0x80000000u)
          << "loaded points get ids this flight's tracker never gives";
      EXPECT_EQ(b->feature(kb[i], j).landmark_id, b->point(pb).landmark_id);
    }
  }
  EXPECT_GT(observations, 1000u);
  // The same bytes again from the loaded map (ids aside, nothing was lost or added).
  EXPECT_EQ(core::encode_map(*b, sim_camera()), bytes);
}

TEST(MapFile, DamagedForeignAndMismatchedFilesAreRefusedWithTheReason) {
  Fixture f;
  const std::vector<uint8_t> good = core::encode_map(f.dm.map, sim_camera());
  auto expect_refused = [&](std::vector<uint8_t> bytes, const std::string& reason, const core::MapCamera& cam,
                            const char* what) {
    auto m = f.empty();
    const std::string e = decode(bytes, *m, cam);
    EXPECT_NE(e.find(reason), std::string::npos) << what << ": got '" << e << "'";
  };
  {
    std::vector<uint8_t> b(good.begin(), good.begin() + static_cast<long>(good.size() / 2));
    expect_refused(b, "truncated", sim_camera(), "truncated");
  }
  {
    std::vector<uint8_t> b = good;
    b[b.size() / 3] ^= 0x10;
    expect_refused(b, "checksum mismatch", sim_camera(), "a flipped byte");
  }
  {
    std::vector<uint8_t> b = good;
    b[0] = 'X';
    expect_refused(b, "not a KMAP file", sim_camera(), "foreign magic");
  }
  {
    std::vector<uint8_t> b = good;
    b[4] = static_cast<uint8_t>(core::kMapVersion + 1);
    expect_refused(b, "format version", sim_camera(), "another version");
  }
  {
    core::MapCamera other = sim_camera();
    other.K.fx = 310.0;
    expect_refused(good, "another camera", other, "another camera");
  }
  {
    // Another vocabulary of the same size (the same k and levels, another room's descriptors).
    SimRoom other_room(3000, 99);
    core::MapOptions o;
    o.max_keyframes = 200;
    o.max_points = 60000;
    core::Map m(o, 300, room_vocabulary(other_room));
    const std::string e = decode(good, m);
    EXPECT_NE(e.find("another place-recognition vocabulary"), std::string::npos) << e;
  }
  {
    auto small = f.empty(4, 60000);
    const std::string e = decode(good, *small);
    EXPECT_NE(e.find("more than this map's capacity"), std::string::npos) << e;
  }
  {
    // Damage the CRC cannot see: a keyframe's rotation made a shear, the checksum recomputed.
    std::vector<uint8_t> b = good;
    const size_t payload = 16, first_pose = payload + 4 + 4 * 8 + 2 * 4 + 2 * 4 + 8;
    b[first_pose + 7] ^= 0x40;  // the high byte of R(0,0)
    const size_t n = b.size() - 20;
    const uint32_t crc = core::crc32(b.data() + payload, n);
    for (int i = 0; i < 4; ++i)
      b[b.size() - 4 + static_cast<size_t>(i)] = static_cast<uint8_t>(crc >> (8 * i));
    expect_refused(b, "keyframe 0: its pose is not a rigid transform", sim_camera(), "a non-rigid pose");
  }
  // Every prefix of a short map decodes to an error, never a crash or a read past the end.
  {
    DriftedMap tiny(f.vocab);
    std::mt19937_64 rng(1);
    tiny.add(f.room, SimRoom::camera(Eigen::Vector3d(0, 0, 1.5), 0.3),
             SimRoom::camera(Eigen::Vector3d(0, 0, 1.5), 0.3), 0, 1, rng);
    const std::vector<uint8_t> t = core::encode_map(tiny.map, sim_camera());
    for (size_t len = 0; len < t.size(); len += 97) {
      auto m = f.empty();
      EXPECT_NE(core::decode_map(t.data(), len, sim_camera(), m.get()), "") << len;
    }
  }
}

}  // namespace
}  // namespace kestrel::map_test

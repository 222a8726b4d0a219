// The dense map's viewer stream (tools/dense/dense_view.hpp, issue 44 item 3)
// without a browser: the encoding decodes to the map's surface within the
// quantisation, only blocks that changed are sent again, evicted or cleared
// blocks are sent as removed, a byte limit per message holds and a round that
// stops at it resumes where it stopped, and the byte budget holds the stream
// under its kbit/s cap.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <map>
#include <vector>

#include "kestrel/core/tsdf_map.hpp"
#include "kestrel/dense/dense_view.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/tools/sim_render.hpp"

namespace kestrel {
namespace {

struct Rendered {
  tools::Scene scene;
  CameraIntrinsics cam;
  DepthModel dm;
  std::vector<uint8_t> rgb;
  std::vector<uint16_t> depth;
  Rendered() {
    scene.room = Eigen::AlignedBox3d(Eigen::Vector3d(-2.5, -2.0, 0.0), Eigen::Vector3d(2.5, 2.0, 2.8));
    tools::SceneBox b;
    b.center_W = {1.2, 0.3, 0.4};
    b.half_m = {0.3, 0.3, 0.4};
    scene.boxes = {b};
    cam.width = 160;
    cam.height = 120;
    cam.fx = cam.fy = 131.25;
    cam.cx = 79.5;
    cam.cy = 59.5;
    rgb.resize(3 * 160 * 120);
    depth.resize(160 * 120);
  }
  void fuse(core::TsdfMap& map, double yaw) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    const Eigen::Vector3d fwd(std::cos(yaw), std::sin(yaw), -0.2);
    Eigen::Matrix3d R;
    R.col(2) = fwd.normalized();
    R.col(0) = R.col(2).cross(Eigen::Vector3d::UnitZ()).normalized();
    R.col(1) = R.col(2).cross(R.col(0));
    T.linear() = R;
    T.translation() = Eigen::Vector3d(0, 0, 1.3);
    tools::RenderOptions ro;
    ro.threads = 1;
    tools::Renderer r(scene, cam, dm, ro);
    r.render(T, 1, rgb.data(), depth.data());
    const ImageView dv{cam.width, cam.height, 2 * cam.width, PixelFormat::kDepthU16,
                       reinterpret_cast<const uint8_t*>(depth.data())};
    const ImageView cv{cam.width, cam.height, 3 * cam.width, PixelFormat::kRgb8, rgb.data()};
    map.integrate(dv, cv, cam, dm, T);
  }
};

core::TsdfOptions small_map() {
  core::TsdfOptions o;
  o.memory_budget_mb = 8;
  return o;
}

int used_blocks_with_surface(const core::TsdfMap& m) {
  std::vector<core::SurfacePoint> buf(dense::kDenseViewMaxBlockPoints);
  int n = 0;
  for (int b = 0; b < m.block_capacity(); ++b) n += m.block_used(b) ? 1 : 0;
  return n;
}

TEST(DenseView, DecodesToTheSurfaceAndResendsOnlyChangedBlocks) {
  Rendered w;
  core::TsdfMap map(small_map());
  w.fuse(map, 0.0);
  dense::DenseViewEncoder enc(map);
  std::vector<uint8_t> buf(4 << 20);
  const std::size_t n = enc.encode(buf.data(), buf.size());
  ASSERT_GT(n, dense::kDenseViewHeaderBytes);
  const std::vector<dense::DenseViewBlock> blocks = dense::decode_dense_view(buf.data(), n);
  EXPECT_EQ(static_cast<int>(blocks.size()), used_blocks_with_surface(map));  // every block, surface or not
  // Block by block, in the order the map gives them: within half a quantisation step.
  const double step = 1.25 * map.block_size_m() / 255.0;
  std::vector<core::SurfacePoint> ref(dense::kDenseViewMaxBlockPoints);
  std::map<std::tuple<int, int, int>, int> slot_of;
  for (int b = 0; b < map.block_capacity(); ++b)
    if (map.block_used(b))
      slot_of[{map.block_key_of(b).x(), map.block_key_of(b).y(), map.block_key_of(b).z()}] = b;
  std::size_t points = 0;
  double worst = 0;
  for (const dense::DenseViewBlock& b : blocks) {
    const int slot = slot_of.at({b.key.x(), b.key.y(), b.key.z()});
    const int k = map.extract_block_surface(slot, ref.data(), static_cast<int>(ref.size()));
    ASSERT_EQ(static_cast<int>(b.points.size()), k);
    for (int i = 0; i < k; ++i) {
      worst = std::max(worst, static_cast<double>((b.points[i].p - ref[i].p).cwiseAbs().maxCoeff()));
      EXPECT_EQ(b.points[i].rgb[0], ref[i].rgb[0]);
    }
    points += b.points.size();
  }
  std::vector<core::SurfacePoint> all;
  map.extract_surface(all);
  EXPECT_EQ(points, all.size());
  EXPECT_LE(worst, 0.5 * step + 1e-5);
  EXPECT_GT(points, 300u);

  // Nothing changed: nothing sent.
  EXPECT_EQ(enc.encode(buf.data(), buf.size()), 0u);
  // Another view: exactly the blocks that frame listed, nothing else.
  const uint64_t frames = map.counters().frames;
  w.fuse(map, 1.5);
  int listed = 0;
  for (int b = 0; b < map.block_capacity(); ++b)
    listed += map.block_used(b) && map.block_updated(b) > frames ? 1 : 0;
  const uint64_t before = rt::alloc_count_this_thread();
  const std::size_t n2 = enc.encode(buf.data(), buf.size());
  EXPECT_EQ(rt::alloc_count_this_thread() - before, 0u);
  ASSERT_GT(listed, 0);
  EXPECT_EQ(static_cast<int>(dense::decode_dense_view(buf.data(), n2).size()), listed);
  EXPECT_LT(listed, used_blocks_with_surface(map));

  // A browser connects: everything again.
  enc.request_all();
  EXPECT_EQ(static_cast<int>(dense::decode_dense_view(buf.data(), enc.encode(buf.data(), buf.size())).size()),
            used_blocks_with_surface(map));

  // The map cleared (a re-integration starts): every block sent is removed.
  const int had = used_blocks_with_surface(map);
  map.clear();
  enc.reset();
  const std::vector<dense::DenseViewBlock> gone =
      dense::decode_dense_view(buf.data(), enc.encode(buf.data(), buf.size()));
  EXPECT_EQ(static_cast<int>(gone.size()), had);
  for (const dense::DenseViewBlock& b : gone) EXPECT_TRUE(b.points.empty());
}

TEST(DenseView, AMessageLimitHoldsAndTheNextRoundResumes) {
  Rendered w;
  core::TsdfMap map(small_map());
  w.fuse(map, 0.0);
  w.fuse(map, 2.5);
  dense::DenseViewEncoder enc(map);
  std::vector<uint8_t> buf(dense::kDenseViewMinMessageBytes);
  std::map<std::tuple<int, int, int>, int> seen;
  int rounds = 0;
  for (std::size_t n; (n = enc.encode(buf.data(), buf.size())) > 0; ++rounds) {
    ASSERT_LE(n, buf.size());
    for (const dense::DenseViewBlock& b : dense::decode_dense_view(buf.data(), n))
      ++seen[{b.key.x(), b.key.y(), b.key.z()}];
    ASSERT_LT(rounds, 100000);
  }
  EXPECT_GT(rounds, 1);
  EXPECT_GT(enc.counters().rounds_full, 0u);
  EXPECT_EQ(static_cast<int>(seen.size()), used_blocks_with_surface(map));
  for (const auto& kv : seen) EXPECT_EQ(kv.second, 1);  // none twice
  // Too small for one block: nothing, rather than a block cut in half.
  EXPECT_EQ(enc.encode(buf.data(), dense::kDenseViewMinMessageBytes - 1), 0u);
}

TEST(DenseView, TheByteBudgetHoldsTheStreamUnderItsCap) {
  constexpr double kKbps = 800;  // 100 kB/s
  constexpr double kBurstS = 0.5;
  dense::ByteBudget budget(kKbps, kBurstS);
  EXPECT_EQ(budget.available(0), 50'000u);  // a full bucket first
  budget.spend(50'000);
  EXPECT_EQ(budget.available(100'000'000), 10'000u);       // 0.1 s later
  EXPECT_EQ(budget.available(10'000'000'000LL), 50'000u);  // never more than the burst
  // A greedy sender polling every 10 ms for 20 s with 9 kB messages.
  dense::ByteBudget b2(kKbps, kBurstS);
  std::size_t sent = 0;
  for (int64_t t = 0; t <= 20'000'000'000LL; t += 10'000'000) {
    while (b2.available(t) >= 9000) {
      b2.spend(9000);
      sent += 9000;
    }
  }
  EXPECT_LE(sent, static_cast<std::size_t>(100'000 * 20 + 50'000));
  EXPECT_GE(sent, static_cast<std::size_t>(100'000 * 20 - 9000));
}

TEST(DenseView, MalformedMessagesAreRefusedNamingTheByte) {
  std::vector<uint8_t> m(dense::kDenseViewHeaderBytes + dense::kDenseViewRecordBytes, 0);
  m[0] = dense::kDenseViewMessageType;
  const uint32_t one = 1;
  const float bs = 0.4f, r = 0.5f;
  std::memcpy(&m[4], &one, 4);
  std::memcpy(&m[8], &bs, 4);
  std::memcpy(&m[12], &r, 4);
  const uint16_t n = 3;  // three points announced, none there
  std::memcpy(&m[dense::kDenseViewHeaderBytes + 12], &n, 2);
  try {
    dense::decode_dense_view(m.data(), m.size());
    FAIL() << "cut-short points accepted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("byte 30"), std::string::npos) << e.what();
  }
  m[0] = 1;
  EXPECT_THROW(dense::decode_dense_view(m.data(), m.size()), std::runtime_error);
}

}  // namespace
}  // namespace kestrel

// The ROS outputs' topics (tools/kestrel/ros2_topics.*) on hand-made poses: a
// closed loop is drawn as it happens (one loop_edges segment per closure,
// between the two keyframes the map state names), not only at the end. The
// Marker encoding itself is decoded by @foxglove/rosmsg2-serialization in
// test_rosbag2_npm (the final loop edges).
#include <gtest/gtest.h>

#include <cstring>
#include <vector>

#include "kestrel/ros2_topics.hpp"

namespace kestrel::cli {
namespace {

struct Captured : Ros2Sink {
  std::vector<std::pair<Ros2Topic, std::vector<uint8_t>>> msgs;
  void publish(Ros2Topic topic, int64_t, const std::vector<uint8_t>& cdr) override {
    msgs.emplace_back(topic, cdr);
  }
  std::vector<std::vector<uint8_t>> of(Ros2Topic t) const {
    std::vector<std::vector<uint8_t>> out;
    for (const auto& m : msgs)
      if (m.first == t) out.push_back(m.second);
    return out;
  }
};

bool contains(const std::vector<uint8_t>& b, const void* what, size_t n) {
  for (size_t i = 0; i + n <= b.size(); ++i)
    if (std::memcmp(b.data() + i, what, n) == 0) return true;
  return false;
}

TEST(Ros2Topics, AClosedLoopIsDrawnWhenItClosesOncePerLoop) {
  Captured sink;
  Ros2Output out(sink);
  core::PoseSample s;
  s.quality = core::TrackingQuality::kTracking;
  s.map.active = true;
  s.map.localized = true;
  for (int k = 0; k < 30; ++k) {
    s.t_ns = 1'000'000'000 + k * 50'000'000LL;
    if (k == 10 || k == 20) {
      ++s.map.loop_closures;
      ++s.map.alignment;
      const double q[3] = {1.25 + k, -0.5, 1.5}, c[3] = {0.75, 2.0 + k, 1.25};
      std::memcpy(s.map.loop_p_M_query, q, sizeof q);
      std::memcpy(s.map.loop_p_M_candidate, c, sizeof c);
    }
    out.on_pose(s);
  }
  const std::vector<std::vector<uint8_t>> markers = sink.of(Ros2Topic::kMarkers);
  ASSERT_EQ(markers.size(), 2u) << "one marker message per closed loop, none otherwise";
  for (int i = 0; i < 2; ++i) {
    const double qx = 1.25 + (i == 0 ? 10 : 20), cy = 2.0 + (i == 0 ? 10 : 20);
    EXPECT_TRUE(contains(markers[static_cast<size_t>(i)], "loop_edges", 10));
    EXPECT_TRUE(contains(markers[static_cast<size_t>(i)], &qx, sizeof qx)) << "the query keyframe's x";
    EXPECT_TRUE(contains(markers[static_cast<size_t>(i)], &cy, sizeof cy)) << "the candidate keyframe's y";
  }
  // Without a map nothing is drawn.
  Captured none;
  Ros2Output out2(none);
  s.map = core::MapFrameState{};
  s.t_ns = 5'000'000'000;
  out2.on_pose(s);
  EXPECT_TRUE(none.of(Ros2Topic::kMarkers).empty());
}

}  // namespace
}  // namespace kestrel::cli

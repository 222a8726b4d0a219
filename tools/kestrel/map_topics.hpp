// The map as it grows, handed from the estimator thread to the output thread
// for the ROS outputs (--mcap-out, --foxglove: PointCloud2 and keyframe
// markers; docs/ros2.md). The estimator thread copies, into memory sized at
// start-up, the tracker's local map points at most map_points_rate_hz (log
// time, so lockstep replays write the same file) and every new keyframe's
// camera pose; it never waits: a full ring or pool drops and counts.
#pragma once

#include <atomic>
#include <cstdint>

#include "kestrel/core/estimator.hpp"
#include "kestrel/rt/object_pool.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::core {
class Tracker;
}

namespace kestrel::cli {

// The viewer's bound (viewer::kMaxMapPoints): a local map larger than this is subsampled evenly.
inline constexpr int kMapCloudMaxPoints = 8192;

struct MapCloud {
  int64_t t_ns = 0;
  int n = 0;
  float xyz_W[3 * kMapCloudMaxPoints]{};  // p_W [m], x y z per point
};

struct KeyframePose {
  int64_t t_ns = 0;
  double p_WC[3] = {0, 0, 0};
  double q_WC[4] = {1, 0, 0, 0};  // w x y z
};

class MapTopicsFeed {
 public:
  static constexpr std::size_t kPoolSize = 3;
  // Allocates the pool: call at start-up. map_points_rate_hz <= 0: no points,
  // keyframes only.
  MapTopicsFeed(const core::Estimator& est, double map_points_rate_hz);
  MapTopicsFeed(const MapTopicsFeed&) = delete;
  MapTopicsFeed& operator=(const MapTopicsFeed&) = delete;
  // False for a backend without the tracker (imu): nothing is ever handed over.
  bool active() const noexcept { return tracker_ != nullptr; }

  // ---- estimator thread, after each add_frame: no allocation, lock or wait.
  void on_frame(int64_t t_ns) noexcept;

  // ---- output thread.
  bool pop_keyframe(KeyframePose& out) noexcept { return keyframes_.try_pop(out); }
  // The oldest cloud not yet taken, or nullptr; hand it back with release().
  const MapCloud* take_cloud(rt::PoolHandle* handle) noexcept;
  void release(rt::PoolHandle h) noexcept { pool_.release(h); }

  // ---- any thread (approximate while running).
  uint64_t clouds_published() const noexcept { return clouds_.load(std::memory_order_relaxed); }
  uint64_t clouds_dropped() const noexcept { return clouds_dropped_.load(std::memory_order_relaxed); }
  uint64_t keyframes_dropped() const noexcept { return keyframes_.drops(); }

 private:
  const core::Tracker* tracker_;
  int64_t period_ns_;
  rt::ObjectPool<MapCloud, kPoolSize> pool_;
  rt::SpscRing<rt::PoolHandle, kPoolSize> ring_;
  rt::SpscRing<KeyframePose, 256> keyframes_;
  std::atomic<uint64_t> clouds_{0}, clouds_dropped_{0};
  // Estimator-thread state.
  int64_t last_cloud_t_ns_ = INT64_MIN;
  int64_t last_keyframe_t_ns_ = -1;
  bool keyframe_since_cloud_ = false;
};

}  // namespace kestrel::cli

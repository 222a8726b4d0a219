// The estimator -> viewer hand-off (docs/viewer.md).
//
// The estimator thread fills fixed-size snapshots taken from a pool sized at
// start-up and passes their handles through an SPSC ring; the viewer thread
// (kst-viewer) encodes and sends them, then gives the slot back. The
// estimator side never allocates, never locks and never waits: with no
// browser connected it only updates a few maxima, and when the viewer still
// holds every slot or the ring is full it skips the snapshot and counts it.
// A slow or absent browser therefore costs the estimator nothing but the
// copy of a downscaled image at most `max_rate_hz` times a second.
#pragma once

#include <atomic>
#include <cstdint>

#include "kestrel/core/estimator.hpp"
#include "kestrel/core/tracker.hpp"
#include "kestrel/msgs.hpp"
#include "kestrel/rt/object_pool.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::viewer {

// Preview sizes: the colour image is subsampled by the smallest integer
// factor that fits it in 320 x 240 (VGA: 2), depth in 160 x 120 (VGA: 4).
inline constexpr int kPreviewMaxWidth = 320;
inline constexpr int kPreviewMaxHeight = 240;
inline constexpr int kDepthMaxWidth = 160;
inline constexpr int kDepthMaxHeight = 120;
inline constexpr int kMaxFeatures = 2048;
inline constexpr int kMaxMapPoints = 8192;

// What the caller knows about the frame it just fed (the harness, not the
// estimator): its own timing. The pipeline's drop and fault counts reach the
// viewer through its perf registry (Server::set_counters).
struct FrameInfo {
  int64_t tracking_ns = 0;         // add_frame's wall time
  int64_t imu_to_pose_max_ns = 0;  // newest IMU sample -> pose, max since the previous frame
  uint64_t frames_fed = 0;         // frames the estimator has taken (this one included)
};

// The state panel's numbers: plain data, one per snapshot.
struct StateSnapshot {
  int64_t t_ns = 0;  // frame time (sensor clock)
  uint32_t seq = 0;
  uint64_t frames_fed = 0;
  core::TrackingQuality quality = core::TrackingQuality::kUninitialized;
  uint32_t reset_counter = 0;
  double p_WB[3] = {0, 0, 0};
  double q_WB[4] = {1, 0, 0, 0};  // w x y z
  double v_WB[3] = {0, 0, 0};
  // The tracker's view of this frame; has_tracker false for backends without one (imu).
  bool has_tracker = false;
  core::TrackStatus track_status = core::TrackStatus::kNoImage;
  bool keyframe = false;
  int detected = 0, with_depth = 0, matched = 0, inliers = 0, map_inliers = 0;
  double inlier_rms_px = 0, area_ratio = 0;
  // Latencies [ns]; *_max over the frames since the previous snapshot.
  int64_t tracking_ns = 0;
  int64_t tracking_max_ns = 0;
  int64_t imu_to_pose_max_ns = 0;
  int64_t optimizer_solve_ns = 0;  // newest solve that reached the tracker (window)
  // Window optimizer counters (has_window false for other backends).
  bool has_window = false;
  uint64_t window_jobs = 0, window_applied = 0, window_failures = 0, window_skipped_busy = 0,
           window_resets = 0;
  // Cumulative counters.
  uint64_t imu_in = 0, frames_in = 0, frames_used = 0, resets = 0, imu_rejected = 0;
  FrameInfo pipeline;
  uint64_t snapshots_skipped = 0;  // the feed found no free slot (the viewer was behind)
};

// One keyframe as the tracker took it: the camera's pose in W.
struct KeyframeMark {
  int64_t t_ns = 0;
  float p_WC[3] = {0, 0, 0};
  float q_WC[4] = {1, 0, 0, 0};  // w x y z
};

struct ViewSnapshot {
  StateSnapshot state;
  // Colour preview, 8-bit RGB, tightly packed; rgb_width == 0 when the frame had none.
  int rgb_width = 0, rgb_height = 0, rgb_step = 1;  // step: source pixels per preview pixel
  uint8_t rgb[kPreviewMaxWidth * kPreviewMaxHeight * 3]{};
  // Depth preview in the rig's units (0 = invalid); depth_width == 0 when absent.
  int depth_width = 0, depth_height = 0, depth_step = 1;
  uint16_t depth[kDepthMaxWidth * kDepthMaxHeight]{};
  int n_features = 0;  // full-resolution pixel coordinates
  core::FeatureMark features[kMaxFeatures];
  bool has_map = false;  // the local map, sent now and then (not in every snapshot)
  int n_map = 0;
  float map_xyz[3 * kMaxMapPoints]{};
};

struct FeedOptions {
  double max_rate_hz = 10.0;  // snapshots per second of wall time, at most
  double map_period_s = 1.0;  // the local map at most this often (and after a keyframe only)
};

class ViewerFeed {
 public:
  // The viewer holds one while encoding; one more (with its place in the ring)
  // is kept for a forced snapshot, so the frame a paused replay holds at always
  // reaches the page: no later frame would carry it.
  static constexpr std::size_t kPoolSize = 5;
  using Pool = rt::ObjectPool<ViewSnapshot, kPoolSize>;

  // Finds the tracker and the window optimizer behind `est` once (either may
  // be absent). Allocates the pool: call at start-up.
  ViewerFeed(const core::Estimator& est, const Rig& rig, const FeedOptions& opt = {});
  ViewerFeed(const ViewerFeed&) = delete;
  ViewerFeed& operator=(const ViewerFeed&) = delete;

  // ---- estimator thread: after each add_frame; no allocation, lock or wait.
  void on_frame(const core::RgbdFrame& f, const FrameInfo& info) noexcept;

  // ---- viewer thread.
  // Set while at least one browser is connected; until then on_frame copies nothing.
  void set_wanted(bool on) noexcept { wanted_.store(on, std::memory_order_relaxed); }
  // The next snapshot carries the map (a browser just connected).
  void request_map() noexcept { map_requested_.store(true, std::memory_order_relaxed); }
  // The next frame is published whatever the rate limit (the frame a paused
  // replay holds at must be the one the page shows).
  void publish_next() noexcept { publish_next_.store(true, std::memory_order_relaxed); }
  // The newest published snapshot (older ones are released), or nullptr.
  // Hand it back with release() when done.
  const ViewSnapshot* take_newest(rt::PoolHandle* handle) noexcept;
  void release(rt::PoolHandle handle) noexcept { pool_.release(handle); }
  bool pop_keyframe(KeyframeMark& out) noexcept { return keyframes_.try_pop(out); }
  // The replay's ground truth as its records pass (the replay feeder pushes).
  using GroundTruthRing = rt::SpscRing<GroundTruthPose, 1024>;
  GroundTruthRing& ground_truth_ring() noexcept { return ground_truth_; }

  // ---- any thread (approximate while running).
  uint64_t published() const noexcept { return published_.load(std::memory_order_relaxed); }
  uint64_t skipped_busy() const noexcept { return skipped_busy_.load(std::memory_order_relaxed); }
  uint64_t keyframes_dropped() const noexcept { return keyframes_.drops(); }
  const Rig& rig() const noexcept { return rig_; }
  const char* estimator_name() const noexcept { return est_.name(); }

 private:
  void fill(ViewSnapshot& s, const core::RgbdFrame& f, const FrameInfo& info, bool with_map) noexcept;

  const core::Estimator& est_;
  const core::Tracker* tracker_;
  Rig rig_;
  int64_t min_period_ns_;
  int64_t map_period_ns_;
  Pool pool_;
  rt::SpscRing<rt::PoolHandle, kPoolSize - 1> ring_;
  rt::SpscRing<KeyframeMark, 64> keyframes_;
  GroundTruthRing ground_truth_;
  std::atomic<bool> wanted_{false};
  std::atomic<bool> map_requested_{false};
  std::atomic<bool> publish_next_{false};
  std::atomic<uint64_t> published_{0};
  std::atomic<uint64_t> skipped_busy_{0};
  // Estimator-thread state.
  int64_t last_publish_wall_ns_ = 0;
  int64_t last_map_wall_ns_ = 0;
  bool keyframe_since_map_ = true;
  int64_t last_keyframe_t_ns_ = -1;
  int64_t tracking_max_ns_ = 0;
  int64_t imu_max_ns_ = 0;
};

// Pause and single-step for replays whose pace allows it (lockstep: one
// thread feeds and drains, so waiting costs nothing but time). The viewer
// thread asks; the replay thread checks before each record.
//
// Pause and step take effect at the next frame, which the feed publishes
// whatever its rate limit: the page then shows the very frame the replay holds
// at (a snapshot goes out at most every 100 ms, so the newest one shown could
// otherwise be a few frames behind).
class PlaybackControl {
 public:
  // feed: told to publish the frame the replay will hold at (may be nullptr).
  PlaybackControl(bool available, ViewerFeed* feed) : available_(available), feed_(feed) {}
  bool available() const noexcept { return available_; }
  bool paused() const noexcept { return paused_.load(std::memory_order_relaxed); }
  // Frames the estimator had taken when the replay last asked (the held frame while paused).
  uint64_t frames() const noexcept { return frames_seen_.load(std::memory_order_relaxed); }
  // Holds after the next frame.
  void pause() noexcept;
  void resume() noexcept;
  // Lets exactly one more frame through, then holds.
  void step() noexcept;
  // Replay thread: may the next record go? `frames_fed` counts the frames
  // the estimator has taken so far.
  bool may_proceed(uint64_t frames_fed) noexcept;

 private:
  bool available_;
  ViewerFeed* feed_;
  std::atomic<bool> paused_{false};
  std::atomic<uint64_t> frames_seen_{0};
  std::atomic<uint64_t> step_until_{0};
};

}  // namespace kestrel::viewer

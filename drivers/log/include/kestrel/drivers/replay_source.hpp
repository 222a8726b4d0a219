// Hardware-in-the-loop replay: a recorded log played into the sensor rings as
// the live drivers would fill them.
#pragma once

#include <atomic>
#include <cstdint>
#include <string>

#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/sensor_rings.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::drivers {

enum class ReplayPace {
  kRealtime,  // records released at their log time on the wall clock; full rings drop, as live
  kFast,      // as fast as the consumer drains; full rings make the feeder wait
  kLockstep,  // the caller alternates step() with draining: deterministic, single thread
};

ReplayPace parse_replay_pace(const std::string& name);  // throws std::invalid_argument
const char* to_string(ReplayPace pace);

struct ReplayStats {
  uint64_t imu_pushed = 0;
  uint64_t frames_pushed = 0;
  uint64_t imu_dropped = 0;       // ring full (realtime pace)
  uint64_t frames_dropped = 0;    // ring full or no free image buffer
  uint64_t images_too_large = 0;  // bigger than the buffers sized at start-up
  uint64_t depth_unpaired = 0;    // a depth image with no colour image at its time
  uint64_t right_unpaired = 0;    // a stereo right image with no left image at its time (mismatched stamps)
  uint64_t ground_truth = 0;      // not fed to the estimator, only counted
  uint64_t events = 0;
  int64_t first_t_ns = -1;
  int64_t last_t_ns = -1;
};

class ReplaySource {
 public:
  // Depth pairs with the colour image it follows when their times differ by
  // at most this much (registered RGB-D cameras stamp both alike).
  static constexpr int64_t kDepthPairingNs = 5'000'000;
  // A stereo pair is triggered together (EuRoC stamps both alike); the same
  // bound, so a right image that belongs to another exposure is refused.
  static constexpr int64_t kRightPairingNs = kDepthPairingNs;
  // How long `--pace fast` sleeps on a full ring before it looks at `stop`
  // again; the consumer's pop wakes it sooner.
  static constexpr int64_t kFullRingWaitNs = 20'000'000;

  ReplaySource(LogSource& log, SensorRings& rings, ReplayPace pace);

  // Ground-truth records also go here as they pass (the live viewer draws
  // them beside the estimate); a full ring drops them (its drops()). Without
  // a ring they are only counted. Set before the first step().
  using GroundTruthRing = rt::SpscRing<GroundTruthPose, 1024>;
  void set_ground_truth_ring(GroundTruthRing* ring) { gt_ring_ = ring; }

  // Moves the next record into the rings (in realtime pace, after sleeping
  // until it is due). Returns false at the end of the log, after flushing a
  // pending frame.
  bool step();

  // The feeder thread's loop: step() until the end or until `stop` is set.
  void run(const std::atomic<bool>& stop);

  bool finished() const { return finished_.load(std::memory_order_acquire); }
  const ReplayStats& stats() const { return stats_; }

 private:
  void emit_pending();
  bool copy_image(const LogImage& img, uint32_t& handle);
  template <class Ring, class T>
  bool push(Ring& ring, rt::Doorbell* bell, const T& value, uint64_t& dropped);
  void finish();
  void wait_until_due(int64_t t_ns);

  LogSource& log_;
  SensorRings& rings_;
  ReplayPace pace_;
  LogRecord rec_;  // reused, so its image vector keeps its capacity
  RgbdFrameMsg pending_{};
  bool have_pending_ = false;
  int64_t wall0_ns_ = -1;
  int64_t log0_ns_ = -1;
  ReplayStats stats_;
  std::atomic<bool> finished_{false};
  const std::atomic<bool>* stop_ = nullptr;
  GroundTruthRing* gt_ring_ = nullptr;
};

}  // namespace kestrel::drivers

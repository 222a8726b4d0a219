// The IMU-rate pose stage shared by `kestrel replay` (realtime pace) and
// `kestrel run`: the consumer of the sensor IMU ring, on its own thread
// (kst-propagate). It forwards every sample to the estimator thread and
// propagates the estimator's newest state (a seqlock mailbox, re-propagated
// over the samples the estimator has not reached yet) to the newest sample at
// once, so the pose never waits while the estimator thread tracks a frame.
// Backend-agnostic: it needs only EstimatorOutput::state. No heap allocation,
// no lock in step() (docs/threads.md).
#pragma once

#include <atomic>
#include <cstdint>

#include "kestrel/core/estimator.hpp"
#include "kestrel/core/imu_propagator.hpp"
#include "kestrel/core/pose_sample.hpp"
#include "kestrel/drivers/sensor_rings.hpp"
#include "kestrel/rt/history_ring.hpp"
#include "kestrel/rt/latency_histogram.hpp"
#include "kestrel/rt/mailbox.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::cli {

using ImuRing = rt::SpscRing<ImuSample, drivers::kImuRingCapacity>;

// The estimator's newest state, handed to the propagation stage.
struct Anchor {
  core::PackedNavState x;
  core::TrackingQuality quality;
  uint32_t reset_counter;
};

Anchor to_anchor(const core::EstimatorOutput& o);

struct ImuRateStats {
  uint64_t forward_drops = 0;          // to-estimator ring full
  uint64_t poses = 0;                  // IMU-rate poses published
  rt::LatencyHistogram imu_to_output;  // ring push (t_recv_ns) -> pose published, after warm-up
  int64_t steady_allocs = 0;           // heap allocations of this thread after warm-up (alloc hook linked)
};

class ImuRateStage {
 public:
  // in: the sensor IMU ring (this stage is its only consumer); to_estimator:
  // every sample, forwarded; anchor: the estimator's state; imu_pose: the
  // newest IMU-rate pose (latest value wins: a slow reader skips poses
  // instead of holding up this thread). warmup_ns of sample time pass before
  // latency and allocations are counted.
  ImuRateStage(ImuRing& in, ImuRing& to_estimator, const rt::Mailbox<Anchor>& anchor, const Rig& rig,
               int64_t warmup_ns, rt::Mailbox<core::PoseSample>& imu_pose);

  // Drains the input ring; false when it was empty.
  bool step();
  // Call on the stage's thread after the last step().
  void finish();
  // Read after the thread stopped.
  const ImuRateStats& stats() const { return stats_; }
  // Any thread, while it runs (the live viewer's latency plot): the largest
  // sample -> pose latency since the previous call [ns].
  int64_t take_recent_max_ns() { return recent_max_ns_.exchange(0, std::memory_order_relaxed); }

 private:
  void refresh_anchor();

  ImuRing& in_;
  ImuRing& to_est_;
  const rt::Mailbox<Anchor>& anchor_;
  core::ImuPropagator prop_;
  int64_t warmup_ns_;
  rt::Mailbox<core::PoseSample>& imu_pose_;
  rt::HistoryRing<ImuSample, 1024> history_;  // 2.5 s at 400 Hz: longer than any tracking step
  uint64_t anchor_version_ = 0;
  bool have_anchor_ = false;
  core::TrackingQuality anchor_quality_ = core::TrackingQuality::kUninitialized;
  uint32_t anchor_reset_counter_ = 0;
  int64_t first_t_ns_ = -1;
  bool counting_ = false;
  uint64_t allocs_at_warmup_ = 0;
  ImuRateStats stats_;
  std::atomic<int64_t> recent_max_ns_{0};
};

}  // namespace kestrel::cli

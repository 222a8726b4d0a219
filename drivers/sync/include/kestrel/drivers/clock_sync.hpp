// Hardware timestamp synchronisation: one module for every clock that is not
// the host's CLOCK_MONOTONIC.
//
//  - ClockSync maps a device clock (the USB bridge's microsecond counter, an
//    OpenNI2 device timestamp, or an IMU's own sample index times its nominal
//    period) onto host time with offset + skew.
//  - StrobeMatcher pairs camera frames with the bridge's exposure-strobe
//    stamps and estimates the residual camera-IMU offset.
//
// Estimator (docs/drivers/usb-imu-bridge.md, "Clock synchronisation"): every
// observation is (device time d, host receive time h) with h = f(d) + latency,
// latency >= floor. Latency jitter only ever makes h later, so the true map is
// a line lying below every point; the line is the lower convex hull edge that
// supports the hull at the mean device time of the window (the linear program
// "maximise the line at mean d subject to staying below all points", as in
// Moon, Skelly & Towsley 1999). Points are first thinned to the lowest one per
// bucket, which bounds the work, and a sliding window follows slow drift
// (temperature). Extreme delays cost nothing: they are never on the envelope.
//
// Real-time: fixed arrays, no allocation, O(window) per bucket close.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>

namespace kestrel::drivers {

// The host clock as protocol state machines see it: injectable, so tests step
// them with a manual clock and never sleep.
class HostClock {
 public:
  virtual ~HostClock() = default;
  virtual int64_t now_ns() const = 0;
};

// CLOCK_MONOTONIC (rt::now_ns).
class MonotonicHostClock final : public HostClock {
 public:
  int64_t now_ns() const override;
};

class ManualClock final : public HostClock {
 public:
  explicit ManualClock(int64_t t0_ns = 0) : t_ns_(t0_ns) {}
  int64_t now_ns() const override { return t_ns_; }
  void set(int64_t t_ns) { t_ns_ = t_ns; }
  void advance(int64_t dt_ns) { t_ns_ += dt_ns; }

 private:
  int64_t t_ns_;
};

struct ClockSyncOptions {
  int64_t bucket_ns = 100'000'000;         // device-time span thinned to one point (lowest latency)
  int max_buckets = 100;                   // window = bucket_ns * max_buckets (10 s)
  int min_buckets_for_skew = 5;            // before this, skew is held at its prior
  double prior_skew = 0.0;                 // host/device rate - 1 assumed until then
  double max_abs_skew = 0.002;             // a fit beyond this is a fault (2000 ppm)
  int64_t latency_floor_ns = 0;            // calibrated constant transport latency, subtracted
  int64_t jump_threshold_ns = 50'000'000;  // a point this far below the line means the clock jumped
};

class ClockSync {
 public:
  static constexpr int kMaxBuckets = 256;

  ClockSync() = default;
  explicit ClockSync(const ClockSyncOptions& o) : opt_(o) { skew_ = o.prior_skew; }

  // One observation. Returns false (and resets, counted) when it shows a
  // clock jump: device time going backwards, or a point far below the line.
  bool add(int64_t device_ns, int64_t host_ns);
  void reset();

  bool valid() const { return n_points_total_ > 0; }
  // Host time of a device time (extrapolates beyond the window with the line).
  int64_t to_host_ns(int64_t device_ns) const;
  // d host / d device - 1 (positive: the device clock runs slow).
  double skew() const { return skew_; }
  int64_t offset_at_ns(int64_t device_ns) const { return to_host_ns(device_ns) - device_ns; }
  // Mean latency above the envelope over the window (jitter indicator).
  double mean_excess_latency_ns() const { return mean_excess_ns_; }
  uint64_t jumps() const { return jumps_; }
  uint64_t skew_faults() const { return skew_faults_; }
  int buckets() const { return count_ + (open_ ? 1 : 0); }
  const ClockSyncOptions& options() const { return opt_; }

 private:
  struct Point {
    int64_t d = 0;  // device ns
    int64_t h = 0;  // host ns
  };
  void close_bucket();
  void refit();
  Point& at(int i) { return pts_[static_cast<size_t>((first_ + i) % kMaxBuckets)]; }

  ClockSyncOptions opt_;
  std::array<Point, kMaxBuckets> pts_{};
  int first_ = 0;
  int count_ = 0;
  bool open_ = false;
  Point cur_;  // lowest point of the open bucket
  int64_t cur_bucket_ = 0;
  // Fitted line: host = base_h_ + (d - base_d_) * (1 + skew_)
  int64_t base_d_ = 0;
  int64_t base_h_origin_ = 0;
  double skew_ = 0.0;
  double mean_excess_ns_ = 0.0;
  int64_t last_d_ = 0;
  uint64_t n_points_total_ = 0;
  uint64_t jumps_ = 0;
  uint64_t skew_faults_ = 0;
  // Scratch for the hull (fixed, no allocation).
  std::array<Point, kMaxBuckets + 1> scratch_{};
  std::array<int, kMaxBuckets + 1> hull_{};
};

// An exposure strobe stamped by the bridge, already mapped to host time.
struct StrobeStamp {
  int64_t t_host_ns = 0;  // start of exposure
  uint32_t seq = 0;
  int32_t duration_us = 0;  // 0 when the bridge did not see the falling edge
};

struct StrobeMatchOptions {
  // Camera timestamp minus strobe time expected before any match (driver
  // latency of an end-of-frame stamp, roughly a frame period); then learnt.
  int64_t initial_offset_ns = 0;
  int64_t tolerance_ns = 8'000'000;  // a strobe further than this from the prediction is not this frame's
  double offset_gain = 0.05;         // residual offset low-pass (per matched frame)
};

struct StrobeMatch {
  bool matched = false;
  int64_t t_exposure_start_ns = 0;  // from the strobe, or camera time minus the learnt offset
  int64_t residual_ns = 0;          // camera time - strobe time for this frame (0 when unmatched)
  uint32_t strobe_seq = 0;
};

class StrobeMatcher {
 public:
  static constexpr int kHistory = 64;
  StrobeMatcher() = default;
  explicit StrobeMatcher(const StrobeMatchOptions& o)
      : opt_(o), offset_ns_(static_cast<double>(o.initial_offset_ns)) {}

  void add_strobe(const StrobeStamp& s);
  // Pairs a frame with the nearest unused strobe around t_camera - offset.
  StrobeMatch match(int64_t t_camera_ns);

  // The residual camera-IMU offset: camera timestamp - true exposure start,
  // low-passed over matched frames. Feed it to Rig::time_offset_cam_imu_ns
  // when frames are stamped by the camera alone.
  int64_t residual_offset_ns() const { return static_cast<int64_t>(offset_ns_); }
  double residual_rms_ns() const;
  uint64_t matched() const { return matched_; }
  uint64_t unmatched_frames() const { return unmatched_; }
  uint64_t strobes_unused() const { return unused_; }

 private:
  StrobeMatchOptions opt_;
  std::array<StrobeStamp, kHistory> hist_{};
  std::array<bool, kHistory> used_{};
  int head_ = 0;  // next write
  int size_ = 0;
  double offset_ns_ = 0.0;
  bool have_offset_ = false;
  double sum_sq_dev_ = 0.0;
  uint64_t matched_ = 0;
  uint64_t unmatched_ = 0;
  uint64_t unused_ = 0;
};

}  // namespace kestrel::drivers

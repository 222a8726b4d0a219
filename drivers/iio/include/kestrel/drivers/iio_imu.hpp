// Linux IIO IMU: the protocol. One combined device (accel and anglvel in one
// scan: BMI088 / ICM-42688 / LSM6DS drivers), or separate accelerometer and
// gyroscope devices at their own rates (RealSense D4xx HID: gyro 200 Hz,
// accel 100 Hz), merged onto the faster stream's stamps by interpolating the
// slower one.
//
//   open: find by name -> timestamp clock -> sampling frequency -> scan
//         elements -> scales -> buffer on (iio_device.hpp)
//   step: poll() the device nodes -> read -> RecordFramer -> decode ->
//         clock map -> merge -> ImuSink
//
// Time (docs/drivers/iio.md, "Time"): the kernel stamps each scan on the
// device's current_timestamp_clock, or a device gives its own hardware stamp
// (HID sensors). Both streams' stamps are on one clock, so the merge
// interpolates in device time; the output is mapped to the host clock by a
// ClockSync fed with (newest stamp of a read, host time of the read). When the
// stamps are already CLOCK_MONOTONIC (checked on the first read, not assumed)
// the sync is fed (stamp, stamp): an identity that still goes through the
// same reset handling.
//
// Real-time: step() allocates nothing and takes no lock: fixed rings, events
// are string literals.
#pragma once

#include <array>
#include <cstdint>
#include <string>

#include "kestrel/drivers/bmx055.hpp"  // ImuSink
#include "kestrel/drivers/clock_sync.hpp"
#include "kestrel/drivers/iio_device.hpp"
#include "kestrel/drivers/iio_scan.hpp"

namespace kestrel::drivers::iio {

struct ImuConfig {
  std::string sysfs_root = kDefaultSysfsRoot;
  std::string dev_root = kDefaultDevRoot;
  std::string device;  // a combined device's name; "" = accel_device + gyro_device
  std::string accel_device;
  std::string gyro_device;
  double rate_hz = 200;        // combined device (<= 0: leave the device's)
  double accel_rate_hz = 100;  // separate devices
  double gyro_rate_hz = 200;
  std::string timestamp_clock = "monotonic";
  int buffer_length_samples = 512;
  int watermark_samples = 1;
  int read_timeout_ms = 20;
  int64_t stall_timeout_ns = 200'000'000;
  int64_t max_stamp_gap_ns = 1'000'000'000;
  int resync_records = 4;
  std::array<int8_t, 3> axis_remap{1, 2, 3};  // as bmx055::Config::axis_remap
  ClockSyncOptions clock;
  bool combined() const { return !device.empty(); }
  void validate() const;  // throws std::invalid_argument naming the field
};

enum class ImuState : uint8_t { kClosed, kWaiting, kStreaming, kStalled, kDisconnected };
const char* to_string(ImuState s);

struct ImuCounters {
  uint64_t reads = 0;  // read() calls that returned bytes
  uint64_t bytes = 0;
  uint64_t samples = 0;  // pushed
  uint64_t sink_drops = 0;
  uint64_t stalls = 0;             // a stream silent for stall_timeout
  uint64_t secondary_held = 0;     // the slower stream had nothing after a sample: its newest value held
  uint64_t secondary_missing = 0;  // samples dropped for want of any slower-stream value before them
  uint64_t secondary_gap_interpolations = 0;  // interpolated across a gap in the slower stream
  uint64_t acc_saturated = 0;
  uint64_t gyro_saturated = 0;
  uint64_t non_finite = 0;         // dropped
  uint64_t time_clamped = 0;       // a mapped time not after the previous output
  uint64_t clock_jumps = 0;        // ClockSync restarted
  uint64_t not_host_clock = 0;     // asked for monotonic stamps, got another clock (HID hardware stamps)
  uint64_t pending_overflows = 0;  // the merge queue was full: the oldest went out with a held value
  uint64_t read_errors = 0;
  uint64_t dropped_on_reset = 0;  // queued samples dropped when a stream's clock restarted
};

class ImuDriver {
 public:
  ImuDriver(const HostClock& clock, const ImuConfig& cfg);
  ~ImuDriver();
  ImuDriver(const ImuDriver&) = delete;
  ImuDriver& operator=(const ImuDriver&) = delete;

  // Start-up (allocates): "" or an error naming the sysfs file / node.
  std::string open();
  void close();
  bool is_open() const;

  // Waits up to read_timeout_ms on the device nodes, reads, delivers. Never
  // waits on the sink.
  ImuState step(ImuSink& sink);

  ImuState state() const { return state_; }
  const ImuCounters& counters() const { return counters_; }
  int streams() const { return n_streams_; }
  const Device& device(int i) const { return streams_[static_cast<size_t>(i)].dev; }
  const FramerCounters& framer_counters(int i) const {
    return streams_[static_cast<size_t>(i)].framer.counters();
  }
  FramerCounters framer_totals() const;
  const ClockSync& clock_sync() const { return sync_; }
  bool stamps_on_host_clock() const { return host_stamps_; }
  // Smallest / largest (host read time - stamp) of the faster stream's reads: the delivery latency when
  // the stamps are host time, the clock offset otherwise.
  int64_t min_read_lag_ns() const { return min_lag_ns_; }
  int64_t max_read_lag_ns() const { return max_lag_ns_; }
  std::string description() const;
  std::string report() const;  // one line of counters

 private:
  struct Stream {
    Device dev;
    RecordFramer framer;
    bool accel = false, gyro = false;
    int64_t last_data_ns = 0;
    bool stalled = false;
    bool got = false;
    int64_t newest_t_dev = 0;
  };
  struct Pending {
    int64_t t_dev = 0;
    int64_t t_rx = 0;
    Vec3d acc{}, gyro{};
    bool acc_sat = false, gyro_sat = false;
    bool complete = false;  // a combined record: needs no interpolation
    uint32_t lost = 0;
  };
  struct SecondaryPoint {
    int64_t t_dev = 0;
    Vec3d v{};
    bool sat = false;
  };
  static constexpr size_t kPendingCap = 1024;
  static constexpr size_t kHistoryCap = 32;

  void read_stream(int i, int64_t t_rx, ImuSink& sink);
  void on_record(int i, const RecordFramer::Record& r, int64_t t_rx, ImuSink& sink);
  void observe_clock(int64_t t_dev, int64_t t_rx, ImuSink& sink);
  void drain(int64_t t_rx, ImuSink& sink);
  int fill_secondary(Pending& p, bool force);  // 1 filled, 0 wait, -1 drop
  void emit(const Pending& p, ImuSink& sink);

  const HostClock& clock_;
  ImuConfig cfg_;
  std::array<Stream, 2> streams_;
  int n_streams_ = 0;
  int primary_ = 0;  // the faster stream (the output's time base)
  ImuState state_ = ImuState::kClosed;
  ImuCounters counters_;
  ClockSync sync_;
  bool want_host_stamps_ = false;
  bool host_stamps_ = false;
  bool clock_checked_ = false;
  int64_t min_lag_ns_ = 0, max_lag_ns_ = 0;
  bool have_lag_ = false;
  std::array<Pending, kPendingCap> pending_{};
  size_t pend_head_ = 0, pend_count_ = 0;
  std::array<SecondaryPoint, kHistoryCap> hist_{};
  size_t hist_head_ = 0, hist_count_ = 0;
  int64_t secondary_period_ns_ = 0;
  bool have_out_ = false;
  int64_t last_out_t_ns_ = 0;
  uint32_t seq_ = 0;
  uint32_t lost_carry_ = 0;
  DecodedRecord dec_;
};

}  // namespace kestrel::drivers::iio

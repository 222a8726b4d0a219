// BMX055 driver: protocol (state machine over a register table) and parser
// (pure functions over FIFO bytes), on top of any I2cBus.
//
//   reset -> wait boot -> probe chip ids -> [self-test -> reset ...] ->
//   configure (table) -> verify (read back, masked) -> stream (FIFO reads)
//   any fault -> counted -> back-off -> reset
//
// Timing (docs/drivers/bmx055.md, "Timestamps"): the gyroscope and the
// accelerometer each run on their own oscillator, so each has a sample clock:
// sample index * nominal period is a device time, and every FIFO read gives
// one observation (index of the newest sample, host time that sample certainly
// existed by): the data-ready (watermark) edge in GPIO mode, the end of the
// FIFO status read when polling. A ClockSync lower envelope turns these into
// per-sample host times and refines the ODR (its skew). Until it has two
// buckets the times are t_dr - (n-1-k)/ODR_nominal. Output samples are the
// gyroscope's; the accelerometer is interpolated to gyro times.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>

#include "kestrel/drivers/bmx055_regs.hpp"
#include "kestrel/drivers/clock_sync.hpp"
#include "kestrel/drivers/i2c_bus.hpp"
#include "kestrel/msgs.hpp"
#include "kestrel/rt/doorbell.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::drivers {

// Where drivers deliver samples and events. push() must not block; false =
// dropped (the sink counts).
class ImuSink {
 public:
  virtual ~ImuSink() = default;
  virtual bool push(const ImuSample& s) noexcept = 0;
  virtual void event(int64_t /*t_ns*/, EventCode /*code*/, const char* /*text*/) noexcept {}
};

// Into an SpscRing (SensorRings::imu): try_push, the ring counts drops; then
// wakes the consumer that sleeps on `bell` (none: nobody sleeps on the ring).
template <class Ring>
class RingImuSink final : public ImuSink {
 public:
  explicit RingImuSink(Ring& r, rt::Doorbell* bell = nullptr) : ring_(r), bell_(bell) {}
  bool push(const ImuSample& s) noexcept override {
    if (!ring_.try_push(s)) return false;
    if (bell_ != nullptr) bell_->ring();
    return true;
  }

 private:
  Ring& ring_;
  rt::Doorbell* bell_;
};

namespace bmx055 {

enum class DataReadyMode : uint8_t {
  kGpio,  // gyro FIFO watermark on INT3 -> a gpiochip line; edge time stamps the read
  kPoll,  // poll the FIFO status on a timer; the read time bounds the newest sample
};

struct Config {
  uint8_t acc_addr = kAccAddrDefault;
  uint8_t gyro_addr = kGyroAddrDefault;
  bool mag_enabled = false;
  uint8_t mag_addr = kMagAddrFirst;
  acc::Range acc_range = acc::Range::k16g;
  acc::Bandwidth acc_bw = acc::Bandwidth::k250Hz;  // 500 Hz ODR
  gyro::Range gyro_range = gyro::Range::k2000dps;
  gyro::Bandwidth gyro_bw = gyro::Bandwidth::k400Hz_47Hz;  // 400 Hz ODR
  int gyro_watermark_frames = 4;                           // 10 ms at 400 Hz
  int acc_watermark_frames = 5;                            // 10 ms at 500 Hz
  DataReadyMode drdy = DataReadyMode::kPoll;
  int64_t poll_period_ns = 5'000'000;
  bool self_test = true;
  // Sensor axes -> IMU frame: body axis i = sign(remap[i]) * sensor axis |remap[i]| (1 = x).
  std::array<int8_t, 3> axis_remap{1, 2, 3};
  // Timeouts (datasheet start-up: acc 1.8 ms, gyro 30 ms after soft reset).
  int64_t boot_wait_ns = 50'000'000;
  int64_t self_test_wait_ns = 50'000'000;
  int64_t stream_timeout_ns = 100'000'000;  // no gyro sample for this long -> reset
  int64_t backoff_min_ns = 100'000'000;
  int64_t backoff_max_ns = 2'000'000'000;
  int max_consecutive_errors = 3;
  // Throws std::invalid_argument naming the field.
  void validate() const;
};

enum class State : uint8_t {
  kReset,
  kWaitBoot,
  kProbe,
  kSelfTestAcc,
  kSelfTestGyro,
  kConfigure,
  kVerify,
  kStream,
  kBackoff,
  kFailed
};
const char* to_string(State s);

struct Counters {
  uint64_t resets = 0;
  uint64_t i2c_errors = 0;  // NACK / timeout / io error on any transfer
  uint64_t chip_id_mismatches = 0;
  uint64_t verify_failures = 0;  // configure-then-verify found a register that did not take
  uint64_t config_lost = 0;      // periodic check found a register changed (brown-out)
  uint64_t read_flips = 0;       // periodic check read a wrong value once, right on re-read
  uint64_t fifo_overruns = 0;
  uint64_t bad_fifo_status = 0;  // frame count beyond the FIFO depth
  uint64_t timeouts = 0;
  uint64_t self_test_failures = 0;
  uint64_t samples = 0;         // pushed successfully
  uint64_t sink_drops = 0;      // the sink refused (ring full)
  uint64_t samples_lost = 0;    // estimated from time gaps after overruns and flushes
  uint64_t acc_missing = 0;     // gyro samples dropped for want of any accelerometer sample
  uint64_t time_clamped = 0;    // a time that would not have been increasing
  uint64_t partial_frames = 0;  // FIFO bytes that did not make a whole frame
};

struct SelfTestReport {
  bool ran = false;
  bool acc_pass = false;
  bool gyro_pass = false;
  std::array<double, 3> acc_diff_mg{};  // |positive - negative| per axis
};

// ---- parser: pure functions over bytes -----------------------------------------

struct RawXyz {
  int16_t x = 0, y = 0, z = 0;
};

// Accelerometer frames (6 bytes: x lsb, x msb, y.., z..; 12-bit left-aligned in
// lsb bits 7:4 + msb). Returns frames decoded (<= max_out); *leftover gets the
// bytes that did not make a whole frame.
size_t parse_acc_fifo(const uint8_t* bytes, size_t n, RawXyz* out, size_t max_out,
                      size_t* leftover = nullptr);
// Gyroscope frames (6 bytes: int16 little endian x, y, z).
size_t parse_gyro_fifo(const uint8_t* bytes, size_t n, RawXyz* out, size_t max_out,
                       size_t* leftover = nullptr);

struct Scales {
  double gyro_rps_per_lsb = 0;
  double acc_mps2_per_lsb = 0;
  std::array<int8_t, 3> axis_remap{1, 2, 3};
};
Scales make_scales(acc::Range ar, gyro::Range gr, const std::array<int8_t, 3>& remap);

// Raw counts -> SI in the IMU frame, with saturation flags when a raw value
// sits at the end of its range (gyro +-32767/-32768, acc 2047/-2048).
void convert(const RawXyz& gyro, const RawXyz& acc, const Scales& s, ImuSample& out);
void convert_gyro(const RawXyz& gyro, const Scales& s, Vec3d& gyro_rps, bool& saturated);
void convert_acc(const RawXyz& acc, const Scales& s, Vec3d& acc_mps2, bool& saturated);
inline float temp_c_from_raw(int8_t raw) { return 23.0f + 0.5f * static_cast<float>(raw); }

// Host times of n FIFO samples read at one data-ready time, without a fitted
// sample clock: t_k = t_dr - (n-1-k) * period.
inline int64_t fifo_sample_time_ns(int64_t t_dr_ns, size_t n, size_t k, int64_t period_ns) {
  return t_dr_ns - static_cast<int64_t>(n - 1 - k) * period_ns;
}

// One register of the configure-then-verify table.
enum class Part : uint8_t { kAcc, kGyro, kMag };
struct RegEntry {
  Part part;
  uint8_t reg;
  uint8_t value;
  uint8_t verify_mask;  // bits compared on read-back (reserved / read-only bits masked out)
  const char* what;
};
constexpr size_t kMaxRegEntries = 24;
// Fills `out` in write order (FIFO_CONFIG_1 last: writing it clears the FIFO).
size_t build_register_table(const Config& c, std::array<RegEntry, kMaxRegEntries>& out);

// ---- protocol --------------------------------------------------------------------

class Driver {
 public:
  Driver(I2cBus& bus, const HostClock& clock, const Config& config);

  // A data-ready / watermark edge seen at host time t_ns (GPIO mode).
  void notify_data_ready(int64_t t_ns) { drdy_t_ns_ = t_ns; }
  // Advances the state machine by one step; returns the host time it wants
  // the next step at (the caller sleeps or waits for the GPIO until then).
  int64_t step(ImuSink& sink);

  State state() const { return state_; }
  const Counters& counters() const { return counters_; }
  const SelfTestReport& self_test() const { return self_test_; }
  const char* last_fault() const { return fault_; }  // "" until the first fault
  double gyro_odr_estimate_hz() const;
  double acc_odr_estimate_hz() const;
  bool mag_present() const { return mag_present_; }
  const Config& config() const { return cfg_; }

 private:
  struct PartClock {
    ClockSync sync;
    int64_t period_ns = 0;
    int64_t index = 0;  // sample index of the next FIFO sample
    bool fresh = true;  // continuity lost: restart the sample clock
  };
  struct AccPoint {
    int64_t t_ns = 0;
    Vec3d acc{};
    bool sat = false;
  };

  void enter(State s, int64_t delay_ns = 0);
  void fault(const char* what, ImuSink& sink);  // counts, goes to back-off
  bool read(Part p, uint8_t reg, uint8_t* dst, size_t n);
  bool write(Part p, uint8_t reg, uint8_t v);
  uint8_t addr(Part p) const;

  void step_probe(ImuSink& sink);
  void step_self_test_acc(ImuSink& sink);
  void step_self_test_gyro(ImuSink& sink);
  void step_configure(ImuSink& sink);
  void step_verify(ImuSink& sink);
  void step_stream(ImuSink& sink);
  // Reads one part's FIFO; returns frames read (0 on error, with *ok false).
  size_t read_fifo(Part p, RawXyz* out, size_t max, int64_t& t_obs_ns, bool& overrun, bool& ok);
  void flush_fifo(Part p);
  void restart_clock(PartClock& c, double keep_skew);
  int64_t sample_time(PartClock& c, size_t n, size_t k, int64_t obs_index, int64_t t_obs_ns);
  bool check_one_register(ImuSink& sink);
  void interpolate_acc(int64_t t_ns, Vec3d& acc, bool& sat, bool& have) const;

  I2cBus& bus_;
  const HostClock& clock_;
  Config cfg_;
  Scales scales_;
  std::array<RegEntry, kMaxRegEntries> table_{};
  size_t table_size_ = 0;
  State state_ = State::kReset;
  int64_t wake_ns_ = 0;
  int64_t backoff_ns_ = 0;
  int64_t drdy_t_ns_ = -1;
  int consecutive_errors_ = 0;
  Counters counters_;
  SelfTestReport self_test_;
  bool self_test_done_ = false;
  bool mag_present_ = false;
  int st_step_ = 0;
  std::array<double, 6> st_values_mg_{};
  const char* fault_ = "";  // always a string literal: no allocation on a fault

  PartClock gyro_clk_;
  PartClock acc_clk_;
  int64_t last_gyro_sample_host_ns_ = 0;
  int64_t last_out_t_ns_ = 0;
  uint32_t seq_ = 0;
  bool gap_pending_ = false;
  size_t check_index_ = 0;
  int64_t next_check_ns_ = 0;
  float temp_c_ = 0.0f;
  uint64_t dither_ = 0x9E3779B97F4A7C15ULL;
  static constexpr int kAccHistory = 64;
  std::array<AccPoint, kAccHistory> acc_hist_{};
  int acc_head_ = 0;
  int acc_count_ = 0;
  // FIFO scratch: the largest burst (gyro FIFO depth) of bytes and frames.
  std::array<uint8_t, gyro::kFifoDepthFrames * gyro::kFrameBytes> bytes_{};
  std::array<RawXyz, gyro::kFifoDepthFrames> gyro_raw_{};
  std::array<RawXyz, gyro::kFifoDepthFrames> acc_raw_{};
};

}  // namespace bmx055
}  // namespace kestrel::drivers

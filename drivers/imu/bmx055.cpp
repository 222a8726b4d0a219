#include "kestrel/drivers/bmx055.hpp"

#include <cmath>
#include <cstdlib>
#include <stdexcept>

namespace kestrel::drivers::bmx055 {
namespace {

constexpr double kStandardGravity = 9.80665;    // datasheet "g"
constexpr int64_t kCheckPeriodNs = 50'000'000;  // one register re-verified every 50 ms
constexpr int64_t kVerifySettleNs = 1'000'000;
constexpr int64_t kBistWaitNs = 20'000'000;
constexpr int kSelfTestAttempts = 3;

ClockSyncOptions sample_clock_options(double prior_skew) {
  ClockSyncOptions o;
  o.bucket_ns = 200'000'000;
  o.max_buckets = 50;  // 10 s window: follows oscillator drift with temperature
  o.min_buckets_for_skew = 3;
  o.prior_skew = prior_skew;
  o.max_abs_skew = 0.1;             // ODR tolerance is a few percent; beyond 10 % the index is wrong
  o.jump_threshold_ns = 5'000'000;  // a sample "seen" 5 ms before it can exist: index lost track
  return o;
}

}  // namespace

const char* to_string(State s) {
  switch (s) {
    case State::kReset:
      return "reset";
    case State::kWaitBoot:
      return "wait-boot";
    case State::kProbe:
      return "probe";
    case State::kSelfTestAcc:
      return "self-test-acc";
    case State::kSelfTestGyro:
      return "self-test-gyro";
    case State::kConfigure:
      return "configure";
    case State::kVerify:
      return "verify";
    case State::kStream:
      return "stream";
    case State::kBackoff:
      return "backoff";
    case State::kFailed:
      return "failed";
  }
  return "?";
}

void Config::validate() const {
  auto bad = [](const char* field, const std::string& why) {
    throw std::invalid_argument(std::string(field) + ": " + why);
  };
  if (acc_addr != kAccAddrDefault && acc_addr != kAccAddrAlt) bad("acc_i2c_addr", "must be 0x18 or 0x19");
  if (gyro_addr != kGyroAddrDefault && gyro_addr != kGyroAddrAlt)
    bad("gyro_i2c_addr", "must be 0x68 or 0x69");
  if (mag_addr < kMagAddrFirst || mag_addr > kMagAddrLast) bad("mag_i2c_addr", "must be 0x10..0x13");
  if (gyro_watermark_frames < 1 || gyro_watermark_frames >= gyro::kFifoDepthFrames)
    bad("gyro_fifo_watermark_frames", "must be 1..99");
  if (acc_watermark_frames < 1 || acc_watermark_frames >= acc::kFifoDepthFrames)
    bad("acc_fifo_watermark_frames", "must be 1..31");
  if (poll_period_ns <= 0) bad("poll_period_us", "must be > 0");
  // The poll period must drain the gyro FIFO before it overruns.
  const double fill_ns = 1e9 * gyro::kFifoDepthFrames / gyro::odr_hz(gyro_bw);
  if (static_cast<double>(poll_period_ns) > 0.5 * fill_ns)
    bad("poll_period_us", "must be under half the gyro FIFO fill time");
  bool seen[3] = {false, false, false};
  for (int8_t r : axis_remap) {
    const int a = std::abs(static_cast<int>(r));
    if (a < 1 || a > 3 || seen[a - 1]) bad("axis_remap", "must be a signed permutation of x, y, z");
    seen[a - 1] = true;
  }
  if (stream_timeout_ns <= 0 || boot_wait_ns <= 0 || backoff_min_ns <= 0 || backoff_max_ns < backoff_min_ns)
    bad("timeouts", "must be > 0 and backoff_max >= backoff_min");
}

// ---- parser ---------------------------------------------------------------------

size_t parse_acc_fifo(const uint8_t* b, size_t n, RawXyz* out, size_t max_out, size_t* leftover) {
  const size_t frames_in = n / acc::kFrameBytes;
  const size_t frames = frames_in < max_out ? frames_in : max_out;
  auto v12 = [](uint8_t lsb, uint8_t msb) {
    // 12-bit two's complement, left-aligned in 16 bits: arithmetic shift keeps the sign.
    const auto u = static_cast<uint16_t>((static_cast<unsigned>(msb) << 8) | (lsb & 0xF0u));
    return static_cast<int16_t>(static_cast<int16_t>(u) >> 4);
  };
  for (size_t i = 0; i < frames; ++i) {
    const uint8_t* f = b + i * acc::kFrameBytes;
    out[i] = RawXyz{v12(f[0], f[1]), v12(f[2], f[3]), v12(f[4], f[5])};
  }
  if (leftover != nullptr) *leftover = n - frames_in * acc::kFrameBytes;
  return frames;
}

size_t parse_gyro_fifo(const uint8_t* b, size_t n, RawXyz* out, size_t max_out, size_t* leftover) {
  const size_t frames_in = n / gyro::kFrameBytes;
  const size_t frames = frames_in < max_out ? frames_in : max_out;
  auto v16 = [](uint8_t lsb, uint8_t msb) {
    return static_cast<int16_t>(static_cast<uint16_t>(lsb | (static_cast<unsigned>(msb) << 8)));
  };
  for (size_t i = 0; i < frames; ++i) {
    const uint8_t* f = b + i * gyro::kFrameBytes;
    out[i] = RawXyz{v16(f[0], f[1]), v16(f[2], f[3]), v16(f[4], f[5])};
  }
  if (leftover != nullptr) *leftover = n - frames_in * gyro::kFrameBytes;
  return frames;
}

Scales make_scales(acc::Range ar, gyro::Range gr, const std::array<int8_t, 3>& remap) {
  Scales s;
  s.gyro_rps_per_lsb = gyro::lsb_mdps(gr) * 1e-3 * M_PI / 180.0;
  s.acc_mps2_per_lsb = acc::lsb_mg(ar) * 1e-3 * kStandardGravity;
  s.axis_remap = remap;
  return s;
}

namespace {
void remap(const double in[3], const std::array<int8_t, 3>& r, Vec3d& out) {
  for (int i = 0; i < 3; ++i) {
    const int a = std::abs(static_cast<int>(r[static_cast<size_t>(i)])) - 1;
    out[static_cast<size_t>(i)] = (r[static_cast<size_t>(i)] < 0 ? -1.0 : 1.0) * in[a];
  }
}
}  // namespace

void convert_gyro(const RawXyz& g, const Scales& s, Vec3d& gyro_rps, bool& saturated) {
  const int16_t v[3] = {g.x, g.y, g.z};
  double si[3];
  saturated = false;
  for (int i = 0; i < 3; ++i) {
    saturated = saturated || v[i] == INT16_MAX || v[i] == INT16_MIN;
    si[i] = v[i] * s.gyro_rps_per_lsb;
  }
  remap(si, s.axis_remap, gyro_rps);
}

void convert_acc(const RawXyz& a, const Scales& s, Vec3d& acc_mps2, bool& saturated) {
  const int16_t v[3] = {a.x, a.y, a.z};
  double si[3];
  saturated = false;
  for (int i = 0; i < 3; ++i) {
    saturated = saturated || v[i] >= 2047 || v[i] <= -2048;
    si[i] = v[i] * s.acc_mps2_per_lsb;
  }
  remap(si, s.axis_remap, acc_mps2);
}

void convert(const RawXyz& gyro, const RawXyz& acc, const Scales& s, ImuSample& out) {
  bool gs = false, as = false;
  convert_gyro(gyro, s, out.gyro_rps, gs);
  convert_acc(acc, s, out.acc_mps2, as);
  if (gs) out.flags |= kImuGyroSaturated;
  if (as) out.flags |= kImuAccSaturated;
}

size_t build_register_table(const Config& c, std::array<RegEntry, kMaxRegEntries>& t) {
  size_t n = 0;
  auto add = [&](Part p, uint8_t reg, uint8_t v, uint8_t mask, const char* what) {
    t[n++] = RegEntry{p, reg, v, mask, what};
  };
  const bool gpio = c.drdy == DataReadyMode::kGpio;
  // Accelerometer. Shadowing stays on (HBW bit 6 = 0) so an LSB/MSB pair is
  // never torn; the filtered output (bit 7 = 0) is what the bandwidth means.
  add(Part::kAcc, acc::kPmuLpw, 0x00, 0xE0, "acc PMU_LPW: normal mode");
  add(Part::kAcc, acc::kPmuRange, static_cast<uint8_t>(c.acc_range), 0x0F, "acc PMU_RANGE");
  add(Part::kAcc, acc::kPmuBw, static_cast<uint8_t>(c.acc_bw), 0x1F, "acc PMU_BW (ODR = 2 x bandwidth)");
  add(Part::kAcc, acc::kAccdHbw, 0x00, 0xC0, "acc ACCD_HBW: filtered, shadowed");
  add(Part::kAcc, acc::kIntEn1, 0x00, 0x70, "acc INT_EN_1: no interrupts (read beside the gyro)");
  add(Part::kAcc, acc::kWdt, 0x06, 0x06, "acc BGW_SPI3_WDT: I2C watchdog 50 ms");
  add(Part::kAcc, acc::kFifoConfig0, static_cast<uint8_t>(c.acc_watermark_frames), 0x3F,
      "acc FIFO_CONFIG_0 watermark");
  add(Part::kAcc, acc::kFifoConfig1, acc::kFifoModeStream, 0xC3, "acc FIFO_CONFIG_1: stream, xyz");
  // Gyroscope. BW bit 7 reads back as 1, hence the mask.
  add(Part::kGyro, gyro::kLpm1, 0x00, 0xA0, "gyro LPM1: normal mode");
  add(Part::kGyro, gyro::kRange, static_cast<uint8_t>(c.gyro_range), 0x07, "gyro RANGE");
  add(Part::kGyro, gyro::kBw, static_cast<uint8_t>(c.gyro_bw), 0x0F, "gyro BW (ODR, filter)");
  add(Part::kGyro, gyro::kRateHbw, 0x00, 0xC0, "gyro RATE_HBW: filtered, shadowed");
  add(Part::kGyro, gyro::kIntEn1, 0x01, 0x0F, "gyro INT_EN_1: INT3 push-pull active high");
  add(Part::kGyro, gyro::kIntMap1, gpio ? 0x04 : 0x00, 0x05, "gyro INT_MAP_1: FIFO -> INT3");
  add(Part::kGyro, gyro::kFifoWmEn, gpio ? 0x80 : 0x00, 0x80, "gyro FIFO watermark interrupt");
  add(Part::kGyro, gyro::kIntEn0, gpio ? 0x40 : 0x00, 0xC0, "gyro INT_EN_0: FIFO interrupt");
  add(Part::kGyro, gyro::kWdt, 0x06, 0x06, "gyro BGW_SPI3_WDT: I2C watchdog 50 ms");
  add(Part::kGyro, gyro::kFifoConfig0, static_cast<uint8_t>(c.gyro_watermark_frames), 0xFF,
      "gyro FIFO_CONFIG_0 watermark, no tag");
  add(Part::kGyro, gyro::kFifoConfig1, gyro::kFifoModeStream, 0xC3, "gyro FIFO_CONFIG_1: stream, xyz");
  return n;
}

// ---- protocol ---------------------------------------------------------------------

Driver::Driver(I2cBus& bus, const HostClock& clock, const Config& config)
    : bus_(bus), clock_(clock), cfg_(config) {
  cfg_.validate();
  scales_ = make_scales(cfg_.acc_range, cfg_.gyro_range, cfg_.axis_remap);
  table_size_ = build_register_table(cfg_, table_);
  backoff_ns_ = cfg_.backoff_min_ns;
  gyro_clk_.period_ns = static_cast<int64_t>(std::llround(1e9 / gyro::odr_hz(cfg_.gyro_bw)));
  acc_clk_.period_ns = static_cast<int64_t>(std::llround(1e9 / acc::odr_hz(cfg_.acc_bw)));
  restart_clock(gyro_clk_, 0.0);
  restart_clock(acc_clk_, 0.0);
  wake_ns_ = clock_.now_ns();
}

uint8_t Driver::addr(Part p) const {
  return p == Part::kAcc ? cfg_.acc_addr : p == Part::kGyro ? cfg_.gyro_addr : cfg_.mag_addr;
}

bool Driver::read(Part p, uint8_t reg, uint8_t* dst, size_t n) {
  if (bus_.read_regs(addr(p), reg, dst, n) == I2cStatus::kOk) return true;
  ++counters_.i2c_errors;
  return false;
}

bool Driver::write(Part p, uint8_t reg, uint8_t v) {
  if (bus_.write_reg(addr(p), reg, v) == I2cStatus::kOk) return true;
  ++counters_.i2c_errors;
  return false;
}

void Driver::enter(State s, int64_t delay_ns) {
  state_ = s;
  wake_ns_ = clock_.now_ns() + delay_ns;
}

void Driver::fault(const char* what, ImuSink& sink) {
  fault_ = what;
  sink.event(clock_.now_ns(), EventCode::kDriverFault, what);
  enter(State::kBackoff, backoff_ns_);
  backoff_ns_ = backoff_ns_ * 2 > cfg_.backoff_max_ns ? cfg_.backoff_max_ns : backoff_ns_ * 2;
}

void Driver::restart_clock(PartClock& c, double keep_skew) {
  c.sync = ClockSync(sample_clock_options(keep_skew));
  c.index = 0;
  c.fresh = false;
}

double Driver::gyro_odr_estimate_hz() const {
  return 1e9 / (static_cast<double>(gyro_clk_.period_ns) * (1.0 + gyro_clk_.sync.skew()));
}
double Driver::acc_odr_estimate_hz() const {
  return 1e9 / (static_cast<double>(acc_clk_.period_ns) * (1.0 + acc_clk_.sync.skew()));
}

int64_t Driver::step(ImuSink& sink) {
  const int64_t now = clock_.now_ns();
  const bool edge = cfg_.drdy == DataReadyMode::kGpio && drdy_t_ns_ >= 0;
  if (now < wake_ns_ && !(state_ == State::kStream && edge)) return wake_ns_;
  switch (state_) {
    case State::kReset:
      // A soft reset may be NACKed by a part that is already resetting: the
      // probe after the boot wait decides whether it worked.
      ++counters_.resets;
      (void)bus_.write_reg(cfg_.acc_addr, acc::kSoftReset, kSoftResetValue);
      (void)bus_.write_reg(cfg_.gyro_addr, gyro::kSoftReset, kSoftResetValue);
      if (cfg_.mag_enabled) (void)bus_.write_reg(cfg_.mag_addr, mag::kPowerCtrl, mag::kPowerOn);
      sink.event(now, EventCode::kDriverReset, "bmx055: soft reset");
      enter(State::kWaitBoot, cfg_.boot_wait_ns);
      break;
    case State::kWaitBoot:
      enter(State::kProbe);
      break;
    case State::kProbe:
      step_probe(sink);
      break;
    case State::kSelfTestAcc:
      step_self_test_acc(sink);
      break;
    case State::kSelfTestGyro:
      step_self_test_gyro(sink);
      break;
    case State::kConfigure:
      step_configure(sink);
      break;
    case State::kVerify:
      step_verify(sink);
      break;
    case State::kStream:
      step_stream(sink);
      break;
    case State::kBackoff:
      enter(State::kReset);
      break;
    case State::kFailed:
      wake_ns_ = now + 1'000'000'000;
      break;
  }
  return wake_ns_;
}

void Driver::step_probe(ImuSink& sink) {
  uint8_t id = 0;
  if (!read(Part::kAcc, acc::kChipIdReg, &id, 1))
    return fault("bmx055: accelerometer does not answer (NACK)", sink);
  if (id != acc::kChipId) {
    ++counters_.chip_id_mismatches;
    return fault("bmx055: accelerometer chip id is not 0xFA", sink);
  }
  if (!read(Part::kGyro, gyro::kChipIdReg, &id, 1))
    return fault("bmx055: gyroscope does not answer (NACK)", sink);
  if (id != gyro::kChipId) {
    ++counters_.chip_id_mismatches;
    return fault("bmx055: gyroscope chip id is not 0x0F", sink);
  }
  if (cfg_.mag_enabled) {
    // Optional part: absence is reported, not a fault.
    mag_present_ =
        bus_.read_regs(cfg_.mag_addr, mag::kChipIdReg, &id, 1) == I2cStatus::kOk && id == mag::kChipId;
  }
  if (cfg_.self_test && !self_test_done_) {
    st_step_ = 0;
    enter(State::kSelfTestAcc);
  } else {
    enter(State::kConfigure);
  }
}

void Driver::step_self_test_acc(ImuSink& sink) {
  // Six measurements: x+, x-, y+, y-, z+, z- at +-8 g with high amplitude,
  // each read 50 ms after switching the excitation (datasheet "Self-test").
  auto setup = [&](int m) {
    const uint8_t axis = static_cast<uint8_t>(m / 2 + 1);
    const uint8_t sign = (m % 2 == 0) ? 0x04 : 0x00;
    return write(Part::kAcc, acc::kSelfTest, static_cast<uint8_t>(acc::kSelfTestAmpHigh | sign | axis));
  };
  if (st_step_ == 0) {
    if (!write(Part::kAcc, acc::kPmuRange, static_cast<uint8_t>(acc::Range::k8g)) || !setup(0))
      return fault("bmx055: self-test set-up write failed", sink);
    st_step_ = 1;
    return enter(State::kSelfTestAcc, cfg_.self_test_wait_ns);
  }
  const int m = st_step_ - 1;
  uint8_t b[2];
  if (!read(Part::kAcc, static_cast<uint8_t>(acc::kDataXLsb + 2 * (m / 2)), b, 2))
    return fault("bmx055: self-test read failed", sink);
  RawXyz r;
  const uint8_t frame[6] = {b[0], b[1], 0, 0, 0, 0};
  parse_acc_fifo(frame, 6, &r, 1);
  st_values_mg_[static_cast<size_t>(m)] = r.x * acc::lsb_mg(acc::Range::k8g);
  if (m < 5) {
    if (!setup(m + 1)) return fault("bmx055: self-test set-up write failed", sink);
    ++st_step_;
    return enter(State::kSelfTestAcc, cfg_.self_test_wait_ns);
  }
  (void)write(Part::kAcc, acc::kSelfTest, 0x00);
  self_test_.acc_pass = true;
  for (size_t a = 0; a < 3; ++a) {
    self_test_.acc_diff_mg[a] = std::abs(st_values_mg_[2 * a] - st_values_mg_[2 * a + 1]);
    self_test_.acc_pass = self_test_.acc_pass && self_test_.acc_diff_mg[a] >= acc::kSelfTestMinDiffMg[a];
  }
  if (!write(Part::kGyro, gyro::kBist, gyro::kBistTrigger))
    return fault("bmx055: gyro BIST trigger failed", sink);
  enter(State::kSelfTestGyro, kBistWaitNs);
}

void Driver::step_self_test_gyro(ImuSink& sink) {
  uint8_t v = 0;
  if (!read(Part::kGyro, gyro::kBist, &v, 1)) return fault("bmx055: gyro BIST read failed", sink);
  self_test_.gyro_pass = (v & gyro::kBistReady) != 0 && (v & gyro::kBistFail) == 0;
  self_test_.ran = true;
  if (self_test_.acc_pass && self_test_.gyro_pass) {
    self_test_done_ = true;
    // The accelerometer must be reset after its self-test (datasheet).
    enter(State::kReset);
    return;
  }
  ++counters_.self_test_failures;
  if (counters_.self_test_failures >= static_cast<uint64_t>(kSelfTestAttempts)) {
    fault_ =
        self_test_.acc_pass ? "bmx055: gyroscope self-test failed" : "bmx055: accelerometer self-test failed";
    sink.event(clock_.now_ns(), EventCode::kDriverFault, fault_);
    enter(State::kFailed);
    return;
  }
  fault(self_test_.acc_pass ? "bmx055: gyroscope self-test failed (retrying)"
                            : "bmx055: accelerometer self-test failed (retrying)",
        sink);
}

void Driver::step_configure(ImuSink& sink) {
  for (size_t i = 0; i < table_size_; ++i) {
    const RegEntry& e = table_[i];
    if (!write(e.part, e.reg, e.value)) return fault("bmx055: configuration write failed", sink);
  }
  enter(State::kVerify, kVerifySettleNs);
}

void Driver::step_verify(ImuSink& sink) {
  for (size_t i = 0; i < table_size_; ++i) {
    const RegEntry& e = table_[i];
    uint8_t v = 0;
    if (!read(e.part, e.reg, &v, 1)) return fault("bmx055: verify read failed", sink);
    if ((v & e.verify_mask) != (e.value & e.verify_mask)) {
      ++counters_.verify_failures;
      return fault("bmx055: a configuration register did not take (verify)", sink);
    }
  }
  const int64_t now = clock_.now_ns();
  restart_clock(gyro_clk_, gyro_clk_.sync.skew());
  restart_clock(acc_clk_, acc_clk_.sync.skew());
  acc_count_ = 0;
  gap_pending_ = counters_.samples > 0;
  last_gyro_sample_host_ns_ = now;
  next_check_ns_ = now + kCheckPeriodNs;
  consecutive_errors_ = 0;
  backoff_ns_ = cfg_.backoff_min_ns;
  drdy_t_ns_ = -1;
  enter(State::kStream, cfg_.poll_period_ns);
}

void Driver::flush_fifo(Part p) {
  // Writing FIFO_CONFIG_1 clears the FIFO and its overrun flag.
  (void)write(p, p == Part::kAcc ? acc::kFifoConfig1 : gyro::kFifoConfig1,
              p == Part::kAcc ? acc::kFifoModeStream : gyro::kFifoModeStream);
  PartClock& c = p == Part::kAcc ? acc_clk_ : gyro_clk_;
  c.fresh = true;
  if (p == Part::kGyro) gap_pending_ = true;
  if (p == Part::kAcc) acc_count_ = 0;
}

size_t Driver::read_fifo(Part p, RawXyz* out, size_t max, int64_t& t_obs_ns, bool& overrun, bool& ok) {
  ok = false;
  overrun = false;
  const uint8_t status_reg = p == Part::kAcc ? acc::kFifoStatus : gyro::kFifoStatus;
  const uint8_t data_reg = p == Part::kAcc ? acc::kFifoData : gyro::kFifoData;
  const size_t depth = p == Part::kAcc ? acc::kFifoDepthFrames : gyro::kFifoDepthFrames;
  uint8_t st = 0;
  if (!read(p, status_reg, &st, 1)) return 0;
  // The newest frame counted in the status certainly existed by the time the
  // status read completed: that bounds its time from above.
  t_obs_ns = clock_.now_ns();
  ok = true;
  const size_t n = st & 0x7Fu;
  if (n > depth) {
    ++counters_.bad_fifo_status;
    flush_fifo(p);
    return 0;
  }
  if ((st & 0x80u) != 0) {
    // Frames were lost before the ones in the FIFO and nobody knows how many,
    // so the sample index is lost too: flush and restart the sample clock.
    ++counters_.fifo_overruns;
    flush_fifo(p);
    return 0;
  }
  if (n == 0) return 0;
  const size_t take = n < max ? n : max;
  if (!read(p, data_reg, bytes_.data(), take * 6)) {
    ok = false;
    return 0;
  }
  size_t leftover = 0;
  const size_t got = p == Part::kAcc ? parse_acc_fifo(bytes_.data(), take * 6, out, max, &leftover)
                                     : parse_gyro_fifo(bytes_.data(), take * 6, out, max, &leftover);
  if (leftover != 0) ++counters_.partial_frames;
  return got;
}

int64_t Driver::sample_time(PartClock& c, size_t /*n*/, size_t k, int64_t /*obs_index*/,
                            int64_t /*t_obs_ns*/) {
  return c.sync.to_host_ns((c.index + static_cast<int64_t>(k)) * c.period_ns);
}

void Driver::interpolate_acc(int64_t t_ns, Vec3d& acc, bool& sat, bool& have) const {
  have = false;
  if (acc_count_ == 0) return;
  auto get = [&](int i) -> const AccPoint& {  // i = 0 oldest
    return acc_hist_[static_cast<size_t>((acc_head_ - acc_count_ + i + kAccHistory) % kAccHistory)];
  };
  have = true;
  const AccPoint& newest = get(acc_count_ - 1);
  if (t_ns >= newest.t_ns) {  // hold the newest: at most one accelerometer period old
    acc = newest.acc;
    sat = newest.sat;
    return;
  }
  if (t_ns <= get(0).t_ns) {
    acc = get(0).acc;
    sat = get(0).sat;
    return;
  }
  for (int i = acc_count_ - 1; i > 0; --i) {
    const AccPoint& a = get(i - 1);
    const AccPoint& b = get(i);
    if (a.t_ns <= t_ns && t_ns <= b.t_ns) {
      const double w =
          b.t_ns > a.t_ns ? static_cast<double>(t_ns - a.t_ns) / static_cast<double>(b.t_ns - a.t_ns) : 1.0;
      for (size_t j = 0; j < 3; ++j) acc[j] = a.acc[j] + w * (b.acc[j] - a.acc[j]);
      sat = a.sat || b.sat;
      return;
    }
  }
  acc = newest.acc;
  sat = newest.sat;
}

bool Driver::check_one_register(ImuSink& sink) {
  const RegEntry& e = table_[check_index_ % table_size_];
  ++check_index_;
  uint8_t v = 0;
  if (!read(e.part, e.reg, &v, 1)) return true;  // counted as an i2c error; checked again next round
  if ((v & e.verify_mask) == (e.value & e.verify_mask)) return true;
  // Read twice before believing it: a flipped bit on the wire is not a lost
  // configuration.
  if (read(e.part, e.reg, &v, 1) && (v & e.verify_mask) == (e.value & e.verify_mask)) {
    ++counters_.read_flips;
    return true;
  }
  ++counters_.config_lost;
  fault("bmx055: configuration register changed while streaming (brown-out?)", sink);
  return false;
}

void Driver::step_stream(ImuSink& sink) {
  const int64_t now = clock_.now_ns();
  const int64_t edge_t = drdy_t_ns_;
  const int64_t prev_read_ns = last_gyro_sample_host_ns_;
  drdy_t_ns_ = -1;
  const int64_t gyro_fill_ns = static_cast<int64_t>(cfg_.gyro_watermark_frames) * gyro_clk_.period_ns;
  // Polling is dithered by up to a quarter period: a poll locked in phase to
  // the ODR would show the lower envelope one constant latency, never its floor.
  dither_ = dither_ * 6364136223846793005ULL + 1442695040888963407ULL;
  const int64_t dither =
      static_cast<int64_t>((dither_ >> 33) % static_cast<uint64_t>(cfg_.poll_period_ns / 4 + 1));
  wake_ns_ = now + (cfg_.drdy == DataReadyMode::kGpio ? 2 * gyro_fill_ns : cfg_.poll_period_ns + dither);

  if (now - last_gyro_sample_host_ns_ > cfg_.stream_timeout_ns) {
    ++counters_.timeouts;
    return fault("bmx055: no gyroscope samples within the stream timeout", sink);
  }
  if (gyro_clk_.fresh) restart_clock(gyro_clk_, gyro_clk_.sync.skew());
  if (acc_clk_.fresh) restart_clock(acc_clk_, acc_clk_.sync.skew());

  int64_t tg = 0, ta = 0;
  bool ovg = false, ova = false, okg = false, oka = false;
  const size_t ng = read_fifo(Part::kGyro, gyro_raw_.data(), gyro_raw_.size(), tg, ovg, okg);
  if (!okg) flush_fifo(Part::kGyro);
  const size_t na = read_fifo(Part::kAcc, acc_raw_.data(), acc_raw_.size(), ta, ova, oka);
  if (!oka) flush_fifo(Part::kAcc);
  int8_t traw = 0;
  const bool okt = read(Part::kAcc, acc::kTemp, reinterpret_cast<uint8_t*>(&traw), 1);
  if (okt) temp_c_ = temp_c_from_raw(traw);
  if (!okg || !oka || !okt) {
    if (++consecutive_errors_ >= cfg_.max_consecutive_errors)
      return fault("bmx055: repeated I2C errors while streaming", sink);
  } else {
    consecutive_errors_ = 0;
  }

  // Accelerometer first, so gyro times can be bracketed by it.
  if (na > 0) {
    PartClock& c = acc_clk_;
    if (!c.sync.add((c.index + static_cast<int64_t>(na) - 1) * c.period_ns, ta)) gap_pending_ = true;
    for (size_t k = 0; k < na; ++k) {
      AccPoint p;
      p.t_ns = sample_time(c, na, k, 0, ta);
      convert_acc(acc_raw_[k], scales_, p.acc, p.sat);
      acc_hist_[static_cast<size_t>(acc_head_)] = p;
      acc_head_ = (acc_head_ + 1) % kAccHistory;
      if (acc_count_ < kAccHistory) ++acc_count_;
    }
    c.index += static_cast<int64_t>(na);
  }
  if (ng > 0) {
    PartClock& c = gyro_clk_;
    if (cfg_.drdy == DataReadyMode::kGpio && edge_t > prev_read_ns &&
        static_cast<int64_t>(ng) >= cfg_.gyro_watermark_frames) {
      // The watermark edge fired when the FIFO held W unread frames: frame W-1 of this read.
      (void)c.sync.add((c.index + cfg_.gyro_watermark_frames - 1) * c.period_ns, edge_t);
    }
    if (!c.sync.add((c.index + static_cast<int64_t>(ng) - 1) * c.period_ns, tg)) gap_pending_ = true;
    for (size_t k = 0; k < ng; ++k) {
      ImuSample s;
      s.t_ns = sample_time(c, ng, k, 0, tg);
      s.t_recv_ns = now;
      s.flags = kImuTimeInterpolated;
      if (seq_ > 0 && s.t_ns <= last_out_t_ns_) {
        ++counters_.time_clamped;
        s.t_ns = last_out_t_ns_ + 1;
      }
      if (gap_pending_ && seq_ > 0) {
        s.flags |= kImuGapBefore;
        const double gap = static_cast<double>(s.t_ns - last_out_t_ns_) / static_cast<double>(c.period_ns);
        const int64_t lost = static_cast<int64_t>(std::llround(gap)) - 1;
        if (lost > 0) {
          counters_.samples_lost += static_cast<uint64_t>(lost);
          seq_ += static_cast<uint32_t>(lost);
        }
      }
      gap_pending_ = false;
      bool gsat = false, asat = false, have = false;
      convert_gyro(gyro_raw_[k], scales_, s.gyro_rps, gsat);
      interpolate_acc(s.t_ns, s.acc_mps2, asat, have);
      if (!have) {
        ++counters_.acc_missing;
        continue;
      }
      if (gsat) s.flags |= kImuGyroSaturated;
      if (asat) s.flags |= kImuAccSaturated;
      s.temp_c = temp_c_;
      s.seq = seq_++;
      last_out_t_ns_ = s.t_ns;
      if (sink.push(s)) {
        ++counters_.samples;
      } else {
        ++counters_.sink_drops;
      }
    }
    c.index += static_cast<int64_t>(ng);
    last_gyro_sample_host_ns_ = now;
  }
  if (now >= next_check_ns_) {
    next_check_ns_ = now + kCheckPeriodNs;
    (void)check_one_register(sink);
  }
}

}  // namespace kestrel::drivers::bmx055

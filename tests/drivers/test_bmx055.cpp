// BMX055: parser byte fixtures, conversion, the register table, and the
// protocol state machine against the fake register file with every fault the
// fake can inject (each one counted and recovered from).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "kestrel/drivers/bmx055.hpp"
#include "kestrel/drivers/bmx055_fake.hpp"
#include "vec_imu_sink.hpp"

namespace kestrel::drivers::bmx055 {
namespace {

constexpr double kPi = 3.14159265358979323846;

using VecImuSink = kestrel::test::VecImuSink;

// ---- parser fixtures -------------------------------------------------------------

TEST(Bmx055Parser, AccelerometerFramesAreTwelveBitLeftAligned) {
  // x = +1 (0x001 << 4 = 0x0010), y = -1 (0xFFF0), z = -2048 (0x8000); new_data bits set in lsb bit 0.
  const uint8_t bytes[] = {0x11, 0x00, 0xF1, 0xFF, 0x01, 0x80,
                           0xF0, 0x7F, 0x00, 0x00, 0x20, 0x03};  // x = 2047, y = 0, z = 0x032 = 50
  RawXyz out[4];
  size_t leftover = 99;
  ASSERT_EQ(parse_acc_fifo(bytes, sizeof bytes, out, 4, &leftover), 2u);
  EXPECT_EQ(leftover, 0u);
  EXPECT_EQ(out[0].x, 1);
  EXPECT_EQ(out[0].y, -1);
  EXPECT_EQ(out[0].z, -2048);
  EXPECT_EQ(out[1].x, 2047);
  EXPECT_EQ(out[1].y, 0);
  EXPECT_EQ(out[1].z, 50);
}

TEST(Bmx055Parser, GyroFramesAreSixteenBitLittleEndian) {
  const uint8_t bytes[] = {0xFF, 0x7F, 0x00, 0x80, 0x01, 0x00, 0x34, 0x12, 0xFE, 0xFF, 0x00, 0x00, 0xAA};
  RawXyz out[4];
  size_t leftover = 0;
  ASSERT_EQ(parse_gyro_fifo(bytes, sizeof bytes, out, 4, &leftover), 2u);
  EXPECT_EQ(leftover, 1u);  // a partial frame is reported, not decoded
  EXPECT_EQ(out[0].x, 32767);
  EXPECT_EQ(out[0].y, -32768);
  EXPECT_EQ(out[0].z, 1);
  EXPECT_EQ(out[1].x, 0x1234);
  EXPECT_EQ(out[1].y, -2);
  EXPECT_EQ(out[1].z, 0);
  // Never writes beyond max_out.
  EXPECT_EQ(parse_gyro_fifo(bytes, sizeof bytes, out, 1, nullptr), 1u);
}

TEST(Bmx055Convert, ScalesMatchTheDatasheetSensitivities) {
  const Scales s = make_scales(acc::Range::k16g, gyro::Range::k2000dps, {1, 2, 3});
  // 7.81 mg/LSB and 61.0 mdps/LSB.
  EXPECT_NEAR(s.acc_mps2_per_lsb, 7.8125e-3 * 9.80665, 1e-12);
  EXPECT_NEAR(s.gyro_rps_per_lsb, 2000.0 / 32768.0 * kPi / 180.0, 1e-15);
  EXPECT_NEAR(acc::lsb_mg(acc::Range::k2g), 0.9765625, 1e-12);
  EXPECT_NEAR(gyro::lsb_mdps(gyro::Range::k125dps), 3.814697265625, 1e-12);
  EXPECT_DOUBLE_EQ(acc::odr_hz(acc::Bandwidth::k250Hz), 500.0);
  EXPECT_DOUBLE_EQ(gyro::odr_hz(gyro::Bandwidth::k400Hz_47Hz), 400.0);
}

TEST(Bmx055Convert, SaturationFlagsAndAxisRemap) {
  const Scales s = make_scales(acc::Range::k16g, gyro::Range::k2000dps, {2, -1, 3});
  ImuSample out;
  convert(RawXyz{100, 200, 300}, RawXyz{10, 20, 30}, s, out);
  EXPECT_EQ(out.flags, 0u);
  EXPECT_NEAR(out.gyro_rps[0], 200 * s.gyro_rps_per_lsb, 1e-15);   // body x = sensor y
  EXPECT_NEAR(out.gyro_rps[1], -100 * s.gyro_rps_per_lsb, 1e-15);  // body y = -sensor x
  EXPECT_NEAR(out.acc_mps2[2], 30 * s.acc_mps2_per_lsb, 1e-15);
  ImuSample sat;
  convert(RawXyz{0, -32768, 0}, RawXyz{2047, 0, 0}, s, sat);
  EXPECT_TRUE(sat.flags & kImuGyroSaturated);
  EXPECT_TRUE(sat.flags & kImuAccSaturated);
  EXPECT_FLOAT_EQ(temp_c_from_raw(-2), 22.0f);
}

TEST(Bmx055Time, FifoBackComputation) {
  // n = 4 samples read at t_dr: the newest at t_dr, the oldest 3 periods before.
  EXPECT_EQ(fifo_sample_time_ns(1'000'000'000, 4, 3, 2'500'000), 1'000'000'000);
  EXPECT_EQ(fifo_sample_time_ns(1'000'000'000, 4, 0, 2'500'000), 992'500'000);
}

TEST(Bmx055Table, FifoConfigIsWrittenLastAndMasksCoverValues) {
  Config c;
  c.drdy = DataReadyMode::kGpio;
  std::array<RegEntry, kMaxRegEntries> t;
  const size_t n = build_register_table(c, t);
  ASSERT_GT(n, 10u);
  int last_acc = -1, last_gyro = -1;
  for (size_t i = 0; i < n; ++i) {
    if (t[i].part == Part::kAcc) last_acc = static_cast<int>(i);
    if (t[i].part == Part::kGyro) last_gyro = static_cast<int>(i);
    // Every bit we set is a bit we verify.
    EXPECT_EQ(t[i].value & ~t[i].verify_mask, 0) << t[i].what;
  }
  EXPECT_EQ(t[static_cast<size_t>(last_acc)].reg, acc::kFifoConfig1);
  EXPECT_EQ(t[static_cast<size_t>(last_gyro)].reg, gyro::kFifoConfig1);
  bool wm_int = false;
  for (size_t i = 0; i < n; ++i) wm_int = wm_int || (t[i].reg == gyro::kFifoWmEn && t[i].value == 0x80);
  EXPECT_TRUE(wm_int);
}

TEST(Bmx055Config, ValidateNamesTheField) {
  Config c;
  c.axis_remap = {1, 1, 3};
  try {
    c.validate();
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("axis_remap"), std::string::npos);
  }
  Config d;
  d.gyro_watermark_frames = 100;
  EXPECT_THROW(d.validate(), std::invalid_argument);
}

// ---- protocol against the fake ----------------------------------------------------

struct Rig {
  ManualClock clock{1'000'000'000};
  FakeBmx055 fake{clock, 7};
  Config cfg;
  VecImuSink sink;
  std::unique_ptr<Driver> drv;
  int64_t wake = 0;

  explicit Rig(bool gpio = false, bool self_test = true) {
    cfg.drdy = gpio ? DataReadyMode::kGpio : DataReadyMode::kPoll;
    cfg.self_test = self_test;
    fake.bus_hz = 400e3;
    fake.gyro_clock_error = 0.007;  // the sensor runs 0.7 % slow
    fake.acc_clock_error = -0.004;
    fake.motion = [](int64_t t, Vec3d& g, Vec3d& a) {
      const double s = 1e-9 * static_cast<double>(t);
      g = {0.5 * std::sin(2 * kPi * 1.3 * s), 0.2, -0.1};
      a = {0.3, -0.2, 9.80665 + 0.5 * std::cos(2 * kPi * 0.7 * s)};
    };
    drv = std::make_unique<Driver>(fake, clock, cfg);
    wake = clock.now_ns();
  }

  void run_for(int64_t dur_ns) {
    const int64_t end = clock.now_ns() + dur_ns;
    const bool gpio = cfg.drdy == DataReadyMode::kGpio;
    // Poll-timer and scheduling jitter of a real thread: 0..200 us late.
    uint64_t lcg = 12345;
    while (clock.now_ns() < end) {
      int64_t edge = 0;
      if (gpio && fake.take_watermark_edge(edge)) {
        drv->notify_data_ready(edge);
        wake = drv->step(sink);
      }
      if (clock.now_ns() >= wake) wake = drv->step(sink);
      if (wake > clock.now_ns()) {
        lcg = lcg * 6364136223846793005ULL + 1;
        const int64_t late = static_cast<int64_t>((lcg >> 33) % 200'000);
        int64_t next = wake + late;
        if (gpio) next = std::min(next, clock.now_ns() + 100'000);
        clock.set(next);
      }
    }
  }
};

// Host-time error of every output sample against the frame the fake produced
// nearest to it (the spacing is 2.5 ms, errors are microseconds).
struct TimeError {
  double rms_us = 0;
  double max_us = 0;
  size_t n = 0;
};
TimeError time_error(const std::vector<ImuSample>& out, const std::vector<int64_t>& truth, int64_t after_ns) {
  TimeError e;
  double sq = 0;
  for (const ImuSample& s : out) {
    if (s.t_ns < after_ns) continue;
    auto it = std::lower_bound(truth.begin(), truth.end(), s.t_ns);
    int64_t best = INT64_MAX;
    if (it != truth.end()) best = std::min<int64_t>(best, std::llabs(*it - s.t_ns));
    if (it != truth.begin()) best = std::min<int64_t>(best, std::llabs(*(it - 1) - s.t_ns));
    const double us = static_cast<double>(best) * 1e-3;
    sq += us * us;
    e.max_us = std::max(e.max_us, us);
    ++e.n;
  }
  e.rms_us = e.n > 0 ? std::sqrt(sq / static_cast<double>(e.n)) : 0;
  return e;
}

void expect_monotonic(const std::vector<ImuSample>& s) {
  for (size_t i = 1; i < s.size(); ++i) {
    ASSERT_GT(s[i].t_ns, s[i - 1].t_ns) << "at " << i;
    ASSERT_GT(s[i].seq, s[i - 1].seq) << "at " << i;
  }
}

TEST(Bmx055Driver, BringUpSelfTestConfigureVerifyStream) {
  Rig r;
  // Boot wait, six 50 ms accelerometer excitations, the gyro BIST, a second reset.
  r.run_for(1'000'000'000);
  ASSERT_EQ(r.drv->state(), State::kStream) << r.drv->last_fault();
  EXPECT_TRUE(r.drv->self_test().ran);
  EXPECT_TRUE(r.drv->self_test().acc_pass);
  EXPECT_TRUE(r.drv->self_test().gyro_pass);
  EXPECT_GT(r.drv->self_test().acc_diff_mg[0], 800.0);
  // The configuration table is in the device.
  std::array<RegEntry, kMaxRegEntries> t;
  const size_t n = build_register_table(r.cfg, t);
  for (size_t i = 0; i < n; ++i) {
    const uint8_t addr = t[i].part == Part::kAcc ? r.cfg.acc_addr : r.cfg.gyro_addr;
    EXPECT_EQ(r.fake.reg(addr, t[i].reg) & t[i].verify_mask, t[i].value & t[i].verify_mask) << t[i].what;
  }
  r.sink.samples.clear();
  r.run_for(2'000'000'000);
  // 400 Hz nominal, 0.7 % slow.
  EXPECT_NEAR(static_cast<double>(r.sink.samples.size()), 800 / 1.007, 6);
  expect_monotonic(r.sink.samples);
  const Counters& c = r.drv->counters();
  EXPECT_EQ(c.i2c_errors, 0u);
  EXPECT_EQ(c.fifo_overruns, 0u);
  EXPECT_EQ(c.sink_drops, 0u);
  // Values: gyro y = 0.2 rad/s, acc x = 0.3 m/s^2 within one LSB (+ interpolation of a constant).
  const ImuSample& s = r.sink.samples.back();
  EXPECT_NEAR(s.gyro_rps[1], 0.2, 2e-3);
  EXPECT_NEAR(s.acc_mps2[0], 0.3, 0.08);
  EXPECT_FLOAT_EQ(s.temp_c, 25.0f);
  EXPECT_TRUE(s.flags & kImuTimeInterpolated);
}

TEST(Bmx055Driver, PolledTimesAndOdrRefinement) {
  Rig r(false, false);
  r.run_for(20'000'000'000);
  ASSERT_EQ(r.drv->state(), State::kStream);
  const TimeError e =
      time_error(r.sink.samples, r.fake.gyro_sample_times(), r.clock.now_ns() - 10'000'000'000);
  std::printf(
      "[ figure ] BMX055 polled FIFO sample times: RMS %.1f us, max %.1f us over %zu samples; "
      "ODR estimate %.3f Hz (true %.3f)\n",
      e.rms_us, e.max_us, e.n, r.drv->gyro_odr_estimate_hz(), 400.0 / 1.007);
  EXPECT_GT(e.n, 3500u);
  EXPECT_LT(e.rms_us, 100.0);
  EXPECT_NEAR(r.drv->gyro_odr_estimate_hz(), 400.0 / 1.007, 0.05);
  EXPECT_NEAR(r.drv->acc_odr_estimate_hz(), 500.0 / 0.996, 0.1);
}

TEST(Bmx055Driver, GpioWatermarkTimes) {
  Rig r(true, false);
  r.run_for(20'000'000'000);
  ASSERT_EQ(r.drv->state(), State::kStream);
  const TimeError e =
      time_error(r.sink.samples, r.fake.gyro_sample_times(), r.clock.now_ns() - 10'000'000'000);
  std::printf(
      "[ figure ] BMX055 GPIO watermark sample times: RMS %.1f us, max %.1f us (edge latency %.0f us)\n",
      e.rms_us, e.max_us, r.fake.drdy_latency_ns * 1e-3);
  EXPECT_GT(e.n, 3500u);
  EXPECT_LT(e.rms_us, 50.0);
}

TEST(Bmx055Driver, SingleNackIsCountedAndStreamingContinues) {
  Rig r(false, false);
  r.run_for(300'000'000);
  ASSERT_EQ(r.drv->state(), State::kStream);
  const uint64_t resets = r.drv->counters().resets;
  r.fake.nack_next(1);
  r.run_for(300'000'000);
  EXPECT_EQ(r.drv->state(), State::kStream);
  EXPECT_EQ(r.drv->counters().i2c_errors, 1u);
  EXPECT_EQ(r.drv->counters().resets, resets);
  expect_monotonic(r.sink.samples);
}

TEST(Bmx055Driver, NackBurstResetsAndRecovers) {
  Rig r(false, false);
  r.run_for(300'000'000);
  const uint64_t resets = r.drv->counters().resets;
  const size_t before = r.sink.samples.size();
  r.fake.nack_next(12);
  r.run_for(1'000'000'000);
  EXPECT_EQ(r.drv->state(), State::kStream) << r.drv->last_fault();
  EXPECT_GE(r.drv->counters().i2c_errors, 12u);
  EXPECT_GT(r.drv->counters().resets, resets);
  EXPECT_GT(r.sink.samples.size(), before + 100);
  expect_monotonic(r.sink.samples);
  bool gap = false;
  for (size_t i = before; i < r.sink.samples.size(); ++i)
    gap = gap || (r.sink.samples[i].flags & kImuGapBefore);
  EXPECT_TRUE(gap);
}

TEST(Bmx055Driver, AbsentDeviceBacksOffThenRecovers) {
  Rig r(false, false);
  r.fake.set_absent(true);
  r.run_for(3'000'000'000);
  EXPECT_NE(r.drv->state(), State::kStream);
  EXPECT_TRUE(r.sink.samples.empty());
  EXPECT_NE(std::string(r.drv->last_fault()).find("does not answer"), std::string::npos);
  const uint64_t tries = r.drv->counters().resets;
  EXPECT_GE(tries, 2u);
  EXPECT_LE(tries, 8u);  // exponential back-off, not a busy loop
  r.fake.set_absent(false);
  r.run_for(3'000'000'000);
  EXPECT_EQ(r.drv->state(), State::kStream);
  EXPECT_FALSE(r.sink.samples.empty());
}

TEST(Bmx055Driver, ChipIdBitFlipAtProbe) {
  Rig r(false, false);
  r.fake.flip_next_read(acc::kChipIdReg == 0 ? kAccAddrDefault : 0, acc::kChipIdReg, 0x01);
  r.run_for(1'000'000'000);
  EXPECT_EQ(r.drv->counters().chip_id_mismatches, 1u);
  EXPECT_EQ(r.drv->state(), State::kStream);
}

TEST(Bmx055Driver, VerifyCatchesARegisterThatDidNotTake) {
  Rig r(false, false);
  r.fake.flip_next_read(kGyroAddrDefault, gyro::kRange, 0x02);
  r.run_for(1'000'000'000);
  EXPECT_EQ(r.drv->counters().verify_failures, 1u);
  EXPECT_EQ(r.drv->state(), State::kStream);
}

TEST(Bmx055Driver, PeriodicCheckTellsAFlipFromABrownOut) {
  Rig r(false, false);
  r.run_for(300'000'000);
  // A flipped bit on every register read once: re-read agrees -> counted, no reset.
  const uint64_t resets = r.drv->counters().resets;
  // The gyro RANGE register is read only by the rotating check (every 50 ms,
  // about 20 registers): within 1.5 s it comes round.
  r.fake.flip_next_read(kGyroAddrDefault, gyro::kRange, 0x01);
  r.run_for(1'500'000'000);
  EXPECT_EQ(r.fake.flips_injected(), 1u);
  EXPECT_GE(r.drv->counters().read_flips, 1u);
  EXPECT_EQ(r.drv->counters().resets, resets);
  EXPECT_EQ(r.drv->state(), State::kStream);
  // A brown-out: registers really are back at reset values.
  r.fake.brown_out();
  r.run_for(3'000'000'000);
  EXPECT_GE(r.drv->counters().config_lost + r.drv->counters().timeouts, 1u);
  EXPECT_GT(r.drv->counters().resets, resets);
  EXPECT_EQ(r.drv->state(), State::kStream);
  expect_monotonic(r.sink.samples);
}

TEST(Bmx055Driver, FifoOverrunIsCountedAndTheGapMarked) {
  Rig r(false, false);
  r.run_for(500'000'000);
  const size_t before = r.sink.samples.size();
  r.fake.force_overrun(true, false);
  r.run_for(500'000'000);
  EXPECT_EQ(r.drv->counters().fifo_overruns, 1u);
  EXPECT_EQ(r.drv->state(), State::kStream);
  bool gap = false;
  for (size_t i = before; i < r.sink.samples.size(); ++i)
    gap = gap || (r.sink.samples[i].flags & kImuGapBefore);
  EXPECT_TRUE(gap);
  EXPECT_GT(r.drv->counters().samples_lost, 0u);
  expect_monotonic(r.sink.samples);
}

TEST(Bmx055Driver, AccOverrunAndBadFifoStatus) {
  Rig r(false, false);
  r.run_for(500'000'000);
  r.fake.force_overrun(false, true);
  r.run_for(100'000'000);
  EXPECT_EQ(r.drv->counters().fifo_overruns, 1u);
  // A flipped bit 6 in the frame count: 0..31 frames read as 64..95, beyond the 32-frame FIFO.
  r.fake.flip_next_read(kAccAddrDefault, acc::kFifoStatus, 0x40);
  r.run_for(100'000'000);
  EXPECT_EQ(r.drv->counters().bad_fifo_status, 1u);
  EXPECT_EQ(r.drv->state(), State::kStream);
  expect_monotonic(r.sink.samples);
}

TEST(Bmx055Driver, StalledDataTimesOutAndRecovers) {
  Rig r(false, false);
  r.run_for(300'000'000);
  r.fake.stall_data(true);
  r.run_for(500'000'000);
  EXPECT_GE(r.drv->counters().timeouts, 1u);
  r.fake.stall_data(false);
  const size_t before = r.sink.samples.size();
  r.run_for(3'000'000'000);
  EXPECT_EQ(r.drv->state(), State::kStream);
  EXPECT_GT(r.sink.samples.size(), before + 500);
}

TEST(Bmx055Driver, SelfTestFailureEndsInFailedWithAMessage) {
  Rig r(false, true);
  r.fake.set_self_test_fail(true, false);
  r.run_for(5'000'000'000);
  EXPECT_EQ(r.drv->state(), State::kFailed);
  EXPECT_EQ(r.drv->counters().self_test_failures, 3u);
  EXPECT_NE(std::string(r.drv->last_fault()).find("accelerometer self-test"), std::string::npos);
  EXPECT_TRUE(r.sink.samples.empty());
}

TEST(Bmx055Driver, FullSinkDropsAreCountedNeverWaitedFor) {
  Rig r(false, false);
  r.sink.capacity = 50;
  r.run_for(1'000'000'000);
  EXPECT_EQ(r.drv->state(), State::kStream);
  EXPECT_EQ(r.sink.samples.size(), 50u);
  EXPECT_GT(r.drv->counters().sink_drops, 250u);
  EXPECT_EQ(r.drv->counters().fifo_overruns, 0u);  // the FIFO kept being drained
}

TEST(Bmx055Driver, RandomFaultSoakNeverStalls) {
  Rig r(false, true);
  r.fake.set_nack_probability(0.01);
  r.fake.set_flip_probability(0.005);
  r.run_for(60'000'000'000);
  const Counters& c = r.drv->counters();
  std::printf(
      "[ figure ] 60 s soak, 1 %% NACK + 0.5 %% flips: %llu samples, %llu i2c errors, %llu resets, "
      "%llu flips seen on re-read, %llu config lost, %llu bad fifo status, %llu verify failures\n",
      static_cast<unsigned long long>(c.samples), static_cast<unsigned long long>(c.i2c_errors),
      static_cast<unsigned long long>(c.resets), static_cast<unsigned long long>(c.read_flips),
      static_cast<unsigned long long>(c.config_lost), static_cast<unsigned long long>(c.bad_fifo_status),
      static_cast<unsigned long long>(c.verify_failures));
  EXPECT_GT(c.i2c_errors, 100u);
  // At least 90 % of the 60 s of data arrives despite the faults.
  EXPECT_GT(static_cast<double>(c.samples), 0.9 * 60 * 400 / 1.007);
  expect_monotonic(r.sink.samples);
  // The last 5 s stream uninterrupted in time (no stall at the end).
  EXPECT_GT(r.sink.samples.back().t_ns, r.clock.now_ns() - 100'000'000);
}

}  // namespace
}  // namespace kestrel::drivers::bmx055

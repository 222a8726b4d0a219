// The flight controller's IMU (drivers/imu/mavlink_imu) against a simulated
// autopilot on loopback UDP (sim_autopilot.hpp), and MAVLink 2 signing
// (drivers/mavlink/mavlink_signing) against node-mavlink's and OpenSSL's.
#include <gtest/gtest.h>
#include <openssl/evp.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/mavlink/sha256.hpp"
#include "kestrel/drivers/mavlink_imu.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/tools/config_file.hpp"
#include "mavlink_imu_fuzz_entry.hpp"
#include "run_command.hpp"
#include "sim_autopilot.hpp"
#include "test_data.hpp"

namespace km = kestrel::mavlink;
namespace kd = kestrel::drivers;
using kestrel::test::SimAutopilot;
using kestrel::test::SimAutopilotOptions;
using kestrel::test::SimImuSample;

namespace {

// A sink that never allocates once reserved (the driver's thread pushes into it).
struct FixedSink final : kd::ImuSink {
  explicit FixedSink(std::size_t cap) { samples.reserve(cap); }
  std::vector<kestrel::ImuSample> samples;
  bool push(const kestrel::ImuSample& s) noexcept override {
    if (samples.size() == samples.capacity()) return false;
    samples.push_back(s);
    return true;
  }
};

// Smooth motion at `rate_hz` for `seconds`: every axis moves, gravity on z.
std::vector<SimImuSample> synthetic_imu(double rate_hz, double seconds) {
  std::vector<SimImuSample> v;
  const int n = static_cast<int>(rate_hz * seconds);
  for (int i = 0; i < n; ++i) {
    SimImuSample s;
    s.t_rel_ns = static_cast<int64_t>(std::llround(i * 1e9 / rate_hz));
    const double t = i / rate_hz;
    s.acc_mps2[0] = 1.5 * std::sin(2.1 * t);
    s.acc_mps2[1] = -0.8 * std::cos(1.3 * t);
    s.acc_mps2[2] = -9.80665 + 0.4 * std::sin(3.7 * t);
    s.gyro_rps[0] = 0.3 * std::sin(1.7 * t);
    s.gyro_rps[1] = -0.2 * std::cos(2.9 * t);
    s.gyro_rps[2] = 0.5 * std::sin(0.7 * t);
    v.push_back(s);
  }
  return v;
}

kd::MavlinkImuConfig driver_config(const SimAutopilot& ap, double rate_hz) {
  kd::MavlinkImuConfig c;
  c.udp = ap.endpoint();
  c.rate_hz = rate_hz;
  return c;
}

// Runs the driver on its own thread (as LiveSensors does) until the autopilot has sent everything.
void run_driver(kd::MavlinkImuDriver& d, FixedSink& sink, const SimAutopilot& ap, int64_t timeout_ns) {
  std::atomic<bool> stop{false};
  std::thread t([&] {
    while (!stop) d.step(sink, 100'000'000);
  });
  const int64_t t0 = kestrel::rt::now_ns();
  while (!ap.done() && kestrel::rt::now_ns() - t0 < timeout_ns)
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  std::this_thread::sleep_for(std::chrono::milliseconds(100));  // the last datagrams
  stop = true;
  t.join();
}

// Which simulated sample an output sample is: the nearest true host time.
std::size_t match_index(const SimAutopilot& ap, std::size_t n, int64_t t_ns, std::size_t from) {
  std::size_t best = from;
  for (std::size_t i = from; i < n; ++i) {
    if (std::llabs(ap.t_host_ns(i) - t_ns) < std::llabs(ap.t_host_ns(best) - t_ns)) best = i;
    if (ap.t_host_ns(i) > t_ns + 100'000'000) break;
  }
  return best;
}

struct StampErrors {
  double mean_us = 0, max_abs_us = 0;
  std::size_t n = 0;
};

}  // namespace

TEST(MavlinkHighresImu, SimulatedAutopilotStampsMapOntoHostClockAndValuesMatch) {
  SimAutopilotOptions o;
  // The autopilot booted 3.2 s before this test: its clock is far behind the host's.
  o.offset_ns = -(kestrel::rt::now_ns() - 3'200'000'000);
  const auto truth = synthetic_imu(200, 3.0);
  SimAutopilot ap(o, truth);
  kd::MonotonicHostClock clock;
  kd::MavlinkImuDriver d(driver_config(ap, 200), clock);
  FixedSink sink(2000);
  run_driver(d, sink, ap, 10'000'000'000);

  ASSERT_TRUE(ap.streaming()) << d.report();
  EXPECT_TRUE(d.interval_accepted()) << d.report();
  EXPECT_FLOAT_EQ(ap.requested_msgid(), 105.0f);
  EXPECT_FLOAT_EQ(ap.requested_interval_us(), 5000.0f);
  EXPECT_TRUE(d.time_sync().converged());
  EXPECT_NEAR(static_cast<double>(d.time_sync().offset_ns()), static_cast<double>(o.offset_ns), 1e6);
  // The stream starts 50 ms after the command, by which time TIMESYNC (10 Hz until converged) has
  // had ~5 answers: most samples come out; every one that does is a simulated one, in order.
  ASSERT_GT(sink.samples.size(), truth.size() * 8 / 10) << d.report();
  const auto& c = d.counters();
  EXPECT_EQ(c.samples, sink.samples.size());
  EXPECT_EQ(c.out_of_order + c.gaps + c.nonfinite + c.stamp_outliers + c.sink_drops, 0u) << d.report();
  EXPECT_EQ(d.decoder_stats().bad_crc, 0u);
  StampErrors e;
  std::size_t k = 0;
  int64_t last = 0;
  for (const auto& s : sink.samples) {
    k = match_index(ap, truth.size(), s.t_ns, k);
    const double err_us = 1e-3 * static_cast<double>(s.t_ns - ap.t_host_ns(k));
    e.mean_us += err_us, e.max_abs_us = std::max(e.max_abs_us, std::abs(err_us)), ++e.n;
    EXPECT_GT(s.t_ns, last);
    last = s.t_ns;
    EXPECT_LE(s.t_ns, s.t_recv_ns + 1'000'000);
    for (int a = 0; a < 3; ++a) {
      EXPECT_EQ(s.acc_mps2[a], static_cast<double>(static_cast<float>(truth[k].acc_mps2[a])));
      EXPECT_EQ(s.gyro_rps[a], static_cast<double>(static_cast<float>(truth[k].gyro_rps[a])));
    }
    EXPECT_FLOAT_EQ(s.temp_c, 35.5f);
  }
  e.mean_us /= static_cast<double>(e.n);
  // Loopback: the TIMESYNC offset is good to the link's asymmetry (tens of us) and time_usec to 1 us.
  EXPECT_LT(e.max_abs_us, 1000.0);
  std::printf(
      "HIGHRES_IMU over loopback UDP: %zu of %zu samples, stamp error vs the autopilot's truth: "
      "mean %+.1f us, max |%.1f| us; offset %.3f ms (truth %.3f ms), last rtt %.1f us\n",
      e.n, truth.size(), e.mean_us, e.max_abs_us, 1e-6 * static_cast<double>(d.time_sync().offset_ns()),
      1e-6 * static_cast<double>(o.offset_ns), 1e-3 * static_cast<double>(d.time_sync().stats().last_rtt_ns));
}

TEST(MavlinkHighresImu, TimeSyncPrefersShortRoundTrips) {
  // Every third answer waits 3 ms in the autopilot's queue behind IMU traffic: its offset sample is
  // 1.45 ms off. The running mean takes a third of that; trusting short exchanges keeps it small.
  auto run = [](bool prefer) {
    km::TimeSyncOptions o;
    o.prefer_short_round_trips = prefer;
    km::TimeSync ts(o);
    const int64_t offset = -7'000'000'000;
    int64_t now = 20'000'000'000;
    km::TimesyncMsg reply;
    for (int i = 0; i < 40; ++i) {
      const km::TimesyncMsg q = ts.request(now);
      const int64_t d1 = 100'000, d2 = i % 3 == 1 ? 3'000'000 : 100'000;
      km::TimesyncMsg ans;
      ans.tc1 = now + d1 + offset;
      ans.ts1 = q.ts1;
      now += d1 + d2;
      ts.on_message(ans, 1, 1, 1, 191, now, &reply);
      now += 1'000'000'000;
    }
    EXPECT_TRUE(ts.converged());
    return static_cast<double>(ts.offset_ns() - offset);
  };
  const double err_mean = run(false), err_short = run(true);
  EXPECT_GT(std::abs(err_mean), 300'000.0) << "the plain running mean is biased by the queued answers";
  EXPECT_LT(std::abs(err_short), 100'000.0);
  std::printf(
      "TIMESYNC with a queued answer in three: offset error %.0f us (mean) vs %.0f us (short round trips)\n",
      1e-3 * err_mean, 1e-3 * err_short);
}

TEST(MavlinkHighresImu, OverASerialPortToo) {
  // The same through the serial transport: the autopilot on a pty's master side, the driver on its slave.
  SimAutopilotOptions o;
  o.serial = true;
  o.offset_ns = 9'000'000'000 - kestrel::rt::now_ns();
  const auto truth = synthetic_imu(200, 1.5);
  auto owned = std::make_unique<SimAutopilot>(o, truth);
  SimAutopilot& ap = *owned;
  kd::MonotonicHostClock clock;
  kd::MavlinkImuConfig c;
  c.serial_device = ap.endpoint();
  c.serial_baud = 921600;
  c.rate_hz = 200;
  kd::MavlinkImuDriver d(c, clock);
  EXPECT_EQ(d.endpoint(), ap.endpoint() + ":921600");
  FixedSink sink(1000);
  run_driver(d, sink, ap, 10'000'000'000);
  EXPECT_TRUE(d.interval_accepted()) << d.report();
  ASSERT_GT(sink.samples.size(), truth.size() / 2) << d.report();
  std::size_t k = 0;
  double worst_us = 0;
  for (const auto& s : sink.samples) {
    k = match_index(ap, truth.size(), s.t_ns, k);
    worst_us = std::max(worst_us, 1e-3 * std::abs(static_cast<double>(s.t_ns - ap.t_host_ns(k))));
    EXPECT_EQ(s.acc_mps2[2], static_cast<double>(static_cast<float>(truth[k].acc_mps2[2])));
  }
  EXPECT_LT(worst_us, 1000.0);
  std::printf("HIGHRES_IMU over a pty: %zu of %zu samples, max stamp error %.1f us\n", sink.samples.size(),
              truth.size(), worst_us);
  // The autopilot's end of the line goes away (an adapter unplugged): counted, and the driver waits out
  // each period instead of spinning on the hung-up descriptor.
  owned.reset();
  const int64_t t0 = kestrel::rt::now_ns();
  for (int i = 0; i < 5; ++i) d.step(sink, 40'000'000);
  EXPECT_GT(d.counters().link_errors, 0u) << d.report();
  EXPECT_GT(kestrel::rt::now_ns() - t0, 100'000'000) << "5 steps returned at once: spinning";
}

TEST(MavlinkHighresImu, ScaledAndRawImuInTheirUnits) {
  for (auto msg : {kd::MavlinkImuMessage::kScaled, kd::MavlinkImuMessage::kRaw}) {
    SimAutopilotOptions o;
    o.offset_ns = 5'000'000'000 - kestrel::rt::now_ns();
    o.message = msg;
    const auto truth = synthetic_imu(100, 1.5);
    SimAutopilot ap(o, truth);
    kd::MonotonicHostClock clock;
    kd::MavlinkImuConfig c = driver_config(ap, 100);
    c.message = msg;
    c.raw_acc_mps2_per_lsb = o.raw_acc_mps2_per_lsb;
    c.raw_gyro_rad_s_per_lsb = o.raw_gyro_rad_s_per_lsb;
    kd::MavlinkImuDriver d(c, clock);
    FixedSink sink(1000);
    run_driver(d, sink, ap, 10'000'000'000);
    ASSERT_GT(sink.samples.size(), truth.size() / 2) << d.report();
    EXPECT_FLOAT_EQ(ap.requested_msgid(), msg == kd::MavlinkImuMessage::kScaled ? 26.0f : 27.0f);
    const double acc_q = msg == kd::MavlinkImuMessage::kScaled ? 9.80665e-3 : o.raw_acc_mps2_per_lsb;
    const double gyro_q = msg == kd::MavlinkImuMessage::kScaled ? 1e-3 : o.raw_gyro_rad_s_per_lsb;
    std::size_t k = 0;
    double worst_us = 0;
    for (const auto& s : sink.samples) {
      k = match_index(ap, truth.size(), s.t_ns, k);
      worst_us = std::max(worst_us, 1e-3 * std::abs(static_cast<double>(s.t_ns - ap.t_host_ns(k))));
      for (int a = 0; a < 3; ++a) {
        EXPECT_NEAR(s.acc_mps2[a], truth[k].acc_mps2[a], 0.5 * acc_q + 1e-9) << to_string(msg);
        EXPECT_NEAR(s.gyro_rps[a], truth[k].gyro_rps[a], 0.5 * gyro_q + 1e-9) << to_string(msg);
      }
      EXPECT_NEAR(s.temp_c, 35.5f, 1e-4);
    }
    // SCALED_IMU's time_boot_ms truncates to a millisecond.
    EXPECT_LT(worst_us, msg == kd::MavlinkImuMessage::kScaled ? 2000.0 : 1000.0) << to_string(msg);
  }
}

TEST(MavlinkHighresImu, FaultsAreCountedAndSurvived) {
  SimAutopilotOptions o;
  o.offset_ns = 1'000'000'000 - kestrel::rt::now_ns();
  o.nan_at = {100};
  o.repeat_time_at = {150};
  o.skip_at = {200, 201, 202, 203, 204};
  o.corrupt_at = {250};
  o.unknown_before = {300};
  o.future_at = {350};
  const auto truth = synthetic_imu(200, 2.0);
  SimAutopilot ap(o, truth);
  kd::MonotonicHostClock clock;
  kd::MavlinkImuDriver d(driver_config(ap, 200), clock);
  FixedSink sink(1000);
  run_driver(d, sink, ap, 10'000'000'000);
  const auto& c = d.counters();
  EXPECT_EQ(c.nonfinite, 1u) << d.report();
  EXPECT_EQ(c.out_of_order, 1u) << d.report();
  EXPECT_GE(c.gaps, 1u) << d.report();
  EXPECT_EQ(d.decoder_stats().bad_crc, 1u) << d.report();
  EXPECT_GE(d.decoder_stats().unknown_msgid, 1u) << d.report();
  EXPECT_EQ(c.stamp_outliers, 1u) << d.report();
  // The stream goes on after each fault, stamps strictly increasing, and the sample after
  // the NaN and after the skipped ones says samples were lost before it.
  ASSERT_GT(sink.samples.size(), 300u) << d.report();
  int flagged = 0;
  for (std::size_t i = 1; i < sink.samples.size(); ++i) {
    EXPECT_GT(sink.samples[i].t_ns, sink.samples[i - 1].t_ns);
    if (sink.samples[i].flags & kestrel::kImuGapBefore) {
      ++flagged;
      const int64_t dt = sink.samples[i].t_ns - sink.samples[i - 1].t_ns;
      EXPECT_GT(dt, 7'000'000) << "flag on sample " << i;
    }
  }
  EXPECT_GE(flagged, 4) << d.report();  // NaN, five skipped, the corrupt one, the one from the future
  std::printf("%s", d.report().c_str());
}

TEST(MavlinkHighresImu, SteadyStateAllocatesNothing) {
  ASSERT_TRUE(kestrel::rt::alloc_hook_linked());
  SimAutopilotOptions o;
  o.offset_ns = 2'000'000'000 - kestrel::rt::now_ns();
  o.signing = true;  // the signed receive path is the heavier one
  for (std::size_t i = 0; i < o.key.bytes.size(); ++i) o.key.bytes[i] = static_cast<uint8_t>(3 * i + 1);
  const auto truth = synthetic_imu(250, 3.0);
  SimAutopilot ap(o, truth);
  kd::MonotonicHostClock clock;
  kd::MavlinkImuConfig c = driver_config(ap, 250);
  c.signing = true;
  c.key = o.key;
  c.link_id = 2;
  kd::MavlinkImuDriver d(c, clock);
  FixedSink sink(2000);
  // Warm-up: until the clock is known and samples flow.
  const int64_t t0 = kestrel::rt::now_ns();
  while (sink.samples.size() < 50 && kestrel::rt::now_ns() - t0 < 5'000'000'000) d.step(sink, 100'000'000);
  ASSERT_GE(sink.samples.size(), 50u) << d.report();
  uint64_t allocs = 0, steps = 0;
  const std::size_t before = sink.samples.size();
  while (!ap.done() && kestrel::rt::now_ns() - t0 < 10'000'000'000) {
    kestrel::rt::AllocCountScope scope;
    d.step(sink, 100'000'000);
    allocs += scope.count();
    ++steps;
  }
  const std::size_t steady = sink.samples.size() - before;
  EXPECT_GT(steady, 400u) << d.report();
  EXPECT_EQ(allocs, 0u) << "over " << steps << " steps, " << steady << " samples";
  ASSERT_NE(d.signing_stats(), nullptr);
  EXPECT_GT(d.signing_stats()->accepted, steady);
  std::printf("steady state: %llu steps, %zu samples (signed), %llu allocations (malloc counted: %s)\n",
              (unsigned long long)steps, steady, (unsigned long long)allocs,
              kestrel::rt::alloc_hook_counts_malloc() ? "yes" : "no");
}

TEST(MavlinkHighresImu, LiveConfigImuTypeMavlinkRunsThroughLiveSensors) {
  const std::string dir = kestrel::test::temp_dir("mavlink_imu_live");
  SimAutopilotOptions o;
  o.offset_ns = 7'000'000'000 - kestrel::rt::now_ns();
  const auto truth = synthetic_imu(200, 1.5);
  SimAutopilot ap(o, truth);
  const std::string cfg_text =
      "drivers:\n  imu:\n    type: mavlink\n    mavlink:\n      udp: " + ap.endpoint() +
      "\n      message: highres_imu\n      rate_hz: 200\n";
  const std::string rig =
      "rig:\n  camera: {width_px: 640, height_px: 480, fx_px: 500, fy_px: 500, cx_px: 320, cy_px: 240}\n";
  std::ofstream(dir + "/live.yaml") << rig << cfg_text;
  const kd::LiveConfig cfg = kestrel::tools::load_live_config(dir + "/live.yaml");
  ASSERT_EQ(cfg.drivers.imu.type, kd::ImuType::kMavlink);
  EXPECT_EQ(cfg.drivers.imu.mavlink.udp, ap.endpoint());
  EXPECT_EQ(cfg.drivers.imu.mavlink.rate_hz, 200);
  kd::LiveSensors sensors(cfg);
  EXPECT_NE(sensors.description().find("MAVLink"), std::string::npos) << sensors.description();
  FixedSink sink(1000);
  struct NoFrames final : kd::FrameSink {
    bool push_frame(const kd::CameraFrame&) noexcept override { return true; }
  } frames;
  sensors.start(sink, frames);
  const int64_t t0 = kestrel::rt::now_ns();
  while (!ap.done() && kestrel::rt::now_ns() - t0 < 10'000'000'000)
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  sensors.stop();
  EXPECT_GT(sink.samples.size(), truth.size() / 2) << sensors.report();
  EXPECT_NE(sensors.report().find("mavlink imu"), std::string::npos) << sensors.report();
}

TEST(MavlinkHighresImu, LiveConfigErrorsNameTheKey) {
  auto err = [](const std::string& imu) {
    try {
      kd::driver_settings_from_yaml_node(YAML::Load("imu:\n" + imu), "cfg.yaml");
    } catch (const std::exception& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(err("  type: mavlink\n").find("drivers.imu.mavlink: missing"), std::string::npos);
  EXPECT_NE(err("  type: mavlink\n  mavlink: {rate_hz: 200}\n").find("udp"), std::string::npos);
  EXPECT_NE(err("  type: mavlink\n  mavlink: {udp: 'a:1', message: raw_imu}\n").find("raw_acc_mps2_per_lsb"),
            std::string::npos);
  EXPECT_NE(
      err("  type: mavlink\n  mavlink: {udp: 'a:1', message: fast_imu}\n").find("highres_imu, scaled_imu"),
      std::string::npos);
  EXPECT_NE(err("  type: mavlink\n  mavlink: {udp: 'a:1', signing: {key_file: /nonexistent/k.key}}\n")
                .find("/nonexistent/k.key"),
            std::string::npos);
}

TEST(MavlinkHighresImu, ShippedTemplateParsesWithItsKeyFile) {
  const std::string dir = kestrel::test::temp_dir("mavlink_imu_template");
  {
    std::ifstream in(std::string(KESTREL_SOURCE_DIR) + "/configs/openni2_px4_imu_mavlink.yaml");
    std::ofstream(dir + "/live.yaml") << in.rdbuf();
  }
  // Without fc.key beside it: the error names the key and the file.
  try {
    kestrel::tools::load_live_config(dir + "/live.yaml");
    ADD_FAILURE() << "loaded without its key file";
  } catch (const std::exception& e) {
    EXPECT_NE(std::string(e.what()).find(dir + "/fc.key"), std::string::npos) << e.what();
  }
  std::ofstream(dir + "/fc.key") << std::string(64, 'a') << "\n";
  const kd::LiveConfig c = kestrel::tools::load_live_config(dir + "/live.yaml");
  EXPECT_EQ(c.drivers.imu.type, kd::ImuType::kMavlink);
  EXPECT_TRUE(c.drivers.imu.mavlink.signing);
  EXPECT_EQ(c.drivers.imu.mavlink.link_id, 1);
  EXPECT_EQ(c.drivers.imu.mavlink.key.bytes[0], 0xAA);
  EXPECT_TRUE(c.mavlink.signing);
  EXPECT_EQ(c.mavlink.signing_link_id, 2);
  EXPECT_EQ(c.rig.imu_rate_hz, 200);
}

// The libFuzzer target's entry (fuzz_mavlink_imu) on a clean stream, then on mutations of it.
TEST(MavlinkHighresImu, FuzzEntryStampsCleanStreamsAndSurvivesMutations) {
  for (uint8_t mode : {0, 1, 2, 4, 6}) {
    km::MavlinkSigning sign(kestrel::test::fuzz_signing_key(), 3, &kestrel::test::fuzz_signing_clock);
    km::MavlinkSigning* sg = (mode & 4) != 0 ? &sign : nullptr;
    std::string bytes(1, static_cast<char>(mode));
    uint8_t f[km::kMaxFrameBytes];
    uint8_t seq = 0;
    for (int i = 0; i < 6; ++i) {
      km::TimesyncMsg t;
      t.tc1 = 5'000'000'000 + i;
      t.ts1 = kestrel::test::kFuzzHostNs;
      bytes.append(reinterpret_cast<char*>(f), km::encode_timesync(t, seq++, 1, 1, f, sg));
    }
    for (int i = 0; i < 20; ++i) {
      const uint64_t t_us = 4'900'000 + 5000 * static_cast<uint64_t>(i);
      std::size_t n = 0;
      if (mode % 4 == 0) {
        km::HighresImuMsg m;
        m.time_usec = t_us, m.zacc = -9.8f;
        n = km::encode_highres_imu(m, seq++, 1, 1, f, sg);
      } else if (mode % 4 == 1) {
        km::ScaledImuMsg m;
        m.time_boot_ms = static_cast<uint32_t>(t_us / 1000), m.zacc = -1000;
        n = km::encode_scaled_imu(m, seq++, 1, 1, f, sg);
      } else {
        km::RawImuMsg m;
        m.time_usec = t_us, m.zacc = -4096;
        n = km::encode_raw_imu(m, seq++, 1, 1, f, sg);
      }
      bytes.append(reinterpret_cast<char*>(f), n);
    }
    const auto* d = reinterpret_cast<const uint8_t*>(bytes.data());
    // The clock converges after 5 answers; all 20 samples (one in 17 refused by the sink) are stamped.
    EXPECT_GE(kestrel::test::mavlink_imu_fuzz_one(d, bytes.size()), 18u) << "mode " << int(mode);
    std::mt19937 rng(mode);
    for (int trial = 0; trial < 500; ++trial) {
      std::string m = bytes;
      const int edits = 1 + static_cast<int>(rng() % 8);
      for (int e = 0; e < edits; ++e) m[1 + rng() % (m.size() - 1)] = static_cast<char>(rng());
      kestrel::test::mavlink_imu_fuzz_one(reinterpret_cast<const uint8_t*>(m.data()), m.size());
    }
  }
}

// ---- signing -----------------------------------------------------------------------------

namespace {

int64_t g_unix_ns = 1'750'000'000'000'000'000;  // 2025-06-15, what the injected clock says
int64_t test_clock() { return g_unix_ns; }

km::SigningKey key_of(uint8_t seed) {
  km::SigningKey k;
  for (std::size_t i = 0; i < k.bytes.size(); ++i) k.bytes[i] = static_cast<uint8_t>(seed + 7 * i);
  return k;
}

std::string hex(const uint8_t* d, std::size_t n) {
  static const char* k = "0123456789abcdef";
  std::string s;
  for (std::size_t i = 0; i < n; ++i) s += k[d[i] >> 4], s += k[d[i] & 15];
  return s;
}

std::string node_cache() {
  const std::string cache = std::string(KESTREL_BUILD_DIR) + "/npm-cache";
  const auto r = kestrel::test::run_command("sh " + std::string(KESTREL_SOURCE_DIR) +
                                            "/tests/mavlink/install_node_mavlink.sh " + cache);
  return r.code == 0 ? cache : "error: " + r.out;
}

std::string node(const std::string& cache, const std::string& args, int* code) {
  const auto r =
      kestrel::test::run_command("NODE_PATH=" + cache + "/node_modules node " +
                                 std::string(KESTREL_SOURCE_DIR) + "/tests/mavlink/signing_check.js " + args);
  *code = r.code;
  return r.out;
}

std::vector<km::MavlinkFrame> decode_all(const std::string& bytes, km::MavlinkSigning* s) {
  km::MavlinkDecoder d;
  d.set_signing(s);
  std::vector<km::MavlinkFrame> out;
  d.feed(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size(),
         [&](const km::MavlinkFrame& f) { out.push_back(f); });
  return out;
}

std::string read_file(const std::string& p) {
  std::ifstream f(p, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
}

}  // namespace

TEST(MavlinkSigning, Sha256MatchesOpenSsl) {
  std::mt19937 rng(43);
  std::vector<uint8_t> data(1000);
  for (auto& b : data) b = static_cast<uint8_t>(rng());
  for (std::size_t n : {0, 1, 3, 55, 56, 57, 63, 64, 65, 119, 120, 128, 255, 300, 999}) {
    uint8_t ours[32], theirs[32];
    km::Sha256 h;
    // In uneven pieces: the block buffering must not matter.
    h.update(data.data(), n / 3);
    h.update(data.data() + n / 3, n - n / 3);
    h.finish(ours);
    unsigned len = 0;
    ASSERT_EQ(EVP_Digest(data.data(), n, theirs, &len, EVP_sha256(), nullptr), 1);
    EXPECT_EQ(hex(ours, 32), hex(theirs, 32)) << n << " bytes";
  }
  uint8_t abc[32];
  km::Sha256 h;
  h.update(reinterpret_cast<const uint8_t*>("abc"), 3);
  h.finish(abc);
  EXPECT_EQ(hex(abc, 32),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");  // FIPS 180-2 B.1
}

TEST(MavlinkSigning, WeVerifyWhatNodeMavlinkSigns) {
  const std::string cache = node_cache();
  if (cache.rfind("error: ", 0) == 0)
    GTEST_SKIP() << "node-mavlink unavailable, signing NOT checked against it: " << cache;
  const std::string dir = kestrel::test::temp_dir("mavlink_signing_node");
  const km::SigningKey key = key_of(11);
  const int64_t unix_ms = g_unix_ns / 1'000'000;
  int code = 0;
  const std::string out =
      node(cache,
           "sign " + hex(key.bytes.data(), 32) + " " + dir + "/signed.bin " + std::to_string(unix_ms) + " 3",
           &code);
  ASSERT_EQ(code, 0) << out;
  const std::string bytes = read_file(dir + "/signed.bin");

  km::MavlinkSigning ours(key, 0, &test_clock);
  const auto frames = decode_all(bytes, &ours);
  ASSERT_EQ(frames.size(), 4u) << out;
  EXPECT_EQ(ours.stats().accepted, 4u);
  EXPECT_EQ(frames[0].msgid, km::kMsgIdHighresImu);
  const km::HighresImuMsg imu = km::unpack_highres_imu(frames[0].payload);
  EXPECT_EQ(imu.time_usec, 123456789u);
  EXPECT_EQ(imu.xacc, 0.5f);
  EXPECT_EQ(imu.zacc, -9.75f);
  EXPECT_EQ(imu.zgyro, 1.5f);
  EXPECT_EQ(imu.temperature, 31.5f);
  EXPECT_EQ(frames[1].msgid, km::kMsgIdTimesync);
  EXPECT_EQ(km::unpack_timesync(frames[1].payload).tc1, 5'000'000'000);
  EXPECT_EQ(km::unpack_command_ack(frames[2].payload).command, 511);
  EXPECT_EQ(km::unpack_command_long(frames[3].payload).param[0], 105.0f);
  // Our timestamp follows the newest accepted one (node's last, 10 us units since 2015).
  EXPECT_EQ(ours.timestamp(), static_cast<uint64_t>(unix_ms + 3 - km::kSigningEpochUnixS * 1000) * 100);

  // The same bytes again: every timestamp is not newer than its stream's last: replays.
  EXPECT_TRUE(decode_all(bytes, &ours).empty());
  EXPECT_EQ(ours.stats().replayed, 4u);
  // Another key: nothing verifies.
  km::MavlinkSigning wrong(key_of(12), 0, &test_clock);
  EXPECT_TRUE(decode_all(bytes, &wrong).empty());
  EXPECT_EQ(wrong.stats().bad_signature, 4u);
  // Our clock two minutes ahead of node's stamps: too old for a stream we have never seen.
  g_unix_ns += 120'000'000'000;
  km::MavlinkSigning late(key, 0, &test_clock);
  EXPECT_TRUE(decode_all(bytes, &late).empty());
  EXPECT_EQ(late.stats().too_old, 4u);
  g_unix_ns -= 120'000'000'000;
  // Without signing on, the decoder reads them (signature skipped), as before.
  EXPECT_EQ(decode_all(bytes, nullptr).size(), 4u);
}

TEST(MavlinkSigning, NodeMavlinkVerifiesWhatWeSign) {
  const std::string cache = node_cache();
  if (cache.rfind("error: ", 0) == 0)
    GTEST_SKIP() << "node-mavlink unavailable, signing NOT checked against it: " << cache;
  const std::string dir = kestrel::test::temp_dir("mavlink_signing_ours");
  const km::SigningKey key = key_of(21);
  km::MavlinkSigning s(key, 5, &test_clock);
  std::string bytes;
  uint8_t f[km::kMaxFrameBytes];
  km::HeartbeatMsg hb;
  bytes.append(reinterpret_cast<char*>(f), km::encode_heartbeat(hb, 0, 1, 197, f, &s));
  km::TimesyncMsg ts;
  ts.ts1 = 987654321;
  bytes.append(reinterpret_cast<char*>(f), km::encode_timesync(ts, 1, 1, 197, f, &s));
  km::OdometryMsg od;
  od.x = 1.5f;
  od.time_usec = 42;
  bytes.append(reinterpret_cast<char*>(f), km::encode_odometry(od, 2, 1, 197, f, &s));
  km::CommandLongMsg cmd;
  cmd.command = km::kMavCmdSetMessageInterval;
  cmd.param[0] = 105;
  cmd.param[1] = 5000;
  cmd.target_system = 1;
  cmd.target_component = 1;
  bytes.append(reinterpret_cast<char*>(f), km::encode_command_long(cmd, 3, 1, 197, f, &s));
  std::ofstream(dir + "/ours.bin", std::ios::binary) << bytes;

  int code = 0;
  const std::string out = node(cache, "verify " + hex(key.bytes.data(), 32) + " " + dir + "/ours.bin", &code);
  ASSERT_EQ(code, 0) << out;
  std::istringstream in(out);
  std::string line;
  std::vector<std::vector<long long>> pkts;
  bool saw_x = false, saw_param = false;
  while (std::getline(in, line)) {
    std::istringstream ls(line);
    std::string tag;
    ls >> tag;
    if (tag == "pkt") {
      std::vector<long long> v(8);
      for (auto& x : v) ls >> x;
      pkts.push_back(v);
    }
    saw_x = saw_x || line == "field 2 x 1.5";
    saw_param = saw_param || line == "field 3 param2 5000";
  }
  ASSERT_EQ(pkts.size(), 4u) << out;
  const uint64_t t0 = km::signing_timestamp_of_unix_ns(g_unix_ns);
  const long long ids[] = {0, 111, 331, 76};
  for (std::size_t i = 0; i < 4; ++i) {
    EXPECT_EQ(pkts[i][1], ids[i]) << out;
    EXPECT_EQ(pkts[i][4], 1) << "signed flag, frame " << i;
    EXPECT_EQ(pkts[i][5], 5) << "link id, frame " << i;
    // The clock stands still: each frame takes the next timestamp.
    EXPECT_EQ(static_cast<uint64_t>(pkts[i][6]), i == 0 ? t0 : t0 + i) << "timestamp, frame " << i;
    EXPECT_EQ(pkts[i][7], 1) << "node's signature check, frame " << i << "\n" << out;
  }
  EXPECT_TRUE(saw_x && saw_param) << out;
  // node's check can fail: with another key it does.
  const std::string bad =
      node(cache, "verify " + hex(key_of(22).bytes.data(), 32) + " " + dir + "/ours.bin", &code);
  std::istringstream bin(bad);
  int refused = 0;
  while (std::getline(bin, line))
    if (line.rfind("pkt ", 0) == 0)
      refused += line.size() > 2 && line.substr(line.size() - 2) == " 0" ? 1 : 0;
  EXPECT_EQ(refused, 4) << bad;
}

TEST(MavlinkSigning, RejectsUnsignedTamperedReplayedAndOldFrames) {
  const km::SigningKey key = key_of(31);
  km::MavlinkSigning tx(key, 1, &test_clock), rx(key, 0, &test_clock);
  uint8_t f[km::kMaxFrameBytes];
  km::HighresImuMsg m;
  m.time_usec = 1000;
  m.xacc = 1;
  const std::size_t n = km::encode_highres_imu(m, 0, 1, 1, f, &tx);
  const std::string good(reinterpret_cast<char*>(f), n);
  EXPECT_EQ(f[2], km::kIncompatSigned);
  EXPECT_EQ(decode_all(good, &rx).size(), 1u);
  // Unsigned while signing is on.
  const std::size_t un = km::encode_highres_imu(m, 1, 1, 1, f, nullptr);
  EXPECT_TRUE(decode_all(std::string(reinterpret_cast<char*>(f), un), &rx).empty());
  EXPECT_EQ(rx.stats().unsigned_rejected, 1u);
  // A payload byte changed and the checksum fixed up (an attacker can do that): the signature fails.
  std::string tampered = good;
  tampered[12] ^= 1;
  uint8_t extra = 0;
  std::size_t full = 0;
  km::message_spec(km::kMsgIdHighresImu, &extra, &full);
  const std::size_t plen = static_cast<uint8_t>(tampered[1]);
  uint16_t crc =
      km::crc_x25(reinterpret_cast<const uint8_t*>(tampered.data()) + 1, km::kHeaderV2Bytes - 1 + plen);
  crc = km::crc_x25_accumulate(extra, crc);
  tampered[km::kHeaderV2Bytes + plen] = static_cast<char>(crc & 0xFF);
  tampered[km::kHeaderV2Bytes + plen + 1] = static_cast<char>(crc >> 8);
  EXPECT_TRUE(decode_all(tampered, &rx).empty());
  EXPECT_EQ(rx.stats().bad_signature, 1u);
  // Replayed.
  EXPECT_TRUE(decode_all(good, &rx).empty());
  EXPECT_EQ(rx.stats().replayed, 1u);
  // The next timestamp of that stream is accepted; another link id is another stream.
  const std::size_t n2 = km::encode_highres_imu(m, 2, 1, 1, f, &tx);
  EXPECT_EQ(decode_all(std::string(reinterpret_cast<char*>(f), n2), &rx).size(), 1u);
  km::MavlinkSigning tx_other_link(key, 9, &test_clock);
  const std::size_t n3 = km::encode_highres_imu(m, 3, 1, 1, f, &tx_other_link);
  EXPECT_EQ(decode_all(std::string(reinterpret_cast<char*>(f), n3), &rx).size(), 1u);
  // A sender whose clock is over a minute behind ours, on a new stream: too old.
  g_unix_ns -= 61'000'000'000;
  km::MavlinkSigning stale(key, 4, &test_clock);
  const std::size_t n4 = km::encode_highres_imu(m, 4, 1, 1, f, &stale);
  g_unix_ns += 61'000'000'000;
  EXPECT_TRUE(decode_all(std::string(reinterpret_cast<char*>(f), n4), &rx).empty());
  EXPECT_EQ(rx.stats().too_old, 1u);
  EXPECT_EQ(rx.stats().accepted, 3u);
}

TEST(MavlinkSigning, KeyFileErrorsNameTheFile) {
  const std::string dir = kestrel::test::temp_dir("mavlink_signing_key");
  auto err = [](const std::string& p) {
    try {
      km::load_signing_key(p);
    } catch (const std::exception& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(err(dir + "/missing.key").find(dir + "/missing.key"), std::string::npos);
  std::ofstream(dir + "/short.key") << "0123456789";
  EXPECT_NE(err(dir + "/short.key").find(dir + "/short.key: MAVLink signing key: expected 32 raw bytes"),
            std::string::npos);
  std::ofstream(dir + "/badhex.key") << std::string(63, 'a') << "g\n";
  EXPECT_NE(err(dir + "/badhex.key").find("badhex.key"), std::string::npos);
  // `sha256sum` output, and 32 raw bytes.
  std::ofstream(dir + "/hex.key") << "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f  -\n";
  const km::SigningKey k = km::load_signing_key(dir + "/hex.key");
  for (int i = 0; i < 32; ++i) EXPECT_EQ(k.bytes[i], i);
  std::string raw(32, '\0');
  for (int i = 0; i < 32; ++i) raw[i] = static_cast<char>(255 - i);
  std::ofstream(dir + "/raw.key", std::ios::binary) << raw;
  EXPECT_EQ(km::load_signing_key(dir + "/raw.key").bytes[0], 255);
  // The live config names the key and the file, relative to the config's folder.
  try {
    kd::mavlink_settings_from_yaml_node(YAML::Load("signing: {key_file: short.key, link_id: 3}"),
                                        dir + "/live.yaml");
    ADD_FAILURE() << "short key accepted";
  } catch (const std::exception& e) {
    EXPECT_NE(std::string(e.what()).find("mavlink.signing.key_file"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find(dir + "/short.key"), std::string::npos) << e.what();
  }
  const kd::MavlinkSettings ms = kd::mavlink_settings_from_yaml_node(
      YAML::Load("signing: {key_file: hex.key, link_id: 3}"), dir + "/live.yaml");
  EXPECT_TRUE(ms.signing);
  EXPECT_EQ(ms.signing_link_id, 3);
  EXPECT_EQ(ms.signing_key.bytes[31], 31);
}

TEST(MavlinkSigning, DriverIgnoresUnsignedAndWronglySignedImuAndSignsWhatItSends) {
  SimAutopilotOptions o;
  o.offset_ns = 4'000'000'000 - kestrel::rt::now_ns();
  o.signing = true;
  o.key = key_of(41);
  o.unsigned_at = {100, 101};
  o.wrong_key_at = {150};
  const auto truth = synthetic_imu(200, 1.5);
  SimAutopilot ap(o, truth);
  kd::MonotonicHostClock clock;
  kd::MavlinkImuConfig c = driver_config(ap, 200);
  c.signing = true;
  c.key = o.key;
  c.link_id = 1;
  kd::MavlinkImuDriver d(c, clock);
  FixedSink sink(1000);
  run_driver(d, sink, ap, 10'000'000'000);
  ASSERT_NE(d.signing_stats(), nullptr);
  EXPECT_EQ(d.signing_stats()->unsigned_rejected, 2u) << d.report();
  EXPECT_EQ(d.signing_stats()->bad_signature, 1u) << d.report();
  EXPECT_EQ(d.decoder_stats().unauthenticated, 3u);
  EXPECT_TRUE(d.interval_accepted());
  // The autopilot, verifying, accepted every command and TIMESYNC we sent.
  EXPECT_EQ(ap.unauthenticated_in(), 0u);
  EXPECT_GT(ap.frames_in(), 3);
  ASSERT_GT(sink.samples.size(), 200u) << d.report();
  for (int skipped : {100, 101, 150})
    for (const auto& s : sink.samples)
      EXPECT_GT(std::llabs(s.t_ns - ap.t_host_ns(skipped)), 1'000'000) << skipped;

  // A driver without the key gets nothing from a signing autopilot: it ignores our commands.
  SimAutopilot ap2(o, truth);
  kd::MavlinkImuDriver d2(driver_config(ap2, 200), clock);
  FixedSink sink2(10);
  const int64_t t0 = kestrel::rt::now_ns();
  while (kestrel::rt::now_ns() - t0 < 500'000'000) d2.step(sink2, 50'000'000);
  EXPECT_EQ(ap2.commands(), 0);
  EXPECT_GT(ap2.unauthenticated_in(), 0u);
  EXPECT_TRUE(sink2.samples.empty());
}

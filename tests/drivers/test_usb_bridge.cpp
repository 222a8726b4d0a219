// USB IMU bridge: wire-format fixtures, the stream parser, and the driver
// against the simulated bridge with loss, reordering, CRC errors, garbage,
// split transfers, stalls, reboots and a full sink. Each fault is counted and
// the stream recovers; sample times stay increasing.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>

#include "kestrel/drivers/usb_bridge.hpp"
#include "kestrel/drivers/usb_bridge_fake.hpp"
#include "kestrel/drivers/usb_bridge_protocol.hpp"
#include "vec_imu_sink.hpp"

namespace kestrel::drivers {
namespace {

using namespace usb_bridge;

TEST(UsbBridgeProtocol, Crc32IsTheIeeeCheckValue) {
  // CRC-32/ISO-HDLC's check value: the definition the bridge firmware uses.
  const char* s = "123456789";
  EXPECT_EQ(crc32(reinterpret_cast<const uint8_t*>(s), 9), 0xCBF43926u);
  EXPECT_EQ(crc32(nullptr, 0), 0u);
  EXPECT_EQ(crc32(nullptr, 0, 0x1234u), 0x1234u);  // nothing added: the running value stands
  // Chained over two pieces, as over one.
  const auto* p = reinterpret_cast<const uint8_t*>(s);
  EXPECT_EQ(crc32(p + 4, 5, crc32(p, 4)), 0xCBF43926u);
}

TEST(UsbBridgeProtocol, PacketBytesFixture) {
  // A one-strobe packet, byte by byte as docs/drivers/usb-imu-bridge.md shows it.
  StrobeWire w{0x0102030405060708ull, 7, 4000};
  uint8_t payload[64];
  const size_t len = encode_strobe_payload(&w, 1, payload, sizeof payload);
  ASSERT_EQ(len, 20u);
  uint8_t pkt[128];
  const size_t n = encode_packet(PacketType::kStrobe, 0x1234, 1'000'000, payload, len, pkt, sizeof pkt);
  ASSERT_EQ(n, 40u);
  const uint8_t header[16] = {'K', 'B', 1, 2, 0x34, 0x12, 20, 0, 0x40, 0x42, 0x0F, 0, 0, 0, 0, 0};
  EXPECT_EQ(std::memcmp(pkt, header, 16), 0);
  const uint8_t body[20] = {1,    0,    0, 0, 0x08, 0x07, 0x06, 0x05, 0x04, 0x03,
                            0x02, 0x01, 7, 0, 0,    0,    0xA0, 0x0F, 0,    0};
  EXPECT_EQ(std::memcmp(pkt + 16, body, 20), 0);
  const uint32_t crc = crc32(pkt, 36);
  EXPECT_EQ(crc, 0xB232E7C0u);  // as the hand-written table computed it before zlib took over
  EXPECT_EQ(pkt[36] | (pkt[37] << 8) | (pkt[38] << 16) | (static_cast<uint32_t>(pkt[39]) << 24), crc);
}

TEST(UsbBridgeProtocol, ImuPayloadRoundTrip) {
  ImuWireSample in[3];
  for (int i = 0; i < 3; ++i) {
    in[i].t_us = 1000000ull * static_cast<unsigned>(i) + 17;
    in[i].gyro[0] = static_cast<int16_t>(-32768 + i);
    in[i].acc[2] = static_cast<int16_t>(2047 - i);
    in[i].temp_raw = static_cast<int8_t>(-3 * i);
    in[i].flags = static_cast<uint8_t>(i);
    in[i].sample_seq = static_cast<uint16_t>(65534 + i);
  }
  uint8_t buf[256];
  const size_t len = encode_imu_payload(in, 3, buf, sizeof buf);
  ASSERT_EQ(len, 4 + 3 * kImuSampleBytes);
  ImuWireSample out[4];
  size_t n = 0;
  ASSERT_TRUE(decode_imu_payload(buf, len, out, 4, n));
  ASSERT_EQ(n, 3u);
  for (int i = 0; i < 3; ++i) {
    EXPECT_EQ(out[i].t_us, in[i].t_us);
    EXPECT_EQ(out[i].gyro[0], in[i].gyro[0]);
    EXPECT_EQ(out[i].acc[2], in[i].acc[2]);
    EXPECT_EQ(out[i].temp_raw, in[i].temp_raw);
    EXPECT_EQ(out[i].flags, in[i].flags);
    EXPECT_EQ(out[i].sample_seq, in[i].sample_seq);
  }
  EXPECT_FALSE(decode_imu_payload(buf, len - 1, out, 4, n));  // count and length disagree
  EXPECT_FALSE(decode_imu_payload(buf, len, out, 2, n));      // more than the caller can take
}

std::vector<uint8_t> status_packet(uint16_t seq) {
  StatusWire st;
  st.boot_id = 99;
  uint8_t p[64];
  const size_t len = encode_status_payload(st, p, sizeof p);
  std::vector<uint8_t> out(kMaxPacketBytes);
  out.resize(encode_packet(PacketType::kStatus, seq, 1000u * seq, p, len, out.data(), out.size()));
  return out;
}

TEST(UsbBridgeProtocol, ParserSurvivesSplitsGarbageAndCorruption) {
  std::vector<uint8_t> stream;
  const uint8_t garbage[] = {0x00, 'K', 'B', 0x07, 'K', 0xFF, 'B'};
  for (uint16_t i = 0; i < 40; ++i) {
    auto p = status_packet(i);
    if (i == 3) p[20] ^= 0x10;  // payload corrupted
    if (i == 6) p[2] = 9;       // unknown version
    if (i == 8) p[7] = 0x03;    // length 800: waits, then fails its CRC
    if (i == 9) stream.insert(stream.end(), garbage, garbage + sizeof garbage);
    stream.insert(stream.end(), p.begin(), p.end());
  }
  // Feed one byte at a time: the worst split.
  StreamParser parser;
  std::vector<uint16_t> seqs;
  for (uint8_t b : stream) {
    parser.feed(&b, 1);
    StreamParser::Packet pk;
    while (parser.next(pk)) seqs.push_back(pk.header.seq);
  }
  // A bogus length delays the packets behind it (at most one maximum packet)
  // but loses none of them.
  std::vector<uint16_t> want;
  for (uint16_t i = 0; i < 40; ++i)
    if (i != 3 && i != 6 && i != 8) want.push_back(i);
  EXPECT_EQ(seqs, want);
  EXPECT_EQ(parser.counters().crc_errors, 2u);
  EXPECT_GE(parser.counters().bad_headers, 1u);
  EXPECT_GT(parser.counters().bytes_skipped, sizeof garbage);
  EXPECT_EQ(parser.counters().packets, 37u);
}

// ---- driver against the simulated bridge -------------------------------------------

using VecImuSink = kestrel::test::VecImuSink;
struct VecStrobeSink final : StrobeSink {
  std::vector<StrobeStamp> s;
  bool push(const StrobeStamp& x) noexcept override {
    s.push_back(x);
    return true;
  }
};

struct Bench {
  ManualClock clock{10'000'000'000};
  FakeUsbBridge fake;
  UsbBridgeConfig cfg;
  std::unique_ptr<UsbBridgeDriver> drv;
  VecImuSink imu;
  VecStrobeSink strobes;

  explicit Bench(const FakeBridgeOptions& o) : fake(clock, o) {
    cfg.clock.latency_floor_ns = o.latency_floor_ns;  // calibrated constant latency
    drv = std::make_unique<UsbBridgeDriver>(fake, clock, cfg);
  }
  void run_for(int64_t ns) {
    const int64_t end = clock.now_ns() + ns;
    while (clock.now_ns() < end) drv->step(imu, &strobes);
  }
};

void expect_increasing(const std::vector<ImuSample>& s) {
  for (size_t i = 1; i < s.size(); ++i) {
    ASSERT_GT(s[i].t_ns, s[i - 1].t_ns) << i;
    ASSERT_GT(s[i].seq, s[i - 1].seq) << i;
  }
}

struct Err {
  double rms_us = 0, max_us = 0;
  size_t n = 0;
};
Err time_error(const Bench& b, int64_t after_ns) {
  Err e;
  double sq = 0;
  const auto& truth = b.fake.imu_truth();
  for (const ImuSample& s : b.imu.samples) {
    if (s.t_ns < after_ns || s.seq >= truth.size()) continue;
    const double us = static_cast<double>(s.t_ns - truth[s.seq].t_host_ns) * 1e-3;
    sq += us * us;
    e.max_us = std::max(e.max_us, std::abs(us));
    ++e.n;
  }
  e.rms_us = e.n ? std::sqrt(sq / static_cast<double>(e.n)) : 0;
  return e;
}

TEST(UsbBridgeDriver, CleanStreamTimesAndValues) {
  FakeBridgeOptions o;
  o.skew = 80e-6;
  Bench b(o);
  b.fake.motion = [](int64_t, double g[3], double a[3]) {
    g[0] = 0.1, g[1] = -0.2, g[2] = 0.3;
    a[0] = 1.0, a[1] = 0.0, a[2] = 9.80665;
  };
  b.run_for(30'000'000'000);
  EXPECT_EQ(b.drv->state(), UsbBridgeState::kStreaming);
  const auto& c = b.drv->counters();
  EXPECT_EQ(c.packets_lost + c.crc_errors + c.samples_lost + c.packets_late, 0u);
  EXPECT_NEAR(static_cast<double>(b.imu.samples.size()), 12000, 3);
  EXPECT_NEAR(static_cast<double>(b.strobes.s.size()), 900, 2);
  expect_increasing(b.imu.samples);
  const ImuSample& s = b.imu.samples.back();
  EXPECT_NEAR(s.gyro_rps[2], 0.3, 1.1e-3);
  EXPECT_NEAR(s.acc_mps2[0], 1.0, 0.08);
  EXPECT_FLOAT_EQ(s.temp_c, 26.0f);
  const Err e = time_error(b, b.clock.now_ns() - 27'000'000'000);
  std::printf(
      "[ figure ] USB bridge end-to-end (80 ppm drift, jitter to 2 ms): sample time RMS %.1f us, max %.1f "
      "us\n",
      e.rms_us, e.max_us);
  EXPECT_LT(e.rms_us, 50.0);
  EXPECT_NEAR(b.drv->clock_sync().skew(), 80e-6, 5e-6);
}

TEST(UsbBridgeDriver, LossReorderCrcGarbageAndSplitsAreCountedAndSurvived) {
  FakeBridgeOptions o;
  o.skew = -100e-6;
  o.loss = 0.05;
  o.reorder = 0.02;
  o.crc_error = 0.03;
  o.garbage = 0.02;
  o.max_transfer_bytes = 64;  // full-speed bulk packets: every IMU packet split
  o.seed = 5;
  Bench b(o);
  b.run_for(60'000'000'000);
  const auto& c = b.drv->counters();
  std::printf(
      "[ figure ] USB faults over 60 s: sent %llu, dropped %llu, corrupted %llu, reordered %llu, garbage "
      "%llu | "
      "driver: lost %llu, crc %llu, late %llu, skipped bytes %llu, samples lost %llu, late %llu\n",
      (unsigned long long)b.fake.packets_sent(), (unsigned long long)b.fake.packets_dropped(),
      (unsigned long long)b.fake.packets_corrupted(), (unsigned long long)b.fake.packets_reordered(),
      (unsigned long long)b.fake.garbage_inserted(), (unsigned long long)c.packets_lost,
      (unsigned long long)c.crc_errors, (unsigned long long)c.packets_late,
      (unsigned long long)c.bytes_skipped, (unsigned long long)c.samples_lost,
      (unsigned long long)c.samples_late);
  EXPECT_EQ(b.drv->state(), UsbBridgeState::kStreaming);
  // Every corrupted packet is a CRC error (a flipped magic byte is skipped as garbage instead).
  EXPECT_GE(c.crc_errors + c.bad_headers, b.fake.packets_corrupted() * 9 / 10);
  EXPECT_GT(c.bytes_skipped, 0u);
  // Lost on the wire or to CRC: every one shows up as a sequence gap.
  EXPECT_GE(c.packets_lost, b.fake.packets_dropped());
  EXPECT_LE(c.packets_late, b.fake.packets_reordered());
  EXPECT_GE(c.packets_late, b.fake.packets_reordered() * 8 / 10);
  EXPECT_GT(c.samples_lost, 0u);
  expect_increasing(b.imu.samples);
  // Delivered + lost = produced (a late arrival was counted lost at its gap,
  // then dropped: time order is kept).
  EXPECT_GT(c.samples_late, 0u);
  EXPECT_NEAR(static_cast<double>(b.imu.samples.size() + c.samples_lost),
              static_cast<double>(b.fake.imu_truth().size()), 30.0);  // the fake generates ~20 ms ahead
  bool gap = false;
  for (const auto& s : b.imu.samples) gap = gap || (s.flags & kImuGapBefore);
  EXPECT_TRUE(gap);
  const Err e = time_error(b, b.clock.now_ns() - 55'000'000'000);
  std::printf("[ figure ] USB bridge with faults: sample time RMS %.1f us, max %.1f us\n", e.rms_us,
              e.max_us);
  EXPECT_LT(e.rms_us, 50.0);
}

TEST(UsbBridgeDriver, StallTimesOutAndRecovers) {
  FakeBridgeOptions o;
  Bench b(o);
  b.run_for(2'000'000'000);
  const int64_t t = b.clock.now_ns();
  b.fake.stall(t, t + 500'000'000);
  b.run_for(400'000'000);
  EXPECT_EQ(b.drv->state(), UsbBridgeState::kStalled);
  EXPECT_EQ(b.drv->counters().timeouts, 1u);
  b.run_for(1'000'000'000);
  EXPECT_EQ(b.drv->state(), UsbBridgeState::kStreaming);
  EXPECT_GT(b.drv->counters().samples_lost, 150u);
  expect_increasing(b.imu.samples);
}

TEST(UsbBridgeDriver, BridgeRebootRestartsClockAndSequences) {
  FakeBridgeOptions o;
  Bench b(o);
  b.run_for(3'000'000'000);
  b.fake.reboot_at(b.clock.now_ns() + 10'000'000);
  const size_t before = b.imu.samples.size();
  b.run_for(5'000'000'000);
  const auto& c = b.drv->counters();
  EXPECT_EQ(c.bridge_reboots, 1u);
  EXPECT_EQ(b.drv->state(), UsbBridgeState::kStreaming);
  EXPECT_GT(b.imu.samples.size(), before + 1900);
  // Times after the reboot are right again (the old mapping is gone).
  const ImuSample& last = b.imu.samples.back();
  EXPECT_NEAR(static_cast<double>(last.t_ns), static_cast<double>(b.clock.now_ns()), 3e6);
}

TEST(UsbBridgeDriver, ConfigMismatchIsCountedAndTheBridgeWins) {
  FakeBridgeOptions o;
  o.acc_range_code = 0x08;  // the bridge runs +-8 g, the config says +-16 g
  Bench b(o);
  b.run_for(1'000'000'000);
  EXPECT_EQ(b.drv->counters().config_mismatches, 1u);
  // The fake encodes with +-16 g counts; decoded with the bridge's +-8 g it reads half.
  EXPECT_NEAR(b.imu.samples.back().acc_mps2[2], 9.80665 / 2, 0.05);
}

TEST(UsbBridgeDriver, FullSinkAndDisconnect) {
  FakeBridgeOptions o;
  Bench b(o);
  b.imu.capacity = 100;
  b.run_for(1'000'000'000);
  EXPECT_EQ(b.imu.samples.size(), 100u);
  EXPECT_GT(b.drv->counters().sink_drops, 250u);
  b.fake.set_disconnected(true);
  b.run_for(100'000'000);
  EXPECT_EQ(b.drv->state(), UsbBridgeState::kDisconnected);
  EXPECT_EQ(b.drv->counters().usb_errors, 1u);
}

TEST(UsbBridgeDriver, StrobesMapToTheHostClock) {
  FakeBridgeOptions o;
  o.skew = 100e-6;
  Bench b(o);
  b.run_for(20'000'000'000);
  ASSERT_GT(b.strobes.s.size(), 500u);
  double sq = 0;
  size_t n = 0;
  for (const auto& s : b.strobes.s) {
    if (s.t_host_ns < b.clock.now_ns() - 17'000'000'000) continue;
    const double e = static_cast<double>(s.t_host_ns - b.fake.strobe_truth()[s.seq]) * 1e-3;
    sq += e * e;
    ++n;
  }
  const double rms = std::sqrt(sq / static_cast<double>(n));
  std::printf("[ figure ] exposure strobe times through the bridge: RMS %.1f us\n", rms);
  EXPECT_LT(rms, 50.0);
}

TEST(UsbBridgeDriver, NoDeviceSaysSo) {
  LibusbEndpoint ep;
  const std::string err = ep.open(0x1209, 0xBEEF, 0x81);
  EXPECT_FALSE(err.empty());
  EXPECT_FALSE(ep.is_open());
  std::printf("open without hardware: %s\n", err.c_str());
}

}  // namespace
}  // namespace kestrel::drivers

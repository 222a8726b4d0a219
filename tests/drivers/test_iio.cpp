// Linux IIO IMU: the scan-type and layout parser on byte fixtures, the record
// framer on torn / gapped / reordered streams, sysfs configuration of a fake
// tree, and the driver against it (combined and separate accel/gyro devices,
// host-clock and device-clock stamps) with faults: wrong scale, a stalled
// stream, a torn record, an overflow, saturation, out-of-order stamps. Linked
// with the allocation hook: steady-state step() must not allocate.
#include <gtest/gtest.h>
#include <time.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "iio_bench.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/iio_device.hpp"
#include "kestrel/drivers/iio_scan.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/tools/config_file.hpp"
#include "vec_imu_sink.hpp"

namespace kestrel::test {
namespace {

using iio::ChannelKind;
using iio::ScanElement;
using iio::ScanLayout;
using iio::ScanType;

// ---- scan types -----------------------------------------------------------------------

TEST(IioScanType, ParsesTheKernelsStrings) {
  ScanType t;
  ASSERT_EQ(iio::parse_scan_type("le:s16/16>>0\n", t), nullptr);
  EXPECT_FALSE(t.big_endian);
  EXPECT_TRUE(t.is_signed);
  EXPECT_EQ(t.real_bits, 16);
  EXPECT_EQ(t.storage_bits, 16);
  EXPECT_EQ(t.shift, 0);
  EXPECT_EQ(t.repeat, 1);
  ASSERT_EQ(iio::parse_scan_type("be:u12/16>>4", t), nullptr);
  EXPECT_TRUE(t.big_endian);
  EXPECT_FALSE(t.is_signed);
  EXPECT_EQ(t.real_bits, 12);
  EXPECT_EQ(t.shift, 4);
  ASSERT_EQ(iio::parse_scan_type("le:s32/32X4>>0", t), nullptr);  // a quaternion
  EXPECT_EQ(t.repeat, 4);
  EXPECT_EQ(t.bytes(), 16u);
  ASSERT_EQ(iio::parse_scan_type("le:s64/64>>0", t), nullptr);
  EXPECT_EQ(t.bytes(), 8u);
  ASSERT_EQ(iio::parse_scan_type("be:s24/32>>8", t), nullptr);
}

TEST(IioScanType, RejectsMalformedStringsSayingWhy) {
  ScanType t;
  const char* bad[] = {"",
                       "le",
                       "xx:s16/16>>0",
                       "le:f16/16>>0",
                       "le:s17/16>>0",
                       "le:s16/16>>1",
                       "le:s16/12>>0",
                       "le:s16/16>0",
                       "le:s16/16>>0 x",
                       "le:s16/16X3>>0",
                       "le:s0/16>>0",
                       "le:s1234/16>>0",
                       "le:s16/>>0",
                       "le:s16/16X>>0",
                       "le:s16/16X0>>0"};
  for (const char* b : bad) {
    const char* err = iio::parse_scan_type(b, t);
    EXPECT_NE(err, nullptr) << b;
    if (err) {
      EXPECT_GT(std::strlen(err), 5u) << b;
    }
  }
}

TEST(IioScanType, ChannelNames) {
  EXPECT_EQ(iio::channel_kind("in_accel_x"), ChannelKind::kAccelX);
  EXPECT_EQ(iio::channel_kind("in_anglvel_z"), ChannelKind::kAnglvelZ);
  EXPECT_EQ(iio::channel_kind("in_timestamp"), ChannelKind::kTimestamp);
  EXPECT_EQ(iio::channel_kind("in_temp"), ChannelKind::kOther);
  EXPECT_EQ(iio::channel_kind("in_accel_x_raw"), ChannelKind::kOther);
  EXPECT_STREQ(iio::channel_name(ChannelKind::kAnglvelY), "in_anglvel_y");
}

// ---- layout ---------------------------------------------------------------------------

ScanElement el(ChannelKind k, int index, const char* type) {
  ScanElement e;
  e.kind = k;
  e.index = index;
  EXPECT_EQ(iio::parse_scan_type(type, e.type), nullptr) << type;
  return e;
}

TEST(IioScanLayout, EachElementAlignedToItsSizeAndTheTimestampTo8) {
  // Given out of index order, as a directory listing gives them.
  ScanLayout l;
  l.el[l.count++] = el(ChannelKind::kTimestamp, 6, "le:s64/64>>0");
  l.el[l.count++] = el(ChannelKind::kAnglvelZ, 5, "le:s16/16>>0");
  l.el[l.count++] = el(ChannelKind::kAccelX, 0, "le:s16/16>>0");
  l.el[l.count++] = el(ChannelKind::kAccelY, 1, "le:s16/16>>0");
  l.el[l.count++] = el(ChannelKind::kAccelZ, 2, "le:s16/16>>0");
  l.el[l.count++] = el(ChannelKind::kAnglvelX, 3, "le:s16/16>>0");
  l.el[l.count++] = el(ChannelKind::kAnglvelY, 4, "le:s16/16>>0");
  ASSERT_EQ(iio::compute_layout(l), nullptr);
  EXPECT_EQ(l.record_bytes, 24u);  // 12 bytes of data, padding to 16, the stamp
  EXPECT_EQ(l.el[static_cast<size_t>(l.timestamp)].offset_bytes, 16u);
  EXPECT_EQ(l.el[static_cast<size_t>(l.accel[0])].offset_bytes, 0u);
  EXPECT_EQ(l.el[static_cast<size_t>(l.gyro[2])].offset_bytes, 10u);
  EXPECT_TRUE(l.has_accel());
  EXPECT_TRUE(l.has_gyro());

  // Mixed sizes: u8, s32, s16, stamp -> 0, 4, 8, 16; record 24.
  ScanLayout m;
  m.el[m.count++] = el(ChannelKind::kOther, 0, "le:u8/8>>0");
  m.el[m.count++] = el(ChannelKind::kAccelX, 1, "le:s32/32>>0");
  m.el[m.count++] = el(ChannelKind::kOther, 2, "be:s16/16>>0");
  m.el[m.count++] = el(ChannelKind::kTimestamp, 3, "le:s64/64>>0");
  ASSERT_EQ(iio::compute_layout(m), nullptr);
  EXPECT_EQ(m.el[1].offset_bytes, 4u);
  EXPECT_EQ(m.el[2].offset_bytes, 8u);
  EXPECT_EQ(m.el[3].offset_bytes, 16u);
  EXPECT_EQ(m.record_bytes, 24u);
  EXPECT_FALSE(m.has_accel());

  // Without a stamp the record pads to its largest element: 3 x s16 = 6.
  ScanLayout n;
  n.el[n.count++] = el(ChannelKind::kAccelX, 0, "le:s16/16>>0");
  n.el[n.count++] = el(ChannelKind::kAccelY, 1, "le:s16/16>>0");
  n.el[n.count++] = el(ChannelKind::kAccelZ, 2, "le:s16/16>>0");
  ASSERT_EQ(iio::compute_layout(n), nullptr);
  EXPECT_EQ(n.record_bytes, 6u);
  EXPECT_EQ(n.timestamp, -1);
  // A quaternion (16 bytes) then the stamp: 16 + 8 -> 32.
  ScanLayout q;
  q.el[q.count++] = el(ChannelKind::kOther, 0, "le:s32/32X4>>0");
  q.el[q.count++] = el(ChannelKind::kTimestamp, 1, "le:s64/64>>0");
  ASSERT_EQ(iio::compute_layout(q), nullptr);
  EXPECT_EQ(q.record_bytes, 32u);
}

TEST(IioScanLayout, RejectsWhatCannotBeARecord) {
  ScanLayout dup;
  dup.el[dup.count++] = el(ChannelKind::kAccelX, 0, "le:s16/16>>0");
  dup.el[dup.count++] = el(ChannelKind::kAccelY, 0, "le:s16/16>>0");
  EXPECT_NE(iio::compute_layout(dup), nullptr);
  ScanLayout twice;
  twice.el[twice.count++] = el(ChannelKind::kAccelX, 0, "le:s16/16>>0");
  twice.el[twice.count++] = el(ChannelKind::kAccelX, 1, "le:s16/16>>0");
  EXPECT_NE(iio::compute_layout(twice), nullptr);
  ScanLayout ts32;
  ts32.el[ts32.count++] = el(ChannelKind::kTimestamp, 0, "le:s32/32>>0");
  EXPECT_NE(iio::compute_layout(ts32), nullptr);
  ScanLayout rep;
  rep.el[rep.count++] = el(ChannelKind::kAccelX, 0, "le:s16/16X2>>0");
  EXPECT_NE(iio::compute_layout(rep), nullptr);
}

// ---- values ---------------------------------------------------------------------------

TEST(IioScanValues, ByteFixtures) {
  const uint8_t le_m2[] = {0xFE, 0xFF};
  EXPECT_EQ(iio::extract_raw(le_m2, el(ChannelKind::kAccelX, 0, "le:s16/16>>0")), -2);
  EXPECT_EQ(iio::extract_raw(le_m2, el(ChannelKind::kAccelX, 0, "le:u16/16>>0")), 65534);
  // Left-justified 12-bit big endian (BMA-style): 0xABC0 >> 4.
  const uint8_t be12[] = {0xAB, 0xC0};
  EXPECT_EQ(iio::extract_raw(be12, el(ChannelKind::kAccelX, 0, "be:u12/16>>4")), 0xABC);
  EXPECT_EQ(iio::extract_raw(be12, el(ChannelKind::kAccelX, 0, "be:s12/16>>4")), 0xABC - 4096);
  const uint8_t ones[] = {0xFF, 0xF0};
  EXPECT_EQ(iio::extract_raw(ones, el(ChannelKind::kAccelX, 0, "be:s12/16>>4")), -1);
  // 24 significant bits in 32, shifted by 8: 0x80000100 >> 8 = 0x800001 -> -8388607.
  const uint8_t s24[] = {0x00, 0x01, 0x00, 0x80};
  EXPECT_EQ(iio::extract_raw(s24, el(ChannelKind::kAccelX, 0, "le:s24/32>>8")), -8388607);
  EXPECT_EQ(iio::extract_raw(s24, el(ChannelKind::kAccelX, 0, "be:s32/32>>0")), 0x00010080);
  const uint8_t ts[] = {0x08, 0x07, 0x06, 0x05, 0x04, 0x03, 0x02, 0x01};
  EXPECT_EQ(iio::extract_raw(ts, el(ChannelKind::kTimestamp, 0, "le:s64/64>>0")), 0x0102030405060708LL);
  EXPECT_EQ(iio::extract_raw(ts, el(ChannelKind::kTimestamp, 0, "be:s64/64>>0")), 0x0807060504030201LL);
  // Unsigned 64-bit beyond int64 saturates at raw_max, never wraps negative
  // (fuzz_iio_scan found the wrap: a value below raw_min).
  const uint8_t all[] = {0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF};
  const ScanElement u64 = el(ChannelKind::kOther, 0, "le:u64/64>>0");
  EXPECT_EQ(iio::extract_raw(all, u64), INT64_MAX);
  EXPECT_EQ(iio::extract_raw(all, u64), iio::raw_max(u64.type));
  const uint8_t top[] = {0, 0, 0, 0, 0, 0, 0, 0x80};
  EXPECT_EQ(iio::extract_raw(top, u64), INT64_MAX);
  const uint8_t below[] = {0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x7F};
  EXPECT_EQ(iio::extract_raw(below, u64), INT64_MAX);
  // Repeat: the k-th value.
  const uint8_t quat[] = {1, 0, 0, 0, 2, 0, 0, 0, 0xFD, 0xFF, 0xFF, 0xFF, 4, 0, 0, 0};
  const ScanElement q = el(ChannelKind::kOther, 0, "le:s32/32X4>>0");
  EXPECT_EQ(iio::extract_raw(quat, q, 2), -3);
  EXPECT_EQ(iio::extract_raw(quat, q, 3), 4);
  EXPECT_EQ(iio::raw_max(q.type), 2147483647);
  EXPECT_EQ(iio::raw_min(el(ChannelKind::kAccelX, 0, "be:s12/16>>4").type), -2048);
  EXPECT_EQ(iio::raw_max(el(ChannelKind::kAccelX, 0, "le:u12/16>>0").type), 4095);
  EXPECT_EQ(iio::raw_min(el(ChannelKind::kAccelX, 0, "le:u12/16>>0").type), 0);
}

TEST(IioScanValues, DecodeAppliesOffsetThenScaleAndFlagsSaturation) {
  ScanLayout l;
  const char* types[] = {"le:s16/16>>0", "be:s16/16>>0", "le:s12/16>>4"};
  for (int i = 0; i < 3; ++i) {
    l.el[l.count] = el(static_cast<ChannelKind>(static_cast<int>(ChannelKind::kAccelX) + i), i, types[i]);
    l.el[l.count].scale = 0.01;
    l.el[l.count].offset = -100;
    ++l.count;
  }
  for (int i = 0; i < 3; ++i) {
    l.el[l.count] =
        el(static_cast<ChannelKind>(static_cast<int>(ChannelKind::kAnglvelX) + i), 3 + i, "le:s16/16>>0");
    l.el[l.count].scale = 0.001;
    ++l.count;
  }
  l.el[l.count++] = el(ChannelKind::kTimestamp, 6, "le:s64/64>>0");
  ASSERT_EQ(iio::compute_layout(l), nullptr);
  ASSERT_EQ(l.record_bytes, 24u);
  const uint8_t rec[24] = {0xE8, 0x03,              // accel x 1000
                           0xFC, 0x18,              // accel y, big endian: -1000
                           0x00, 0x80,              // accel z s12>>4: 0x800 = -2048, the negative end
                           0xFF, 0x7F,              // gyro x 32767: saturated
                           0x01, 0x00, 0x00, 0x00,  // gyro y 1, z 0
                           0,    0,    0,    0,     // padding
                           0x00, 0xCA, 0x9A, 0x3B, 0, 0, 0, 0};  // 1e9 ns
  iio::DecodedRecord d;
  iio::decode_record(rec, l, d);
  EXPECT_EQ(d.t_dev_ns, 1'000'000'000);
  EXPECT_NEAR(d.acc_mps2[0], (1000 - 100) * 0.01, 1e-12);
  EXPECT_NEAR(d.acc_mps2[1], (-1000 - 100) * 0.01, 1e-12);  // 0xFC18 = -1000
  EXPECT_NEAR(d.acc_mps2[2], (-2048 - 100) * 0.01, 1e-12);
  EXPECT_TRUE(d.acc_saturated);
  EXPECT_NEAR(d.gyro_rps[0], 32.767, 1e-12);
  EXPECT_NEAR(d.gyro_rps[1], 0.001, 1e-15);
  EXPECT_TRUE(d.gyro_saturated);
  EXPECT_FALSE(d.non_finite);
}

// ---- framer ---------------------------------------------------------------------------

// Accel x/y/z s16 + stamp: 16-byte records, 5 ms apart.
struct FramerFixture {
  ScanLayout l;
  iio::RecordFramer f;
  static constexpr int64_t kPeriod = 5'000'000;
  FramerFixture() {
    l.el[l.count++] = el(ChannelKind::kAccelX, 0, "le:s16/16>>0");
    l.el[l.count++] = el(ChannelKind::kAccelY, 1, "le:s16/16>>0");
    l.el[l.count++] = el(ChannelKind::kAccelZ, 2, "le:s16/16>>0");
    l.el[l.count++] = el(ChannelKind::kTimestamp, 3, "le:s64/64>>0");
    EXPECT_EQ(iio::compute_layout(l), nullptr);
    iio::FramerOptions o;
    o.nominal_period_ns = kPeriod;
    f.configure(&l, o);
  }
  static void record(std::vector<uint8_t>& out, int64_t t, int16_t x) {
    uint8_t r[16] = {};
    std::memcpy(r, &x, 2);
    const int16_t y = static_cast<int16_t>(x * 3 + 7), z = static_cast<int16_t>(-x);
    std::memcpy(r + 2, &y, 2);
    std::memcpy(r + 4, &z, 2);
    std::memcpy(r + 8, &t, 8);
    out.insert(out.end(), r, r + 16);
  }
  // Feeds in uneven pieces, collecting every record's stamp and flags.
  std::vector<iio::RecordFramer::Record> run(const std::vector<uint8_t>& bytes, std::vector<int64_t>& ts,
                                             size_t piece = 7) {
    std::vector<iio::RecordFramer::Record> out;
    size_t at = 0, k = 0;
    while (at < bytes.size()) {
      const size_t n = std::min(bytes.size() - at, 1 + (piece * k++) % 37);
      EXPECT_EQ(f.feed(bytes.data() + at, n), n);
      at += n;
      iio::RecordFramer::Record r;
      while (f.next(r)) {
        out.push_back(r);
        ts.push_back(r.t_dev_ns);
        int16_t x = 0;
        std::memcpy(&x, r.bytes, 2);
        EXPECT_EQ(static_cast<int64_t>(x) * kPeriod + 1'000'000'000, r.t_dev_ns)
            << "payload and stamp disagree";
      }
    }
    return out;
  }
};

constexpr int64_t kT0 = 1'000'000'000;
int64_t stamp(int i) { return kT0 + i * FramerFixture::kPeriod; }

TEST(IioFramer, CleanStreamInUnevenPieces) {
  FramerFixture fx;
  std::vector<uint8_t> b;
  for (int i = 0; i < 200; ++i) FramerFixture::record(b, stamp(i), static_cast<int16_t>(i));
  std::vector<int64_t> ts;
  const auto out = fx.run(b, ts);
  ASSERT_EQ(out.size(), 200u);
  for (int i = 0; i < 200; ++i) EXPECT_EQ(ts[static_cast<size_t>(i)], stamp(i));
  const auto& c = fx.f.counters();
  EXPECT_EQ(c.records, 200u);
  EXPECT_EQ(c.torn_records + c.resyncs + c.bytes_skipped + c.gaps + c.out_of_order + c.discarded_records, 0u);
  for (const auto& r : out) EXPECT_EQ(r.flags, 0u);
}

TEST(IioFramer, TornRecordIsSkippedCountedAndAlignmentRegained) {
  for (int cut : {1, 5, 8, 13, 15}) {
    for (bool from_end : {true, false}) {
      FramerFixture fx;
      std::vector<uint8_t> b;
      for (int i = 0; i < 100; ++i) {
        std::vector<uint8_t> r;
        FramerFixture::record(r, stamp(i), static_cast<int16_t>(i));
        if (i == 40) r.erase(from_end ? r.end() - cut : r.begin(), from_end ? r.end() : r.begin() + cut);
        b.insert(b.end(), r.begin(), r.end());
      }
      std::vector<int64_t> ts;
      const auto out = fx.run(b, ts);
      SCOPED_TRACE(std::to_string(cut) + (from_end ? " from the end" : " from the start"));
      // Record 40 is lost, nothing else; the stamps tell the gap.
      ASSERT_EQ(out.size(), 99u);
      EXPECT_EQ(ts[39], stamp(39));
      EXPECT_EQ(ts[40], stamp(41));
      const auto& c = fx.f.counters();
      EXPECT_EQ(c.torn_records, 1u);
      EXPECT_EQ(c.resyncs, 1u);
      EXPECT_EQ(c.bytes_skipped, static_cast<uint64_t>(16 - cut));
      EXPECT_EQ(c.samples_lost, 1u);
      EXPECT_TRUE(out[40].flags & iio::kRecordResynced);
      EXPECT_TRUE(out[40].flags & iio::kRecordGapBefore);
      EXPECT_EQ(out[40].lost_before, 1u);
    }
  }
}

TEST(IioFramer, OverflowGapIsCountedWithoutResync) {
  FramerFixture fx;
  std::vector<uint8_t> b;
  for (int i = 0; i < 100; ++i)
    if (i < 30 || i >= 47) FramerFixture::record(b, stamp(i), static_cast<int16_t>(i));
  std::vector<int64_t> ts;
  const auto out = fx.run(b, ts);
  ASSERT_EQ(out.size(), 83u);
  const auto& c = fx.f.counters();
  EXPECT_EQ(c.gaps, 1u);
  EXPECT_EQ(c.samples_lost, 17u);
  EXPECT_EQ(c.resyncs, 0u);
  EXPECT_EQ(out[30].lost_before, 17u);
  EXPECT_EQ(out[30].flags, static_cast<uint32_t>(iio::kRecordGapBefore));
}

TEST(IioFramer, AStallLongerThanTheGapLimitIsConfirmedThenBelieved) {
  FramerFixture fx;
  std::vector<uint8_t> b;
  for (int i = 0; i < 50; ++i) FramerFixture::record(b, stamp(i), static_cast<int16_t>(i));
  for (int i = 1050; i < 1100; ++i) FramerFixture::record(b, stamp(i), static_cast<int16_t>(i));  // 5 s later
  std::vector<int64_t> ts;
  const auto out = fx.run(b, ts);
  ASSERT_EQ(out.size(), 100u);
  EXPECT_EQ(fx.f.counters().samples_lost, 1000u);
  EXPECT_EQ(fx.f.counters().torn_records, 0u);
  EXPECT_EQ(fx.f.counters().discarded_records, 0u);
}

TEST(IioFramer, DuplicateAndOlderStampsAreDroppedAndCounted) {
  FramerFixture fx;
  std::vector<uint8_t> b;
  for (int i = 0; i < 60; ++i) {
    FramerFixture::record(b, stamp(i), static_cast<int16_t>(i));
    if (i == 20) FramerFixture::record(b, stamp(20), 20);  // duplicate
    if (i == 30) FramerFixture::record(b, stamp(25), 25);  // behind
  }
  std::vector<int64_t> ts;
  const auto out = fx.run(b, ts);
  ASSERT_EQ(out.size(), 60u);
  for (size_t i = 1; i < ts.size(); ++i) EXPECT_GT(ts[i], ts[i - 1]);
  EXPECT_EQ(fx.f.counters().out_of_order, 2u);
  EXPECT_EQ(fx.f.counters().samples_lost, 0u);
}

TEST(IioFramer, AClockThatRestartsIsFollowed) {
  for (int64_t back_ns : {int64_t{500'000'000}, int64_t{100'000'000'000}}) {
    FramerFixture fx;
    std::vector<uint8_t> b;
    for (int i = 0; i < 300; ++i) FramerFixture::record(b, stamp(i), static_cast<int16_t>(i));
    const int k0 = 300 - static_cast<int>(back_ns / FramerFixture::kPeriod);
    for (int i = k0; i < k0 + 100; ++i) FramerFixture::record(b, stamp(i), static_cast<int16_t>(i));
    std::vector<int64_t> ts;
    const auto out = fx.run(b, ts);
    SCOPED_TRACE(back_ns);
    EXPECT_EQ(fx.f.counters().clock_resets, 1u);
    // Within the gap limit the first few are taken for reordered records first.
    EXPECT_GE(out.size(), 400u - 4u);
    EXPECT_EQ(ts.back(), stamp(k0 + 99));
    bool reset_seen = false;
    for (const auto& r : out) reset_seen = reset_seen || (r.flags & iio::kRecordClockReset);
    EXPECT_TRUE(reset_seen);
  }
}

TEST(IioFramer, GarbageIsDiscardedUntilStampsLineUp) {
  FramerFixture fx;
  std::vector<uint8_t> b;
  std::mt19937 rng(3);
  for (int i = 0; i < 101; ++i) b.push_back(static_cast<uint8_t>(rng()));
  for (int i = 0; i < 50; ++i) FramerFixture::record(b, stamp(i), static_cast<int16_t>(i));
  std::vector<int64_t> ts;
  const auto out = fx.run(b, ts);
  EXPECT_EQ(out.size(), 50u);
  EXPECT_EQ(fx.f.counters().bytes_skipped, 101u);
  EXPECT_EQ(ts.front(), stamp(0));
}

// ---- sysfs helpers ----------------------------------------------------------------------

TEST(IioSysfs, ChoosesTheSlowestRateAtOrAboveTheRequest) {
  iio::AvailableRates a;
  ASSERT_EQ(iio::parse_available_rates("400 25 50 100 200\n", a), nullptr);
  EXPECT_EQ(iio::choose_rate(a, 150), 200);
  EXPECT_EQ(iio::choose_rate(a, 200), 200);
  EXPECT_EQ(iio::choose_rate(a, 1000), 400);
  EXPECT_EQ(iio::choose_rate(a, 10), 25);
  EXPECT_EQ(iio::choose_rate(a, 0), 0);
  ASSERT_EQ(iio::parse_available_rates("[12.5 12.5 800]", a), nullptr);
  EXPECT_TRUE(a.is_range);
  EXPECT_DOUBLE_EQ(iio::choose_rate(a, 100), 100);
  EXPECT_DOUBLE_EQ(iio::choose_rate(a, 30), 37.5);
  EXPECT_DOUBLE_EQ(iio::choose_rate(a, 5000), 800);
  for (const char* bad : {"", "fast", "100 x", "[1 2]", "[5 1 2]", "-5 10", "nan"})
    EXPECT_NE(iio::parse_available_rates(bad, a), nullptr) << bad;
  double v = 0;
  EXPECT_TRUE(iio::parse_number("0.000598550\n", v));
  EXPECT_DOUBLE_EQ(v, 0.00059855);
  EXPECT_TRUE(iio::parse_number("-1e-3", v));
  for (const char* bad : {"", "nan", "inf", "0x10", "1.5 2", "abc"})
    EXPECT_FALSE(iio::parse_number(bad, v)) << bad;
}

// ---- the driver against the fake tree ----------------------------------------------------

using VecImuSink = kestrel::test::VecImuSink;

TEST(IioDevice, ConfiguresTheTreeAsTheKernelExpects) {
  IioBench b("configure", {combined_imu_spec("100")});
  b.cfg.device = "icm42688";
  b.cfg.rate_hz = 300;  // not offered: the next one up
  ASSERT_EQ(b.open(), "");
  const auto& t = *b.tree;
  EXPECT_EQ(t.read(0, "buffer/enable"), "1");
  EXPECT_EQ(t.read(0, "buffer/length"), "512");
  EXPECT_EQ(t.read(0, "buffer/watermark"), "1");
  EXPECT_EQ(t.read(0, "current_timestamp_clock"), "monotonic");
  EXPECT_EQ(t.read(0, "sampling_frequency"), "400");
  EXPECT_EQ(t.read(0, "scan_elements/in_temp_en"), "0");
  EXPECT_EQ(t.read(0, "scan_elements/in_accel_x_en"), "1");
  EXPECT_EQ(t.read(0, "scan_elements/in_anglvel_z_en"), "1");
  EXPECT_EQ(t.read(0, "scan_elements/in_timestamp_en"), "1");
  const iio::Device& d = b.drv->device(0);
  EXPECT_EQ(d.layout().record_bytes, 24u);
  EXPECT_DOUBLE_EQ(d.rate_hz(), 400);
  EXPECT_NEAR(d.layout().el[static_cast<size_t>(d.layout().accel[1])].scale, 0.004788403, 1e-15);
  EXPECT_NEAR(d.layout().el[static_cast<size_t>(d.layout().gyro[2])].scale, 0.001065264, 1e-15);
  EXPECT_NE(b.drv->description().find("icm42688"), std::string::npos);
  b.drv->close();
  EXPECT_EQ(t.read(0, "buffer/enable"), "0");
}

TEST(IioDevice, DeviceNotFoundListsWhatIsThere) {
  IioBench b("notfound", {d4xx_accel_spec(), d4xx_gyro_spec()});
  b.cfg.device = "bmi088";
  const std::string e = b.open();
  EXPECT_NE(e.find("no IIO device named \"bmi088\""), std::string::npos) << e;
  EXPECT_NE(e.find("accel_3d (iio:device0)"), std::string::npos) << e;
  EXPECT_NE(e.find("gyro_3d (iio:device1)"), std::string::npos) << e;
  iio::ImuConfig c = b.cfg;
  c.sysfs_root = b.tree->sysfs_root() + "/nothing";
  iio::ImuDriver d(b.clock, c);
  EXPECT_NE(d.open().find("cannot list IIO devices"), std::string::npos);
}

// Wrong or absent scales are refused at open with the file in the message.
TEST(IioDevice, WrongScaleIsAClearErrorNamingTheFile) {
  struct Case {
    const char* what;
    void (*edit)(iio::FakeDeviceSpec&);
    const char* file;
    const char* says;
  };
  const Case cases[] = {
      {"absent", [](iio::FakeDeviceSpec& s) { s.accel_scale = ""; }, "/in_accel_scale", "missing"},
      {"not a number", [](iio::FakeDeviceSpec& s) { s.gyro_scale = "fast"; }, "/in_anglvel_scale",
       "not a positive"},
      {"zero", [](iio::FakeDeviceSpec& s) { s.accel_scale = "0"; }, "/in_accel_scale", "not a positive"},
      {"nan", [](iio::FakeDeviceSpec& s) { s.accel_scale = "nan"; }, "/in_accel_scale", "not a positive"},
      {"g per count", [](iio::FakeDeviceSpec& s) { s.accel_scale = "0.000488"; }, "/in_accel_scale",
       "in g rather"},
      {"mg per count", [](iio::FakeDeviceSpec& s) { s.accel_scale = "0.488"; }, "/in_accel_scale", "in mg"},
      {"degrees", [](iio::FakeDeviceSpec& s) { s.gyro_scale = "0.061"; }, "/in_anglvel_scale", "degrees"},
      {"offset", [](iio::FakeDeviceSpec& s) { s.accel_offset = "x"; }, "/in_accel_offset", "not a number"},
      {"type", [](iio::FakeDeviceSpec& s) { s.gyro_type = "le:s16/8>>0"; }, "/in_anglvel_x_type",
       "real bits"},
      {"no stamp", [](iio::FakeDeviceSpec& s) { s.timestamp_type = "le:s32/32>>0"; }, "scan_elements", "64"},
      {"no buffer", [](iio::FakeDeviceSpec& s) { s.has_buffer = false; }, "/buffer/enable", "no buffered"},
      {"rates", [](iio::FakeDeviceSpec& s) { s.available_hz = "1 2 lots"; }, "sampling_frequency_available",
       "not a"},
  };
  int k = 0;
  for (const Case& c : cases) {
    iio::FakeDeviceSpec s = combined_imu_spec();
    c.edit(s);
    IioBench b(std::string("badscale") + std::to_string(k++), {s});
    b.cfg.device = "icm42688";
    const std::string e = b.open();
    EXPECT_NE(e.find(c.file), std::string::npos) << c.what << ": " << e;
    EXPECT_NE(e.find(c.says), std::string::npos) << c.what << ": " << e;
    EXPECT_NE(e.find(b.tree->sysfs_root()), std::string::npos) << c.what << ": " << e;
    std::printf("[ message ] %s: %s\n", c.what, e.c_str());
  }
}

TEST(IioDevice, NoTimestampClockFileMeansRealtimeStampsMappedByClockSync) {
  iio::FakeDeviceSpec s = combined_imu_spec();
  s.timestamp_clock_file = false;
  IioBench b("noclockfile", {s});
  b.cfg.device = "icm42688";
  ASSERT_EQ(b.open(), "");
  EXPECT_EQ(b.drv->device(0).timestamp_clock(), "realtime");
  EXPECT_FALSE(b.drv->stamps_on_host_clock());
  ASSERT_FALSE(b.drv->device(0).notes().empty());
  EXPECT_NE(b.drv->device(0).notes()[0].find("current_timestamp_clock: missing"), std::string::npos);
}

// Host-clock stamps (current_timestamp_clock = monotonic): samples come out
// at exactly their stamps, values within half a count of the input.
TEST(IioImuDriver, CombinedDeviceDeliversEverySampleWithinQuantisation) {
  IioBench b("combined", {combined_imu_spec()});
  b.cfg.device = "icm42688";
  ASSERT_EQ(b.open(), "");
  VecImuSink sink;
  const int64_t t0 = b.clock.now_ns();
  std::vector<Vec3d> acc, gyro;
  const int n = 2000;  // 10 s at 200 Hz
  for (int i = 0; i < n; ++i) {
    const double t = i * 0.005;
    acc.push_back({0.3 * std::sin(t), -0.2 * std::cos(2 * t), 9.80665 + 0.1 * std::sin(5 * t)});
    gyro.push_back({0.5 * std::sin(3 * t), 0.01 * i / n, -1.2 * std::cos(t)});
    const int64_t ts = t0 + int64_t{5'000'000} * (i + 1);
    b.put(0, ts, acc.back(), gyro.back());
    b.step_at(ts + 300'000, sink);
  }
  ASSERT_EQ(b.drv->state(), iio::ImuState::kStreaming);
  EXPECT_TRUE(b.drv->stamps_on_host_clock());
  // The framer holds back the first records until their stamps confirm alignment.
  ASSERT_GE(sink.samples.size(), static_cast<size_t>(n - 4));
  const size_t skip = static_cast<size_t>(n) - sink.samples.size();
  const double qa = 0.004788403 / 2 + 1e-12, qg = 0.001065264 / 2 + 1e-12;
  for (size_t k = 0; k < sink.samples.size(); ++k) {
    const ImuSample& s = sink.samples[k];
    const size_t i = k + skip;
    ASSERT_EQ(s.t_ns, t0 + int64_t{5'000'000} * static_cast<int64_t>(i + 1)) << k;
    EXPECT_EQ(s.seq, k);
    EXPECT_EQ(s.flags, 0u);
    for (size_t a = 0; a < 3; ++a) {
      ASSERT_NEAR(s.acc_mps2[a], acc[i][a], qa) << k;
      ASSERT_NEAR(s.gyro_rps[a], gyro[i][a], qg) << k;
    }
  }
  const auto& c = b.drv->counters();
  EXPECT_EQ(c.stalls + c.secondary_held + c.time_clamped + c.clock_jumps + c.not_host_clock, 0u);
  EXPECT_EQ(b.drv->framer_totals().samples_lost, 0u);
  std::printf("[ figure ] %s\n", b.drv->report().c_str());
}

TEST(IioImuDriver, AxisRemapAndPerAxisScalesAndOffsets) {
  iio::FakeDeviceSpec s = combined_imu_spec();
  s.per_axis_scale = true;
  s.accel_offset = "-12";
  s.accel_type = "be:s12/16>>4";
  s.accel_scale = "0.0191536";  // +-4 g at 12 bits... as m/s^2 per count
  IioBench b("remap", {s});
  b.cfg.device = "icm42688";
  b.cfg.axis_remap = {2, -1, 3};  // body x = sensor y, body y = -sensor x
  ASSERT_EQ(b.open(), "");
  VecImuSink sink;
  const int64_t t0 = b.clock.now_ns();
  for (int i = 1; i <= 20; ++i) {
    b.put(0, t0 + int64_t{5'000'000} * i, {1.0, 2.0, 9.8}, {0.1, -0.2, 0.3});
    b.step_at(t0 + int64_t{5'000'000} * i + 100'000, sink);
  }
  ASSERT_FALSE(sink.samples.empty());
  const ImuSample& o = sink.samples.back();
  EXPECT_NEAR(o.acc_mps2[0], 2.0, 0.0096);
  EXPECT_NEAR(o.acc_mps2[1], -1.0, 0.0096);
  EXPECT_NEAR(o.acc_mps2[2], 9.8, 0.0096);
  EXPECT_NEAR(o.gyro_rps[0], -0.2, 0.00054);
  EXPECT_NEAR(o.gyro_rps[1], -0.1, 0.00054);
}

// The RealSense case: gyro 200 Hz and accel at another rate as two devices,
// stamps from the device's own clock (offset and drift) although the clock
// file says monotonic. Output at gyro stamps, accel interpolated, times on
// the host clock within tens of microseconds.
TEST(IioImuDriver, SeparateDevicesMergedOnTheGyroStampsAndMappedToHostTime) {
  IioBench b("d4xx", {d4xx_accel_spec(), d4xx_gyro_spec()});
  b.cfg.accel_device = "accel_3d";
  b.cfg.gyro_device = "gyro_3d";
  b.cfg.accel_rate_hz = 100;
  b.cfg.gyro_rate_hz = 200;
  b.cfg.clock.latency_floor_ns = 200'000;
  ASSERT_EQ(b.open(), "");
  EXPECT_EQ(b.tree->read(0, "in_accel_sampling_frequency"), "100");
  EXPECT_EQ(b.tree->read(1, "in_anglvel_sampling_frequency"), "200");
  EXPECT_EQ(b.drv->device(0).name(), "gyro_3d");

  const int64_t h0 = b.clock.now_ns();
  const double skew = 60e-6;
  const int64_t d0 = 7'777'000'000'000;  // the device clock at h0
  auto dev = [&](int64_t h) { return d0 + static_cast<int64_t>(std::llround((h - h0) * (1.0 - skew))); };
  auto acc_at = [](double t) {
    return Vec3d{0.5 * t, -1.0 + 0.2 * t, 9.8};
  };  // a ramp: interpolation is exact
  auto gyro_at = [](double t) { return Vec3d{0.2, std::sin(t), -0.1 * t}; };
  std::mt19937 rng(11);
  std::exponential_distribution<double> jitter(1.0 / 150e3);
  VecImuSink sink;
  std::vector<int64_t> truth;        // host time of each gyro sample
  for (int i = 1; i <= 4000; ++i) {  // 20 s
    const int64_t h = h0 + int64_t{5'000'000} * static_cast<int64_t>(i);
    const double t = (h - h0) * 1e-9;
    if (i % 2 == 0) b.put(0, dev(h), acc_at(t), {});
    b.put(1, dev(h), {}, gyro_at(t));
    truth.push_back(h);
    b.step_at(h + 200'000 + static_cast<int64_t>(jitter(rng)), sink);
  }
  ASSERT_GT(sink.samples.size(), 3990u);
  EXPECT_FALSE(b.drv->stamps_on_host_clock());
  EXPECT_EQ(b.drv->counters().not_host_clock, 1u);
  double sq = 0, worst = 0, acc_err = 0, gyro_err = 0;
  size_t n = 0;
  for (const ImuSample& s : sink.samples) {
    // The nearest true gyro time.
    const int64_t k = (s.t_ns - h0 + 2'500'000) / 5'000'000;
    const int64_t h = h0 + int64_t{5'000'000} * k;
    const double t = (h - h0) * 1e-9;
    if (t < 10.0) continue;  // clock sync settled
    const double e_us = (s.t_ns - h) * 1e-3;
    sq += e_us * e_us;
    worst = std::max(worst, std::abs(e_us));
    for (size_t a = 0; a < 3; ++a) {
      acc_err = std::max(acc_err, std::abs(s.acc_mps2[a] - acc_at(t)[a]));
      gyro_err = std::max(gyro_err, std::abs(s.gyro_rps[a] - gyro_at(t)[a]));
    }
    ++n;
  }
  const double rms = std::sqrt(sq / static_cast<double>(n));
  std::printf(
      "[ figure ] D4xx-style pair, 60 ppm drift, jitter mean 150 us: time RMS %.1f us, max %.1f us; "
      "accel max err %.4f m/s^2, gyro %.5f rad/s; skew %.1f ppm\n",
      rms, worst, acc_err, gyro_err, b.drv->clock_sync().skew() * 1e6);
  std::printf("[ figure ] %s\n", b.drv->report().c_str());
  EXPECT_LT(rms, 30.0);
  EXPECT_LT(worst, 200.0);
  EXPECT_LT(acc_err, 0.00980665 / 2 + 1e-6);  // half a count: the ramp interpolates exactly
  EXPECT_LT(gyro_err, 0.000175 / 2 + 1e-6);
  EXPECT_NEAR(b.drv->clock_sync().skew(), skew, 5e-6);
  for (size_t i = 1; i < sink.samples.size(); ++i) ASSERT_GT(sink.samples[i].t_ns, sink.samples[i - 1].t_ns);
  EXPECT_EQ(b.drv->counters().secondary_held, 0u);
  EXPECT_LE(b.drv->counters().secondary_missing, 2u);  // the first gyro sample may precede any accel
}

TEST(IioImuDriver, StalledStreamIsDetectedReportedAndSurvived) {
  IioBench b("stall", {combined_imu_spec()});
  b.cfg.device = "icm42688";
  b.cfg.stall_timeout_ns = 100'000'000;
  ASSERT_EQ(b.open(), "");
  VecImuSink sink;
  const int64_t t0 = b.clock.now_ns();
  int64_t ts = t0;
  for (int i = 0; i < 100; ++i) {
    ts += 5'000'000;
    b.put(0, ts, {0, 0, 9.8}, {});
    b.step_at(ts + 100'000, sink);
  }
  const size_t before = sink.samples.size();
  // 300 ms of silence: the host clock moves on, nothing to read.
  for (int k = 1; k <= 30; ++k) b.step_at(ts + 100'000 + k * 10'000'000, sink);
  EXPECT_EQ(b.drv->state(), iio::ImuState::kStalled);
  EXPECT_EQ(b.drv->counters().stalls, 1u);
  bool said = false;
  for (const auto& e : sink.events)
    said = said || e.find("no data within stall_timeout_ms") != std::string::npos;
  EXPECT_TRUE(said);
  // Resumes: the stamps show the 60 samples the device did not deliver.
  ts += 305'000'000;
  for (int i = 0; i < 50; ++i) {
    ts += 5'000'000;
    b.put(0, ts, {0, 0, 9.8}, {});
    b.step_at(ts + 100'000, sink);
  }
  EXPECT_EQ(b.drv->state(), iio::ImuState::kStreaming);
  ASSERT_EQ(sink.samples.size(), before + 50);
  const ImuSample& first = sink.samples[before];
  EXPECT_TRUE(first.flags & kImuGapBefore);
  EXPECT_EQ(first.seq, sink.samples[before - 1].seq + 62);
  EXPECT_EQ(b.drv->framer_totals().samples_lost, 61u);
}

TEST(IioImuDriver, TornRecordIsResynchronisedAndCounted) {
  IioBench b("torn", {combined_imu_spec()});
  b.cfg.device = "icm42688";
  ASSERT_EQ(b.open(), "");
  VecImuSink sink;
  const int64_t t0 = b.clock.now_ns();
  for (int i = 1; i <= 200; ++i) {
    const int64_t ts = t0 + int64_t{5'000'000} * i;
    uint8_t r[64];
    const size_t n = b.tree->encode(0, ts, {0.1 * i, 0, 9.8}, {0, 0, 0.01 * i}, r, sizeof r);
    ASSERT_EQ(n, 24u);
    if (i == 100)
      b.put_bytes(0, r, 11);  // the rest of this record never arrives
    else
      b.put_bytes(0, r, n);
    b.step_at(ts + 100'000, sink);
  }
  const auto f = b.drv->framer_totals();
  EXPECT_EQ(f.torn_records, 1u);
  EXPECT_EQ(f.resyncs, 1u);
  EXPECT_EQ(f.bytes_skipped, 11u);
  EXPECT_EQ(f.samples_lost, 1u);
  EXPECT_GE(sink.samples.size(), 195u);
  for (size_t i = 1; i < sink.samples.size(); ++i) ASSERT_GT(sink.samples[i].t_ns, sink.samples[i - 1].t_ns);
  // Every delivered value belongs to its stamp: no sample built from two records.
  for (const ImuSample& s : sink.samples) {
    const double i = static_cast<double>(s.t_ns - t0) / 5e6;
    EXPECT_NEAR(s.gyro_rps[2], 0.01 * i, 0.0006);
    EXPECT_NEAR(s.acc_mps2[0], 0.1 * i, 0.0025);
  }
}

TEST(IioImuDriver, OverflowGapIsCountedAndFlagged) {
  IioBench b("overflow", {combined_imu_spec()});
  b.cfg.device = "icm42688";
  ASSERT_EQ(b.open(), "");
  VecImuSink sink;
  const int64_t t0 = b.clock.now_ns();
  // The reader was late: the kernel buffer filled and 37 scans were lost in it.
  for (int i = 1; i <= 300; ++i) {
    if (i > 100 && i <= 137) continue;
    b.put(0, t0 + int64_t{5'000'000} * i, {0, 0, 9.8}, {});
    if (i % 10 == 0) b.step_at(t0 + int64_t{5'000'000} * i + 100'000, sink);
  }
  EXPECT_EQ(b.drv->framer_totals().gaps, 1u);
  EXPECT_EQ(b.drv->framer_totals().samples_lost, 37u);
  int flagged = 0;
  for (const auto& s : sink.samples) flagged += (s.flags & kImuGapBefore) ? 1 : 0;
  EXPECT_EQ(flagged, 1);
  EXPECT_EQ(sink.samples.back().seq - sink.samples.front().seq + 1, sink.samples.size() + 37);
}

TEST(IioImuDriver, SaturationAndOutOfOrderStampsAreCounted) {
  IioBench b("sat", {combined_imu_spec()});
  b.cfg.device = "icm42688";
  ASSERT_EQ(b.open(), "");
  VecImuSink sink;
  const int64_t t0 = b.clock.now_ns();
  for (int i = 1; i <= 100; ++i) {
    const int64_t ts = t0 + int64_t{5'000'000} * i;
    const double ax = i == 50 ? 400.0 : 0.0;   // beyond +-16 g: clamped by the sensor
    const double gz = i == 60 ? -100.0 : 0.0;  // beyond +-2000 dps
    b.put(0, ts, {ax, 0, 9.8}, {0, 0, gz});
    if (i == 70) b.put(0, ts - 10'000'000, {0, 0, 9.8}, {});  // late duplicate of an older scan
    b.step_at(ts + 100'000, sink);
  }
  const auto& c = b.drv->counters();
  EXPECT_EQ(c.acc_saturated, 1u);
  EXPECT_EQ(c.gyro_saturated, 1u);
  EXPECT_EQ(b.drv->framer_totals().out_of_order, 1u);
  int sat = 0;
  for (const auto& s : sink.samples)
    sat += ((s.flags & kImuAccSaturated) ? 1 : 0) + ((s.flags & kImuGyroSaturated) ? 1 : 0);
  EXPECT_EQ(sat, 2);
  for (size_t i = 1; i < sink.samples.size(); ++i) ASSERT_GT(sink.samples[i].t_ns, sink.samples[i - 1].t_ns);
}

// The accelerometer stops while the gyroscope goes on: after stall_timeout
// the gyro samples go out with the last accel value held, counted.
TEST(IioImuDriver, SlowerStreamStallHoldsItsLastValueAndSaysSo) {
  iio::FakeDeviceSpec a = d4xx_accel_spec(), g = d4xx_gyro_spec();
  a.timestamp_clock = g.timestamp_clock = "monotonic";
  IioBench b("secstall", {a, g});
  b.cfg.accel_device = "accel_3d";
  b.cfg.gyro_device = "gyro_3d";
  b.cfg.stall_timeout_ns = 50'000'000;
  ASSERT_EQ(b.open(), "");
  VecImuSink sink;
  const int64_t t0 = b.clock.now_ns();
  for (int i = 1; i <= 400; ++i) {
    const int64_t ts = t0 + int64_t{5'000'000} * i;
    if (i % 2 == 0 && i < 200) b.put(0, ts, {0, 0, 9.8}, {});
    b.put(1, ts, {}, {0, 0, 0.1});
    b.step_at(ts + 100'000, sink);
  }
  EXPECT_TRUE(b.drv->stamps_on_host_clock());
  EXPECT_EQ(b.drv->state(), iio::ImuState::kStalled);
  EXPECT_GE(b.drv->counters().stalls, 1u);
  EXPECT_GT(b.drv->counters().secondary_held, 150u);
  EXPECT_GT(sink.samples.size(), 390u);
  EXPECT_NEAR(sink.samples.back().acc_mps2[2], 9.8, 0.01);
  bool said = false;
  for (const auto& e : sink.events) said = said || e.find("slower stream") != std::string::npos;
  EXPECT_TRUE(said);
}

// A sink that stores into a preallocated array: the measurement must not
// count its own allocations.
struct ArraySink final : drivers::ImuSink {
  std::vector<ImuSample> s = std::vector<ImuSample>(20000);
  size_t n = 0;
  bool push(const ImuSample& x) noexcept override {
    if (n >= s.size()) return false;
    s[n++] = x;
    return true;
  }
};

TEST(IioImuDriver, SteadyStateAllocatesNothing) {
  ASSERT_TRUE(rt::alloc_hook_linked());
  IioBench b("alloc", {d4xx_accel_spec(), d4xx_gyro_spec()});
  b.cfg.accel_device = "accel_3d";
  b.cfg.gyro_device = "gyro_3d";
  ASSERT_EQ(b.open(), "");
  ArraySink sink;
  const int64_t t0 = b.clock.now_ns();
  uint64_t allocs = 0, steps = 0;
  double cpu_ns = 0;
  size_t samples_measured = 0;
  for (int i = 1; i <= 6000; ++i) {  // 30 s at 200 Hz
    const int64_t ts = t0 + int64_t{5'000'000} * i;
    // Encoding and writing is the fake device's work, outside the measurement.
    if (i % 2 == 0) b.put(0, ts, {0.1, 0.2, 9.8}, {});
    b.put(1, ts, {}, {0.01, 0.02, 0.03});
    if (i == 3000) {  // a torn record and a gap in steady state too
      uint8_t r[64];
      const size_t n = b.tree->encode(1, ts + 2'500'000, {}, {0, 0, 0}, r, sizeof r);
      b.put_bytes(1, r, n - 3);
    }
    b.clock.set(ts + 150'000);
    const size_t n0 = sink.n;
    timespec c0{}, c1{};
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &c0);
    rt::AllocCountScope scope;
    b.drv->step(sink);
    const uint64_t a = scope.count();
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &c1);
    if (i > 200) {  // after the first second
      allocs += a;
      ++steps;
      cpu_ns += (c1.tv_sec - c0.tv_sec) * 1e9 + (c1.tv_nsec - c0.tv_nsec);
      samples_measured += sink.n - n0;
    }
  }
  std::printf(
      "[ figure ] iio driver steady state: %llu allocations in %llu steps; %.2f us CPU per step, "
      "%.2f us per sample (poll + 2 reads + parse + merge + push, %zu samples)\n",
      (unsigned long long)allocs, (unsigned long long)steps, cpu_ns / steps * 1e-3,
      cpu_ns / static_cast<double>(samples_measured) * 1e-3, samples_measured);
  EXPECT_EQ(allocs, 0u);
  EXPECT_GT(samples_measured, 5500u);
  EXPECT_EQ(b.drv->framer_totals().torn_records, 1u);
}

TEST(IioImuConfig, ValidateNamesTheField) {
  iio::ImuConfig c;
  auto says = [&](const char* what) {
    try {
      c.validate();
    } catch (const std::invalid_argument& e) {
      return std::string(e.what()).find(what) != std::string::npos;
    }
    return false;
  };
  EXPECT_TRUE(says("device: missing"));
  c.device = "x";
  c.accel_device = "y";
  EXPECT_TRUE(says("excludes"));
  c.accel_device.clear();
  c.timestamp_clock = "gps";
  EXPECT_TRUE(says("timestamp_clock"));
  c.timestamp_clock = "boottime";
  c.watermark_samples = 0;
  EXPECT_TRUE(says("watermark_samples"));
  c.watermark_samples = 1;
  c.axis_remap = {1, 1, 3};
  EXPECT_TRUE(says("axis_remap"));
  c.axis_remap = {1, 2, 3};
  EXPECT_NO_THROW(c.validate());
}

// ---- the live config and the sensor thread ----------------------------------------------

std::string live_yaml(const std::string& imu) {
  return "rig:\n  camera: {width_px: 640, height_px: 480, fx_px: 500, fy_px: 500, cx_px: 320, cy_px: 240}\n"
         "drivers:\n  imu:\n" +
         imu;
}

TEST(IioLiveConfig, TheIioSectionWithUnitsInItsKeys) {
  const drivers::LiveConfig c = kestrel::tools::live_config_from_yaml(
      live_yaml("    type: iio\n    axis_remap: [+y, -x, +z]\n    iio:\n      accel_device: accel_3d\n"
                "      gyro_device: gyro_3d\n      sysfs_root: fake/sys\n      dev_root: /tmp/dev\n"
                "      accel_rate_hz: 200\n      gyro_rate_hz: 400\n      timestamp_clock: boottime\n"
                "      buffer_length_samples: 1024\n      watermark_samples: 2\n      read_timeout_ms: 50\n"
                "      stall_timeout_ms: 300\n      max_stamp_gap_ms: 2000\n      latency_floor_us: 90\n"),
      "/cfg/live.yaml");
  const iio::ImuConfig& i = c.drivers.imu.iio;
  EXPECT_EQ(c.drivers.imu.type, drivers::ImuType::kIio);
  EXPECT_EQ(i.accel_device, "accel_3d");
  EXPECT_EQ(i.gyro_device, "gyro_3d");
  EXPECT_EQ(i.sysfs_root, "/cfg/fake/sys");  // relative to the config
  EXPECT_EQ(i.dev_root, "/tmp/dev");
  EXPECT_EQ(i.accel_rate_hz, 200);
  EXPECT_EQ(i.gyro_rate_hz, 400);
  EXPECT_EQ(i.timestamp_clock, "boottime");
  EXPECT_EQ(i.buffer_length_samples, 1024);
  EXPECT_EQ(i.watermark_samples, 2);
  EXPECT_EQ(i.read_timeout_ms, 50);
  EXPECT_EQ(i.stall_timeout_ns, 300'000'000);
  EXPECT_EQ(i.max_stamp_gap_ns, 2'000'000'000);
  EXPECT_EQ(i.clock.latency_floor_ns, 90'000);
  EXPECT_EQ(i.axis_remap, (std::array<int8_t, 3>{2, -1, 3}));
  // Defaults: the kernel's paths, monotonic stamps.
  const drivers::LiveConfig d = kestrel::tools::live_config_from_yaml(
      live_yaml("    type: iio\n    iio: {device: bmi088}\n"), "x.yaml");
  EXPECT_EQ(d.drivers.imu.iio.sysfs_root, "/sys/bus/iio/devices");
  EXPECT_EQ(d.drivers.imu.iio.dev_root, "/dev");
  EXPECT_EQ(d.drivers.imu.iio.timestamp_clock, "monotonic");
  EXPECT_EQ(d.drivers.imu.iio.rate_hz, 200);
}

TEST(IioLiveConfig, ErrorsNameFileAndKey) {
  auto error = [](const std::string& imu) {
    try {
      kestrel::tools::live_config_from_yaml(live_yaml(imu), "live.yaml");
    } catch (const std::runtime_error& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(error("    type: iio\n").find("live.yaml: drivers.imu.iio.device: missing"), std::string::npos)
      << error("    type: iio\n");
  EXPECT_NE(error("    type: iio\n    iio: {device: a, rate: 5}\n").find("drivers.imu.iio.rate: unknown key"),
            std::string::npos);
  EXPECT_NE(error("    type: iio\n    iio: {device: a, timestamp_clock: gps}\n")
                .find("drivers.imu.iio.timestamp_clock: expected one of"),
            std::string::npos);
  EXPECT_NE(error("    type: iio\n    iio: {device: a, accel_device: b}\n")
                .find("drivers.imu.iio.device: a combined"),
            std::string::npos);
  EXPECT_NE(error("    type: iio\n    iio: {device: a, stall_timeout_ms: 0}\n")
                .find("drivers.imu.iio.stall_timeout_ms: must be in"),
            std::string::npos);
}

// The sensor thread of `kestrel record` / `kestrel run`: LiveSensors opens the
// fake tree from a config and its kst-imu thread waits in poll() on the FIFO.
struct CountingSink final : drivers::ImuSink {
  std::atomic<uint64_t> n{0};
  std::atomic<int64_t> last_t{0};
  std::atomic<uint64_t> out_of_order{0};
  bool push(const ImuSample& s) noexcept override {
    if (s.t_ns <= last_t.load()) out_of_order.fetch_add(1);
    last_t.store(s.t_ns);
    n.fetch_add(1);
    return true;
  }
};
struct NoFrames final : drivers::FrameSink {
  bool push_frame(const drivers::CameraFrame&) noexcept override { return true; }
};

TEST(IioLiveSensors, TheImuThreadReadsTheConfiguredDevice) {
  iio::FakeIioTree tree(temp_dir("iio_live"), {combined_imu_spec()});
  const drivers::LiveConfig c = kestrel::tools::live_config_from_yaml(
      live_yaml("    type: iio\n    iio:\n      device: icm42688\n      sysfs_root: " + tree.sysfs_root() +
                "\n      dev_root: " + tree.dev_root() + "\n"),
      "live.yaml");
  drivers::LiveSensors live(c);
  EXPECT_NE(live.description().find("Linux IIO (icm42688"), std::string::npos) << live.description();
  tree.open_writers();
  CountingSink sink;
  NoFrames frames;
  live.start(sink, frames);
  // 0.4 s of scans at 200 Hz in real time, stamped on CLOCK_MONOTONIC as the kernel would.
  for (int i = 0; i < 80; ++i) {
    uint8_t r[64];
    const size_t n = tree.encode(0, rt::now_ns(), {0, 0, 9.8}, {0, 0, 0.1}, r, sizeof r);
    ASSERT_EQ(tree.write_bytes(0, r, n), n);
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  // The thread may be slow to wake on a loaded machine: wait for it, up to 2 s.
  for (int k = 0; k < 200 && sink.n.load() < 80; ++k)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  live.stop();
  const std::string report = live.report();
  std::printf("[ figure ] %s", report.c_str());
  EXPECT_GE(sink.n.load(), 76u);  // the first few wait for the framer to confirm alignment
  EXPECT_EQ(sink.out_of_order.load(), 0u);
  EXPECT_NE(report.find("iio imu: state streaming"), std::string::npos);
  EXPECT_NE(report.find("host-clock stamps"), std::string::npos);
}

TEST(IioLiveSensors, AMissingDeviceIsNamedWhenOpening) {
  iio::FakeIioTree tree(temp_dir("iio_live_missing"), {d4xx_accel_spec()});
  const drivers::LiveConfig c = kestrel::tools::live_config_from_yaml(
      live_yaml("    type: iio\n    iio:\n      accel_device: accel_3d\n      gyro_device: gyro_3d\n"
                "      sysfs_root: " +
                tree.sysfs_root() + "\n"),
      "live.yaml");
  try {
    drivers::LiveSensors live(c);
    FAIL() << "opened a gyro that is not there";
  } catch (const std::runtime_error& e) {
    const std::string m = e.what();
    EXPECT_NE(m.find("IMU (Linux IIO)"), std::string::npos) << m;
    EXPECT_NE(m.find("no IIO device named \"gyro_3d\""), std::string::npos) << m;
  }
}

}  // namespace
}  // namespace kestrel::test

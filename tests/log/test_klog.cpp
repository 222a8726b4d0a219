// .klog writer/reader: round trip, truncation, corruption, resynchronisation.
#include <gtest/gtest.h>
#include <zlib.h>

#include <algorithm>
#include <cstring>
#include <filesystem>
#include <random>
#include <set>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/klog_format.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "klog_fuzz_entry.hpp"
#include "log_fixtures.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

using drivers::KlogReader;
using drivers::LogRecord;
using drivers::RecordType;

bool same_bits(double a, double b) { return std::memcmp(&a, &b, sizeof a) == 0; }

void expect_imu_eq(const ImuSample& a, const ImuSample& b) {
  EXPECT_EQ(a.t_ns, b.t_ns);
  EXPECT_EQ(a.t_recv_ns, b.t_recv_ns);
  EXPECT_EQ(a.seq, b.seq);
  EXPECT_EQ(a.flags, b.flags);
  for (int k = 0; k < 3; ++k) {
    EXPECT_TRUE(same_bits(a.gyro_rps[k], b.gyro_rps[k]));
    EXPECT_TRUE(same_bits(a.acc_mps2[k], b.acc_mps2[k]));
  }
  EXPECT_EQ(a.temp_c, b.temp_c);
}

void expect_image_eq(const drivers::LogImage& a, const drivers::LogImage& b) {
  EXPECT_EQ(a.t_ns, b.t_ns);
  EXPECT_EQ(a.t_recv_ns, b.t_recv_ns);
  EXPECT_EQ(a.seq, b.seq);
  EXPECT_EQ(a.exposure_us, b.exposure_us);
  EXPECT_EQ(a.width, b.width);
  EXPECT_EQ(a.height, b.height);
  EXPECT_EQ(a.format, b.format);
  EXPECT_EQ(a.pixels, b.pixels);
}

struct Small {
  std::string path;
  std::vector<uint8_t> bytes;
  std::vector<RecordSpan> spans;
};

Small small_log(const std::string& name) {
  Small s;
  s.path = temp_dir(name) + "/small.klog";
  write_small_klog(s.path, &s.spans);
  s.bytes = read_bytes(s.path);
  return s;
}

std::vector<LogRecord> read_all(drivers::LogSource& src) {
  std::vector<LogRecord> out;
  LogRecord r;
  while (src.next(r)) out.push_back(r);
  return out;
}

TEST(Klog, RoundTripsEveryRecordType) {
  const std::string path = temp_dir("klog_rt") + "/rt.klog";
  const Rig rig = fixture_rig();
  std::vector<ImuSample> imu;
  std::vector<drivers::LogImage> images;
  const PixelFormat formats[] = {PixelFormat::kGray8, PixelFormat::kRgb8, PixelFormat::kBgr8,
                                 PixelFormat::kYuyv, PixelFormat::kDepthU16};
  {
    drivers::KlogWriter w;
    w.open(path, rig);
    for (uint32_t i = 0; i < 5; ++i) {
      imu.push_back(fixture_imu(i));
      w.write_imu(imu.back());
      images.push_back(fixture_image(i, formats[i], 6 + static_cast<int>(i), 4));
      w.write_image(formats[i] == PixelFormat::kDepthU16 ? RecordType::kDepth : RecordType::kRgb,
                    images.back());
    }
    // A strided view is packed on the way in.
    std::vector<uint8_t> strided(3 * 10, 0xEE);
    for (int y = 0; y < 3; ++y)
      for (int x = 0; x < 4; ++x) strided[y * 10 + x] = static_cast<uint8_t>(y * 4 + x);
    w.write_image(RecordType::kRgb, 77, 78, 9, -1, ImageView{4, 3, 10, PixelFormat::kGray8, strided.data()});
    w.write_ground_truth(fixture_gt(3, false));
    w.write_ground_truth(fixture_gt(4, true));
    w.write_event(Event{42, EventCode::kDriverFault, std::string("bmx055: NACK \0 at 0x18", 22)});
    w.write_event(Event{43, EventCode::kInfo, ""});
    EXPECT_EQ(w.records_written(), 15u);
    EXPECT_EQ(w.bytes_written(), std::filesystem::file_size(path));
  }
  KlogReader r(path);
  EXPECT_EQ(r.format_name(), "klog");
  EXPECT_EQ(r.version(), drivers::kKlogVersion);
  EXPECT_TRUE(drivers::rig_equal(r.rig(), rig));
  for (int pass = 0; pass < 2; ++pass) {
    const auto recs = read_all(r);
    ASSERT_EQ(recs.size(), 15u);
    for (size_t i = 0; i < 5; ++i) {
      ASSERT_EQ(recs[2 * i].type, RecordType::kImu);
      expect_imu_eq(recs[2 * i].imu, imu[i]);
      ASSERT_EQ(recs[2 * i + 1].type,
                formats[i] == PixelFormat::kDepthU16 ? RecordType::kDepth : RecordType::kRgb);
      expect_image_eq(recs[2 * i + 1].image, images[i]);
    }
    const auto& s = recs[10].image;
    EXPECT_EQ(s.t_ns, 77);
    EXPECT_EQ(s.exposure_us, -1);
    ASSERT_EQ(s.pixels.size(), 12u);
    for (int k = 0; k < 12; ++k) EXPECT_EQ(s.pixels[k], k);
    for (int k = 0; k < 2; ++k) {
      const auto want = fixture_gt(3 + k, k == 1);
      const auto& got = recs[11 + k].gt;
      ASSERT_EQ(recs[11 + k].type, RecordType::kGroundTruth);
      EXPECT_EQ(got.t_ns, want.t_ns);
      EXPECT_EQ(got.p_WB, want.p_WB);
      EXPECT_EQ(got.q_WB, want.q_WB);
      EXPECT_EQ(got.has_velocity, want.has_velocity);
      EXPECT_EQ(got.v_WB, want.v_WB);
    }
    EXPECT_EQ(recs[13].event.code, EventCode::kDriverFault);
    EXPECT_EQ(recs[13].event.text, std::string("bmx055: NACK \0 at 0x18", 22));
    EXPECT_EQ(recs[14].event.text, "");
    r.rewind();
  }
  EXPECT_TRUE(r.problems().empty());
  auto via_open = drivers::open_log(path);
  EXPECT_EQ(via_open->format_name(), "klog");
}

TEST(Klog, PayloadSizesMatchTheDocumentedLayout) {
  std::string b;
  drivers::klog::encode_imu(fixture_imu(1), b);
  EXPECT_EQ(b.size(), drivers::klog::kImuPayloadBytes);
  b.clear();
  drivers::klog::encode_image_header(1, 2, 3, 4, 5, 6, PixelFormat::kRgb8, b);
  EXPECT_EQ(b.size(), drivers::klog::kImageHeaderBytes);
  b.clear();
  drivers::klog::encode_ground_truth(fixture_gt(1, true), b);
  EXPECT_EQ(b.size(), drivers::klog::kGroundTruthPayloadBytes);
  b.clear();
  drivers::klog::encode_event(Event{1, EventCode::kInfo, "abc"}, b);
  EXPECT_EQ(b.size(), drivers::klog::kEventHeaderBytes + 3);
  // The sync marker's bytes on disk, as docs/log-format.md gives them.
  b.clear();
  drivers::klog::ByteWriter(b).u32(drivers::klog::kSyncMarker);
  EXPECT_EQ(b, std::string("\xA5\x4B\x52\x5A", 4));
}

TEST(Klog, RecoversEveryIntactRecordAtEveryTruncation) {
  const Small s = small_log("klog_trunc");
  const uint64_t data_start = s.spans.front().begin;
  for (size_t cut = 0; cut <= s.bytes.size(); ++cut) {
    SCOPED_TRACE("cut at " + std::to_string(cut));
    if (cut < data_start) {
      EXPECT_THROW(KlogReader::from_memory(s.bytes.data(), cut, "t.klog", {}), std::runtime_error);
      auto salvaged = KlogReader::from_memory(s.bytes.data(), cut, "t.klog", KlogReader::Options{true});
      LogRecord r;
      EXPECT_FALSE(salvaged->next(r));
      ASSERT_FALSE(salvaged->problems().empty());
      EXPECT_EQ(salvaged->problems()[0].kind, "bad-header");
      continue;
    }
    auto reader = KlogReader::from_memory(s.bytes.data(), cut, "t.klog", {});
    const auto recs = read_all(*reader);
    size_t intact = 0;
    while (intact < s.spans.size() && s.spans[intact].end <= cut) ++intact;
    ASSERT_EQ(recs.size(), intact);
    for (size_t i = 0; i < intact; ++i) {
      EXPECT_EQ(recs[i].offset, s.spans[i].begin);
      EXPECT_EQ(recs[i].type, s.spans[i].type);
    }
    const bool on_boundary = intact == s.spans.size() || s.spans[intact].begin == cut;
    if (on_boundary) {
      EXPECT_TRUE(reader->problems().empty());
    } else {
      ASSERT_EQ(reader->problems().size(), 1u);
      EXPECT_EQ(reader->problems()[0].kind, "truncated");
      EXPECT_EQ(reader->problems()[0].where, "t.klog@" + std::to_string(s.spans[intact].begin));
    }
  }
}

TEST(Klog, TruncatedFileOnDiskKeepsItsRecords) {
  Small s = small_log("klog_trunc_disk");
  const uint64_t cut = s.spans[5].begin + 20;  // inside the ground-truth payload
  std::filesystem::resize_file(s.path, cut);
  KlogReader r(s.path);
  EXPECT_EQ(read_all(r).size(), 5u);
  ASSERT_EQ(r.problems().size(), 1u);
  EXPECT_EQ(r.problems()[0].where, s.path + "@" + std::to_string(s.spans[5].begin));
  EXPECT_EQ(r.problems()[0].kind, "truncated");
}

TEST(Klog, BitFlipLosesOnlyTheFlippedRecord) {
  const Small s = small_log("klog_flip");
  size_t flips = 0;
  for (size_t k = 0; k < s.spans.size(); ++k) {
    const RecordSpan& sp = s.spans[k];
    for (uint64_t byte = sp.begin; byte < sp.end; ++byte) {
      for (int bit = 0; bit < 8; bit += (byte - sp.begin < drivers::klog::kRecordHeaderBytes ? 1 : 3)) {
        std::vector<uint8_t> b = s.bytes;
        b[byte] ^= static_cast<uint8_t>(1u << bit);
        auto reader = KlogReader::from_memory(b.data(), b.size(), "f.klog", {});
        const auto recs = read_all(*reader);
        SCOPED_TRACE("record " + std::to_string(k) + " byte " + std::to_string(byte) + " bit " +
                     std::to_string(bit));
        ASSERT_EQ(recs.size(), s.spans.size() - 1);
        for (size_t i = 0, j = 0; i < s.spans.size(); ++i) {
          if (i == k) continue;
          EXPECT_EQ(recs[j++].offset, s.spans[i].begin);
        }
        ASSERT_EQ(reader->problems().size(), 1u);
        const auto& p = reader->problems()[0];
        EXPECT_EQ(p.where, "f.klog@" + std::to_string(sp.begin));
        const uint64_t in = byte - sp.begin;
        if (in < 4) {
          EXPECT_EQ(p.kind, "bad-sync");
        } else if (in >= 8 && in < 12) {
          // A damaged length may point past the file end or beyond the cap before the CRC is checked.
          EXPECT_TRUE(p.kind == "bad-crc" || p.kind == "bad-length" || p.kind == "truncated") << p.kind;
        } else {
          EXPECT_EQ(p.kind, "bad-crc");
        }
        ++flips;
      }
    }
  }
  EXPECT_GT(flips, 1000u);
}

TEST(Klog, SkipsInsertedGarbageAndUnknownTypes) {
  const Small s = small_log("klog_garbage");
  const uint64_t at = s.spans[4].begin;
  // Garbage with a fake sync marker whose "record" fails its CRC.
  std::vector<uint8_t> junk = {0x00, 0xA5, 0x4B, 0x52, 0x5A, 1, 0, 0, 0, 4, 0,
                               0,    0,    9,    9,    9,    9, 1, 2, 3, 4, 0xFF};
  // A well-formed record of a type from the future: CRC passes, type unknown.
  std::string future;
  drivers::klog::ByteWriter w(future);
  const uint8_t payload[3] = {1, 2, 3};
  w.u32(drivers::klog::kSyncMarker);
  w.u16(99);
  w.u16(0);
  w.u32(3);
  w.u32(drivers::klog::record_crc(99, 0, 3, payload));
  w.bytes(payload, 3);
  // And a known type whose CRC passes but whose payload is malformed.
  std::string bad_imu;
  drivers::klog::ByteWriter b(bad_imu);
  std::vector<uint8_t> short_imu(drivers::klog::kImuPayloadBytes - 1, 0);
  b.u32(drivers::klog::kSyncMarker);
  b.u16(1);
  b.u16(0);
  b.u32(static_cast<uint32_t>(short_imu.size()));
  b.u32(drivers::klog::record_crc(1, 0, static_cast<uint32_t>(short_imu.size()), short_imu.data()));
  b.bytes(short_imu.data(), short_imu.size());

  std::vector<uint8_t> bytes(s.bytes.begin(), s.bytes.begin() + static_cast<long>(at));
  bytes.insert(bytes.end(), junk.begin(), junk.end());
  const uint64_t future_at = bytes.size();
  bytes.insert(bytes.end(), future.begin(), future.end());
  const uint64_t bad_imu_at = bytes.size();
  bytes.insert(bytes.end(), bad_imu.begin(), bad_imu.end());
  bytes.insert(bytes.end(), s.bytes.begin() + static_cast<long>(at), s.bytes.end());

  auto reader = KlogReader::from_memory(bytes.data(), bytes.size(), "g.klog", {});
  const auto recs = read_all(*reader);
  ASSERT_EQ(recs.size(), s.spans.size());
  const auto& p = reader->problems();
  ASSERT_EQ(p.size(), 3u);
  EXPECT_EQ(p[0].kind, "bad-sync");
  EXPECT_EQ(p[0].where, "g.klog@" + std::to_string(at));
  EXPECT_EQ(p[1].kind, "bad-type");
  EXPECT_EQ(p[1].where, "g.klog@" + std::to_string(future_at));
  EXPECT_EQ(p[2].kind, "bad-payload");
  EXPECT_EQ(p[2].where, "g.klog@" + std::to_string(bad_imu_at));
  // Rewinding replays the same records without reporting the damage twice.
  reader->rewind();
  EXPECT_EQ(read_all(*reader).size(), s.spans.size());
  EXPECT_EQ(reader->problems().size(), 3u);
}

TEST(Klog, HugeLengthIsRejectedWithoutAllocating) {
  const Small s = small_log("klog_huge");
  std::vector<uint8_t> b = s.bytes;
  const uint64_t at = s.spans[2].begin;
  for (int k = 0; k < 4; ++k) b[at + 8 + k] = 0xFF;  // length = 4 GiB - 1
  auto reader = KlogReader::from_memory(b.data(), b.size(), "h.klog", {});
  EXPECT_EQ(read_all(*reader).size(), s.spans.size() - 1);
  ASSERT_EQ(reader->problems().size(), 1u);
  EXPECT_EQ(reader->problems()[0].kind, "bad-length");
}

TEST(Klog, DamagedHeaderThrowsUnlessSalvaging) {
  const Small s = small_log("klog_header");
  std::vector<uint8_t> b = s.bytes;
  b[30] ^= 0x10;  // inside the rig YAML
  const std::string path = temp_dir("klog_header2") + "/bad.klog";
  write_bytes(path, b.data(), b.size());
  try {
    KlogReader r(path);
    ADD_FAILURE() << "no throw";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(path), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("CRC"), std::string::npos) << e.what();
  }
  KlogReader r(path, KlogReader::Options{true});
  EXPECT_EQ(read_all(r).size(), s.spans.size());
  ASSERT_EQ(r.problems().size(), 1u);
  EXPECT_EQ(r.problems()[0].kind, "bad-header");
  EXPECT_EQ(r.problems()[0].where, path + "@0");

  EXPECT_THROW(KlogReader(temp_dir("klog_header3") + "/absent.klog"), std::runtime_error);
}

TEST(Klog, NewerVersionIsRefused) {
  const Small s = small_log("klog_version");
  std::vector<uint8_t> b = s.bytes;
  b[4] = static_cast<uint8_t>(drivers::kKlogVersion + 1);
  // Re-seal the header so that only the version differs.
  const uint32_t header_len = b[8] | (b[9] << 8) | (b[10] << 16) | (static_cast<uint32_t>(b[11]) << 24);
  const auto crc = static_cast<uint32_t>(crc32(crc32(0L, Z_NULL, 0), b.data(), header_len - 4));
  for (int k = 0; k < 4; ++k) b[header_len - 4 + k] = static_cast<uint8_t>(crc >> (8 * k));
  try {
    KlogReader::from_memory(b.data(), b.size(), "v.klog", KlogReader::Options{true});
    ADD_FAILURE() << "no throw";
  } catch (const std::runtime_error& e) {
    const std::string want = "v.klog: klog version " + std::to_string(drivers::kKlogVersion + 1);
    EXPECT_NE(std::string(e.what()).find(want), std::string::npos) << e.what();
  }
}

// A few thousand deterministic mutations of a valid log through the fuzz
// entry: no crash, termination (checked inside), and every record that lies
// wholly before the first damaged byte is recovered.
TEST(Klog, MutationsNeverLoseIntactRecords) {
  const Small s = small_log("klog_mut");
  std::mt19937_64 rng(20240611);
  const size_t n = s.bytes.size();
  for (int iter = 0; iter < 4000; ++iter) {
    std::vector<uint8_t> b = s.bytes;
    uint64_t first_damage = n;
    const int kind = iter % 4;
    std::set<size_t> touched;  // records hit by bit flips (flips never shift bytes)
    if (kind == 0) {           // 1..3 bit flips within 8 bytes: CRC32 detects every such error
      const int flips = 1 + static_cast<int>(rng() % 3);
      const uint64_t base = rng() % n;
      for (int f = 0; f < flips; ++f) {
        const uint64_t at = std::min<uint64_t>(n - 1, base + rng() % 8);
        b[at] ^= static_cast<uint8_t>(1u << (rng() % 8));
      }
      // Two flips of one bit cancel, so the damage is what actually differs.
      for (uint64_t at = base; at < std::min<uint64_t>(n, base + 8); ++at) {
        if (b[at] == s.bytes[at]) continue;
        first_damage = std::min(first_damage, at);
        for (size_t k = 0; k < s.spans.size(); ++k)
          if (s.spans[k].begin <= at && at < s.spans[k].end) touched.insert(k);
      }
    } else if (kind == 1) {  // truncation
      const uint64_t cut = rng() % (n + 1);
      b.resize(cut);
      first_damage = cut;
    } else if (kind == 2) {  // inserted garbage, sometimes with sync markers in it
      const uint64_t at = rng() % (n + 1);
      std::vector<uint8_t> junk(1 + rng() % 40);
      for (auto& j : junk) j = static_cast<uint8_t>(rng());
      if (rng() % 2 && junk.size() >= 4) std::memcpy(junk.data(), "\xA5\x4B\x52\x5A", 4);
      b.insert(b.begin() + static_cast<long>(at), junk.begin(), junk.end());
      first_damage = at;
    } else {  // overwritten run
      const uint64_t at = rng() % n;
      const uint64_t len = std::min<uint64_t>(n - at, 1 + rng() % 64);
      for (uint64_t k = 0; k < len; ++k) b[at + k] = static_cast<uint8_t>(rng());
      first_damage = at;
    }
    SCOPED_TRACE("iteration " + std::to_string(iter) + " kind " + std::to_string(kind) + " damage at " +
                 std::to_string(first_damage));
    const bool header_hit = first_damage < s.spans.front().begin;
    const KlogFuzzResult strict = klog_fuzz_one(b.data(), b.size(), false);
    const KlogFuzzResult res = klog_fuzz_one(b.data(), b.size(), true);
    ASSERT_TRUE(res.opened);
    if (!header_hit) {
      ASSERT_TRUE(strict.opened);
    }
    size_t intact = 0;
    while (intact < s.spans.size() && s.spans[intact].end <= first_damage) ++intact;
    if (!header_hit) {
      ASSERT_GE(res.offsets.size(), intact);
      for (size_t i = 0; i < intact; ++i) ASSERT_EQ(res.offsets[i], s.spans[i].begin);
    }
    if (kind == 0 && !header_hit) {
      // Flipped bits lose the records they hit and nothing else.
      std::vector<uint64_t> want;
      for (size_t k = 0; k < s.spans.size(); ++k)
        if (!touched.count(k)) want.push_back(s.spans[k].begin);
      EXPECT_EQ(res.offsets, want);
      EXPECT_EQ(strict.offsets, want);
    }
  }
}

}  // namespace
}  // namespace kestrel::test

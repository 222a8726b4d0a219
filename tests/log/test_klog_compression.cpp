// Compressed .klog images (format version 2): the pre-filters invert exactly,
// every codec round-trips every pixel format bit for bit, version 1 files
// still read, and a damaged compressed record is reported and skipped without
// trusting any size it claims.
#include <gtest/gtest.h>
#include <zlib.h>
#include <zstd.h>

#include <algorithm>
#include <cstring>
#include <random>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/klog_format.hpp"
#include "kestrel/drivers/klog_image_codec.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "klog_fuzz_entry.hpp"
#include "log_fixtures.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

using drivers::KlogReader;
using drivers::KlogWriter;
using drivers::LogImage;
using drivers::LogRecord;
using drivers::RecordType;
namespace klog = drivers::klog;

// A smooth scene with sensor noise and invalid depth blobs: compressible the
// way camera frames are, with every byte value still reachable.
LogImage scene_image(uint32_t i, PixelFormat f, int w, int h, uint32_t seed = 1) {
  LogImage img;
  img.t_ns = 2'000'000'000 + int64_t{i} * 33'333'333;
  img.t_recv_ns = img.t_ns + 3'000'000;
  img.seq = i;
  img.exposure_us = 5000 + static_cast<int32_t>(i);
  img.width = w;
  img.height = h;
  img.format = f;
  const int bpp = bytes_per_pixel(f);
  img.pixels.resize(static_cast<size_t>(w) * h * bpp);
  std::mt19937 rng(seed * 7919 + i);
  std::normal_distribution<double> noise(0.0, 2.0);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const double s = 0.5 + 0.5 * std::sin(0.05 * x + 0.03 * y + 0.2 * i) * std::cos(0.04 * y - 0.01 * x);
      uint8_t* p = &img.pixels[(static_cast<size_t>(y) * w + x) * bpp];
      if (f == PixelFormat::kDepthU16) {
        const bool hole = ((x / 7 + y / 5 + static_cast<int>(i)) % 17) == 0;
        const int d = hole ? 0 : std::clamp(static_cast<int>(800 + 3000 * s + noise(rng)), 1, 65535);
        p[0] = static_cast<uint8_t>(d & 0xff);
        p[1] = static_cast<uint8_t>(d >> 8);
      } else {
        for (int c = 0; c < bpp; ++c)
          p[c] =
              static_cast<uint8_t>(std::clamp(static_cast<int>(40 + 170 * s + 20 * c + noise(rng)), 0, 255));
      }
    }
  return img;
}

LogImage random_image(std::mt19937& rng, PixelFormat f, int w, int h) {
  LogImage img;
  img.width = w;
  img.height = h;
  img.format = f;
  img.pixels.resize(static_cast<size_t>(w) * h * bytes_per_pixel(f));
  // Extremes on purpose: the residuals must wrap and unwrap exactly.
  std::uniform_int_distribution<int> pick(0, 3);
  std::uniform_int_distribution<int> byte(0, 255);
  for (auto& b : img.pixels) {
    const int k = pick(rng);
    b = static_cast<uint8_t>(k == 0 ? 0 : k == 1 ? 255 : byte(rng));
  }
  return img;
}

std::vector<LogRecord> read_all(drivers::LogSource& src) {
  std::vector<LogRecord> out;
  LogRecord r;
  while (src.next(r)) out.push_back(r);
  return out;
}

const PixelFormat kFormats[] = {PixelFormat::kGray8, PixelFormat::kRgb8, PixelFormat::kBgr8,
                                PixelFormat::kYuyv, PixelFormat::kDepthU16};

TEST(KlogCompression, FiltersInvertExactlyOnEveryFormatAndShape) {
  std::mt19937 rng(11);
  const int shapes[][2] = {{1, 1}, {1, 7}, {7, 1}, {2, 2}, {13, 5}, {64, 3}, {33, 17}};
  for (PixelFormat f : kFormats) {
    const klog::ImageFilter filter = klog::filter_for(f);
    for (const auto& s : shapes) {
      const LogImage img = random_image(rng, f, s[0], s[1]);
      const int bpp = bytes_per_pixel(f);
      const size_t bytes = img.pixels.size();
      // The forward filter reads through a stride wider than the row.
      const int stride = s[0] * bpp + 5;
      std::vector<uint8_t> strided(static_cast<size_t>(stride) * s[1], 0xAB);
      for (int y = 0; y < s[1]; ++y)
        std::memcpy(&strided[static_cast<size_t>(y) * stride],
                    &img.pixels[static_cast<size_t>(y) * s[0] * bpp], static_cast<size_t>(s[0]) * bpp);
      std::vector<uint8_t> res(bytes), scratch(klog::filter_scratch_bytes(s[0])), back(bytes, 0x5A);
      klog::filter_forward(filter, ImageView{s[0], s[1], stride, f, strided.data()}, res.data(),
                           scratch.data());
      klog::filter_inverse(filter, f, s[0], s[1], res.data(), back.data());
      EXPECT_EQ(back, img.pixels) << "format " << int(f) << " " << s[0] << "x" << s[1];
    }
  }
}

TEST(KlogCompression, MedianPredictorMatchesItsDefinition) {
  // A 3x2 gray image worked by hand: row 0 predicts from the left, (0,1) from
  // above, (1,1) from median(a=left, b=up, a+b-c).
  const uint8_t px[6] = {10, 12, 20, 11, 30, 5};
  std::vector<uint8_t> res(6), scratch(klog::filter_scratch_bytes(3));
  klog::filter_forward(klog::ImageFilter::kMedPlanar, ImageView{3, 2, 3, PixelFormat::kGray8, px}, res.data(),
                       scratch.data());
  // (1,1): a=11 b=12 c=10 -> a+b-c = 13 clamped to [11,12] = 12; 30-12 = 18.
  // (2,1): a=30 b=20 c=12 -> 38 clamped to [20,30] = 30; 5-30 wraps to 231.
  const std::vector<uint8_t> want = {10, 2, 8, 1, 18, 231};
  EXPECT_EQ(res, want);
}

TEST(KlogCompression, EveryCodecRoundTripsEveryFormatBitForBit) {
  const std::string dir = temp_dir("klogz_rt");
  for (klog::ImageCodec codec : {klog::ImageCodec::kRaw, klog::ImageCodec::kZstd, klog::ImageCodec::kLz4}) {
    const std::string path = dir + "/" + klog::codec_name(codec) + ".klog";
    std::vector<LogImage> written;
    KlogWriter::Options o;
    o.compression.codec = codec;
    {
      KlogWriter w;
      w.open(path, fixture_rig(), o);
      uint32_t i = 0;
      for (PixelFormat f : kFormats)
        for (const auto& s : {std::pair<int, int>{96, 64}, {31, 9}, {1, 1}}) {
          written.push_back(scene_image(i++, f, s.first, s.second));
          w.write_image(f == PixelFormat::kDepthU16 ? RecordType::kDepth : RecordType::kRgb, written.back());
          w.write_imu(fixture_imu(i));
        }
      if (codec == klog::ImageCodec::kZstd) {
        EXPECT_LT(w.image_bytes_stored() * 3, w.image_bytes_raw() * 2) << "zstd should shrink smooth images";
      } else if (codec == klog::ImageCodec::kLz4) {
        EXPECT_LT(w.image_bytes_stored() * 10, w.image_bytes_raw() * 9) << "lz4 should shrink smooth images";
      } else {
        EXPECT_EQ(w.image_bytes_stored(), w.image_bytes_raw());
      }
    }
    KlogReader r(path);
    EXPECT_EQ(r.version(), 2u);
    const auto recs = read_all(r);
    EXPECT_TRUE(r.problems().empty()) << r.problems()[0].where << " " << r.problems()[0].detail;
    size_t k = 0;
    for (const auto& rec : recs) {
      if (rec.type == RecordType::kImu) continue;
      ASSERT_LT(k, written.size());
      const LogImage& a = written[k++];
      EXPECT_EQ(rec.image.pixels, a.pixels) << klog::codec_name(codec) << " image " << k;
      EXPECT_EQ(rec.image.width, a.width);
      EXPECT_EQ(rec.image.height, a.height);
      EXPECT_EQ(rec.image.format, a.format);
      EXPECT_EQ(rec.image.t_ns, a.t_ns);
      EXPECT_EQ(rec.image.t_recv_ns, a.t_recv_ns);
      EXPECT_EQ(rec.image.seq, a.seq);
      EXPECT_EQ(rec.image.exposure_us, a.exposure_us);
    }
    EXPECT_EQ(k, written.size());
  }
}

TEST(KlogCompression, IncompressiblePixelsAreStoredRaw) {
  std::mt19937 rng(5);
  LogImage img = random_image(rng, PixelFormat::kRgb8, 64, 48);
  std::uniform_int_distribution<int> byte(0, 255);
  for (auto& b : img.pixels) b = static_cast<uint8_t>(byte(rng));
  const std::string path = temp_dir("klogz_noise") + "/n.klog";
  {
    KlogWriter w;
    w.open(path, fixture_rig());
    w.write_image(RecordType::kRgb, img);
    EXPECT_EQ(w.image_bytes_stored(), w.image_bytes_raw());
  }
  const auto b = read_bytes(path);
  KlogReader r(path);
  const size_t image_at = r.data_offset() + klog::kRecordHeaderBytes;
  EXPECT_EQ(b[image_at + klog::kImageCodecByte], 0);
  EXPECT_EQ(b[image_at + klog::kImageFilterByte], 0);
  const auto recs = read_all(r);
  ASSERT_EQ(recs.size(), 1u);
  EXPECT_EQ(recs[0].image.pixels, img.pixels);
}

// ---- version 1 -------------------------------------------------------------------------------------------

// A version 1 file assembled byte by byte as the version 1 layout says
// (docs/log-format.md), independent of today's writer.
std::vector<uint8_t> hand_made_v1(const LogImage& img, const ImuSample* s, uint16_t type = 2) {
  std::string out;
  klog::ByteWriter w(out);
  const std::string yaml = drivers::rig_to_yaml(fixture_rig());
  w.bytes("KLOG", 4);
  w.u32(1);
  w.u32(static_cast<uint32_t>(16 + yaml.size() + 4));
  w.u32(static_cast<uint32_t>(yaml.size()));
  w.bytes(yaml.data(), yaml.size());
  w.u32(static_cast<uint32_t>(
      crc32(0, reinterpret_cast<const Bytef*>(out.data()), static_cast<uInt>(out.size()))));
  auto record = [&](uint16_t type, const std::string& payload) {
    w.u32(0x5A524BA5u);
    w.u16(type);
    w.u16(0);
    w.u32(static_cast<uint32_t>(payload.size()));
    w.u32(klog::record_crc(type, 0, static_cast<uint32_t>(payload.size()),
                           reinterpret_cast<const uint8_t*>(payload.data())));
    w.bytes(payload.data(), payload.size());
  };
  std::string p;
  klog::ByteWriter pw(p);
  pw.i64(img.t_ns);
  pw.i64(img.t_recv_ns);
  pw.u32(img.seq);
  pw.i32(img.exposure_us);
  pw.u32(static_cast<uint32_t>(img.width));
  pw.u32(static_cast<uint32_t>(img.height));
  pw.u8(static_cast<uint8_t>(img.format));
  pw.u8(0);
  pw.u8(0);
  pw.u8(0);
  pw.bytes(img.pixels.data(), img.pixels.size());
  record(type, p);
  if (s) {
    std::string q;
    klog::encode_imu(*s, q);
    record(1, q);
  }
  return std::vector<uint8_t>(out.begin(), out.end());
}

TEST(KlogCompression, HandMadeVersion1FileStillReads) {
  const LogImage img = scene_image(3, PixelFormat::kRgb8, 40, 30);
  const ImuSample s = fixture_imu(4);
  const auto bytes = hand_made_v1(img, &s);
  const std::string path = temp_dir("klogz_v1") + "/v1.klog";
  write_bytes(path, bytes.data(), bytes.size());
  KlogReader r(path);
  EXPECT_EQ(r.version(), 1u);
  const auto recs = read_all(r);
  EXPECT_TRUE(r.problems().empty());
  ASSERT_EQ(recs.size(), 2u);
  EXPECT_EQ(recs[0].image.pixels, img.pixels);
  EXPECT_EQ(recs[0].image.seq, img.seq);
  EXPECT_EQ(recs[1].imu.seq, s.seq);
}

TEST(KlogCompression, WriterEmitsVersion1OnRequestAndReadsItBack) {
  const std::string path = temp_dir("klogz_v1w") + "/v1.klog";
  const LogImage img = scene_image(0, PixelFormat::kDepthU16, 40, 30);
  KlogWriter::Options o;
  o.version = 1;
  o.compression.codec = klog::ImageCodec::kRaw;
  {
    KlogWriter w;
    w.open(path, fixture_rig(), o);
    w.write_image(RecordType::kDepth, img);
  }
  // Byte for byte what the version 1 layout gives.
  EXPECT_EQ(read_bytes(path), hand_made_v1(img, nullptr, 3));
  KlogReader r(path);
  EXPECT_EQ(r.version(), 1u);
  const auto recs = read_all(r);
  ASSERT_EQ(recs.size(), 1u);
  EXPECT_EQ(recs[0].image.pixels, img.pixels);
  // Version 1 has no compressed images: asking for both is refused.
  KlogWriter w;
  o.compression.codec = klog::ImageCodec::kZstd;
  EXPECT_THROW(w.open(temp_dir("klogz_v1w") + "/bad.klog", fixture_rig(), o), std::invalid_argument);
}

TEST(KlogCompression, CodecByteInAVersion1FileIsABadPayload) {
  const LogImage img = scene_image(1, PixelFormat::kGray8, 16, 8);
  const ImuSample imu = fixture_imu(1);
  auto bytes = hand_made_v1(img, &imu);
  // The image record follows the header: 16 fixed bytes, the rig, the CRC.
  const size_t rec = 16 + drivers::rig_to_yaml(fixture_rig()).size() + 4;
  const size_t payload = rec + klog::kRecordHeaderBytes;
  bytes[payload + klog::kImageCodecByte] = 1;
  uint32_t len = 0;
  std::memcpy(&len, &bytes[rec + 8], 4);
  const uint32_t crc = klog::record_crc(2, 0, len, &bytes[payload]);
  for (int k = 0; k < 4; ++k) bytes[rec + 12 + k] = static_cast<uint8_t>(crc >> (8 * k));
  auto r = KlogReader::from_memory(bytes.data(), bytes.size(), "v1c.klog", {});
  const auto recs = read_all(*r);
  ASSERT_EQ(recs.size(), 1u);  // the IMU record after it survives
  EXPECT_EQ(recs[0].type, RecordType::kImu);
  ASSERT_EQ(r->problems().size(), 1u);
  EXPECT_EQ(r->problems()[0].kind, "bad-payload");
  EXPECT_EQ(r->problems()[0].where, "v1c.klog@" + std::to_string(rec));
  EXPECT_NE(r->problems()[0].detail.find("version 1"), std::string::npos) << r->problems()[0].detail;
}

// ---- damage ----------------------------------------------------------------------------------------------

struct CompressedLog {
  std::vector<uint8_t> bytes;
  std::vector<RecordSpan> spans;
  std::vector<LogImage> images;
};

// IMU, compressed RGB, IMU, compressed depth, IMU, lz4 RGB, IMU.
CompressedLog compressed_log(const std::string& name) {
  CompressedLog c;
  const std::string dir = temp_dir(name);
  const std::string path = dir + "/c.klog";
  KlogWriter w;
  w.open(path, fixture_rig());
  uint64_t at = w.bytes_written();
  auto mark = [&](RecordType t) {
    c.spans.push_back({t, at, w.bytes_written()});
    at = w.bytes_written();
  };
  w.write_imu(fixture_imu(0));
  mark(RecordType::kImu);
  c.images.push_back(scene_image(0, PixelFormat::kRgb8, 48, 32));
  w.write_image(RecordType::kRgb, c.images.back());
  mark(RecordType::kRgb);
  w.write_imu(fixture_imu(1));
  mark(RecordType::kImu);
  c.images.push_back(scene_image(0, PixelFormat::kDepthU16, 48, 32));
  w.write_image(RecordType::kDepth, c.images.back());
  mark(RecordType::kDepth);
  w.write_imu(fixture_imu(2));
  mark(RecordType::kImu);
  w.close();
  KlogWriter::Options lz;
  lz.compression.codec = klog::ImageCodec::kLz4;
  const std::string path2 = dir + "/lz.klog";
  w.open(path2, fixture_rig(), lz);
  c.images.push_back(scene_image(1, PixelFormat::kRgb8, 48, 32));
  w.write_image(RecordType::kRgb, c.images.back());
  w.write_imu(fixture_imu(3));
  w.close();
  c.bytes = read_bytes(path);
  // Append the lz4 file's records (after its header) to the zstd file.
  const auto more = read_bytes(path2);
  KlogReader r2(path2);
  const uint64_t base = c.bytes.size();
  const uint64_t cut = r2.data_offset();
  c.bytes.insert(c.bytes.end(), more.begin() + static_cast<std::ptrdiff_t>(cut), more.end());
  const uint64_t img_end = base + klog::kRecordHeaderBytes + [&] {
    uint32_t len = 0;
    std::memcpy(&len, &more[cut + 8], 4);
    return uint64_t{len};
  }();
  c.spans.push_back({RecordType::kRgb, base, img_end});
  c.spans.push_back({RecordType::kImu, img_end, c.bytes.size()});
  return c;
}

void reseal(std::vector<uint8_t>& b, const RecordSpan& s) {
  uint16_t type = 0, flags = 0;
  uint32_t len = 0;
  std::memcpy(&type, &b[s.begin + 4], 2);
  std::memcpy(&flags, &b[s.begin + 6], 2);
  std::memcpy(&len, &b[s.begin + 8], 4);
  if (len > b.size() - s.begin - klog::kRecordHeaderBytes) return;  // a mutated length: leave it damaged
  const uint32_t crc = klog::record_crc(type, flags, len, &b[s.begin + klog::kRecordHeaderBytes]);
  for (int k = 0; k < 4; ++k) b[s.begin + 12 + k] = static_cast<uint8_t>(crc >> (8 * k));
}

TEST(KlogCompression, FixtureHasCompressedRecordsOfBothCodecs) {
  const CompressedLog c = compressed_log("klogz_fixture");
  ASSERT_EQ(c.spans.size(), 7u);
  EXPECT_EQ(c.bytes[c.spans[1].begin + 16 + klog::kImageCodecByte], uint8_t(klog::ImageCodec::kZstd));
  EXPECT_EQ(c.bytes[c.spans[3].begin + 16 + klog::kImageCodecByte], uint8_t(klog::ImageCodec::kZstd));
  EXPECT_EQ(c.bytes[c.spans[5].begin + 16 + klog::kImageCodecByte], uint8_t(klog::ImageCodec::kLz4));
  EXPECT_EQ(c.bytes[c.spans[1].begin + 16 + klog::kImageFilterByte], uint8_t(klog::ImageFilter::kMedPlanar));
  auto r = KlogReader::from_memory(c.bytes.data(), c.bytes.size(), "c.klog", {});
  const auto recs = read_all(*r);
  EXPECT_TRUE(r->problems().empty());
  ASSERT_EQ(recs.size(), 7u);
  EXPECT_EQ(recs[1].image.pixels, c.images[0].pixels);
  EXPECT_EQ(recs[3].image.pixels, c.images[1].pixels);
  EXPECT_EQ(recs[5].image.pixels, c.images[2].pixels);
}

TEST(KlogCompression, DamagedCompressedStreamIsReportedAndSkipped) {
  const CompressedLog c = compressed_log("klogz_damage");
  // Flip bytes inside each compressed stream and reseal the CRC, as a writer
  // bug or a crafted file would: the CRC passes, the decoder must refuse.
  for (size_t which : {size_t{1}, size_t{3}, size_t{5}}) {
    const RecordSpan& s = c.spans[which];
    const size_t px = s.begin + klog::kRecordHeaderBytes + klog::kImageHeaderBytes;
    int refused = 0, trials = 0;
    for (size_t at = px; at < s.end; at += std::max<size_t>(1, (s.end - px) / 40)) {
      for (uint8_t mask : {uint8_t{0x01}, uint8_t{0x80}, uint8_t{0xff}}) {
        std::vector<uint8_t> b = c.bytes;
        b[at] ^= mask;
        reseal(b, s);
        auto r = KlogReader::from_memory(b.data(), b.size(), "d.klog", {});
        const auto recs = read_all(*r);
        ++trials;
        // Every other record is intact; the damaged one either decodes to
        // exactly its size (a flip the codec cannot see) or is reported.
        size_t others = 0;
        for (const auto& rec : recs)
          if (rec.offset != s.begin) ++others;
        EXPECT_EQ(others, c.spans.size() - 1);
        if (recs.size() == c.spans.size() - 1) {
          ++refused;
          ASSERT_EQ(r->problems().size(), 1u);
          EXPECT_EQ(r->problems()[0].kind, "bad-payload");
          EXPECT_EQ(r->problems()[0].where, "d.klog@" + std::to_string(s.begin));
        } else {
          EXPECT_TRUE(r->problems().empty());
          for (const auto& rec : recs)
            if (rec.offset == s.begin) {
              EXPECT_EQ(rec.image.pixels.size(), c.images[which / 2].pixels.size());
            }
        }
      }
    }
    // zstd frames carry a checksum of their content, so every flip is
    // caught; an lz4 block has none, and a flip in a literal just changes
    // pixels (the record CRC is what catches those on disk).
    if (which == 5)
      EXPECT_GT(refused, 0) << "record " << which;
    else
      EXPECT_EQ(refused, trials) << "record " << which;
  }
}

TEST(KlogCompression, BitFlipWithoutResealIsACrcErrorAndReadingResumes) {
  const CompressedLog c = compressed_log("klogz_crc");
  const RecordSpan& s = c.spans[3];
  std::vector<uint8_t> b = c.bytes;
  b[s.begin + klog::kRecordHeaderBytes + klog::kImageHeaderBytes + 5] ^= 0x10;
  auto r = KlogReader::from_memory(b.data(), b.size(), "crc.klog", {});
  const auto recs = read_all(*r);
  EXPECT_EQ(recs.size(), c.spans.size() - 1);
  ASSERT_EQ(r->problems().size(), 1u);
  EXPECT_EQ(r->problems()[0].kind, "bad-crc");
  EXPECT_EQ(r->problems()[0].where, "crc.klog@" + std::to_string(s.begin));
}

TEST(KlogCompression, TruncationInsideACompressedRecordKeepsEverythingBefore) {
  const CompressedLog c = compressed_log("klogz_cut");
  for (size_t which : {size_t{1}, size_t{3}, size_t{5}}) {
    const RecordSpan& s = c.spans[which];
    for (size_t cut : {s.begin + 20, s.begin + 60, (s.begin + s.end) / 2, s.end - 1}) {
      auto r = KlogReader::from_memory(c.bytes.data(), cut, "t.klog", {});
      const auto recs = read_all(*r);
      EXPECT_EQ(recs.size(), which);
      ASSERT_EQ(r->problems().size(), 1u);
      EXPECT_EQ(r->problems()[0].kind, "truncated");
      EXPECT_EQ(r->problems()[0].where, "t.klog@" + std::to_string(s.begin));
    }
  }
}

// A CRC-valid image record with the given header fields and pixel section.
struct OneImage {
  std::vector<uint8_t> bytes;
  uint64_t at = 0;  // the image record's offset
};

OneImage one_image_log(uint32_t w, uint32_t h, PixelFormat f, klog::ImageCodec codec,
                       klog::ImageFilter filter, const std::string& pixels) {
  uint64_t at = 0;
  uint64_t* record_at = &at;
  const std::string path = temp_dir("klogz_one") + "/h.klog";
  {
    KlogWriter wr;
    wr.open(path, fixture_rig());
  }
  auto bytes = read_bytes(path);
  *record_at = bytes.size();
  std::string p;
  klog::encode_image_header(1, 2, 3, 4, static_cast<int>(w), static_cast<int>(h), f, p, codec, filter);
  p += pixels;
  std::string rec;
  klog::ByteWriter bw(rec);
  bw.u32(klog::kSyncMarker);
  bw.u16(2);
  bw.u16(0);
  bw.u32(static_cast<uint32_t>(p.size()));
  bw.u32(klog::record_crc(2, 0, static_cast<uint32_t>(p.size()), reinterpret_cast<const uint8_t*>(p.data())));
  rec += p;
  bytes.insert(bytes.end(), rec.begin(), rec.end());
  std::string imu;
  klog::encode_imu(fixture_imu(9), imu);
  std::string r2;
  klog::ByteWriter b2(r2);
  b2.u32(klog::kSyncMarker);
  b2.u16(1);
  b2.u16(0);
  b2.u32(static_cast<uint32_t>(imu.size()));
  b2.u32(klog::record_crc(1, 0, static_cast<uint32_t>(imu.size()),
                          reinterpret_cast<const uint8_t*>(imu.data())));
  r2 += imu;
  bytes.insert(bytes.end(), r2.begin(), r2.end());
  return OneImage{bytes, at};
}

std::string zstd_of(const std::vector<uint8_t>& raw) {
  std::string out(ZSTD_compressBound(raw.size()), '\0');
  out.resize(ZSTD_compress(&out[0], out.size(), raw.data(), raw.size(), 1));
  return out;
}

void expect_refused(const OneImage& one, const char* needle) {
  const std::vector<uint8_t>& bytes = one.bytes;
  const uint64_t at = one.at;
  auto r = KlogReader::from_memory(bytes.data(), bytes.size(), "lie.klog", {});
  const auto recs = read_all(*r);
  ASSERT_EQ(recs.size(), 1u);
  EXPECT_EQ(recs[0].type, RecordType::kImu);  // reading resumes after the refused record
  ASSERT_EQ(r->problems().size(), 1u);
  EXPECT_EQ(r->problems()[0].kind, "bad-payload");
  EXPECT_EQ(r->problems()[0].where, "lie.klog@" + std::to_string(at));
  EXPECT_NE(r->problems()[0].detail.find(needle), std::string::npos) << r->problems()[0].detail;
}

TEST(KlogCompression, SizeClaimsAreNeverTrusted) {
  // 32768 x 32768 RGB from a few bytes: refused before any buffer is sized.
  expect_refused(one_image_log(32768, 32768, PixelFormat::kRgb8, klog::ImageCodec::kZstd,
                               klog::ImageFilter::kNone, std::string(20, 'x')),
                 "64 MiB");
  // 4000 x 4000 gray (16 MB) from 40 bytes of zstd: more than zstd can produce.
  expect_refused(one_image_log(4000, 4000, PixelFormat::kGray8, klog::ImageCodec::kZstd,
                               klog::ImageFilter::kNone, std::string(40, 'x')),
                 "more than the codec can produce");
  expect_refused(one_image_log(4000, 4000, PixelFormat::kGray8, klog::ImageCodec::kLz4,
                               klog::ImageFilter::kNone, std::string(40, 'x')),
                 "more than the codec can produce");
  // A zstd frame of 2000 bytes in a 10x10 gray record: its declared size disagrees.
  const std::vector<uint8_t> big(2000, 7), small(100, 7), smaller(60, 7);
  expect_refused(one_image_log(10, 10, PixelFormat::kGray8, klog::ImageCodec::kZstd, klog::ImageFilter::kNone,
                               zstd_of(big)),
                 "declares 2000 bytes");
  // A frame that hides its size (streamed) and decodes to more than the
  // image: the decoder stops at the image's size.
  {
    ZSTD_CCtx* cc = ZSTD_createCCtx();
    ZSTD_CCtx_setParameter(cc, ZSTD_c_contentSizeFlag, 0);
    std::string out(ZSTD_compressBound(big.size()), '\0');
    out.resize(ZSTD_compress2(cc, &out[0], out.size(), big.data(), big.size()));
    ZSTD_freeCCtx(cc);
    expect_refused(
        one_image_log(10, 10, PixelFormat::kGray8, klog::ImageCodec::kZstd, klog::ImageFilter::kNone, out),
        "zstd");
  }
  // Too few bytes: the frame fills 60 of 100.
  expect_refused(one_image_log(10, 10, PixelFormat::kGray8, klog::ImageCodec::kZstd, klog::ImageFilter::kNone,
                               zstd_of(smaller)),
                 "declares 60 bytes");
  // Unknown codec and a filter on a format it does not apply to.
  expect_refused(one_image_log(10, 10, PixelFormat::kGray8, static_cast<klog::ImageCodec>(9),
                               klog::ImageFilter::kNone, zstd_of(small)),
                 "unknown image codec");
  expect_refused(one_image_log(5, 10, PixelFormat::kYuyv, klog::ImageCodec::kZstd,
                               klog::ImageFilter::kMedPlanar, zstd_of(small)),
                 "does not apply");
  // Raw with a filter is not a layout.
  expect_refused(one_image_log(10, 10, PixelFormat::kGray8, klog::ImageCodec::kRaw,
                               klog::ImageFilter::kMedPlanar, std::string(100, 'x')),
                 "raw pixels with a pre-filter");
  // The well-formed version of the same record reads.
  const auto ok = one_image_log(10, 10, PixelFormat::kGray8, klog::ImageCodec::kZstd,
                                klog::ImageFilter::kNone, zstd_of(small))
                      .bytes;
  auto r = KlogReader::from_memory(ok.data(), ok.size(), "ok.klog", {});
  const auto recs = read_all(*r);
  EXPECT_TRUE(r->problems().empty());
  ASSERT_EQ(recs.size(), 2u);
  EXPECT_EQ(recs[0].image.pixels, small);
}

TEST(KlogCompression, MutationsOfACompressedLogNeverLoseIntactRecords) {
  // The fuzz entry's invariants (no crash, no loop, rewind replays the same)
  // on deterministic mutations of the compressed fixture.
  const CompressedLog c = compressed_log("klogz_mut");
  std::mt19937 rng(4242);
  for (int k = 0; k < 600; ++k) {
    std::vector<uint8_t> b = c.bytes;
    const int flips = 1 + static_cast<int>(rng() % 4);
    for (int f = 0; f < flips; ++f) b[rng() % b.size()] ^= static_cast<uint8_t>(1u << (rng() % 8));
    if (k % 3 == 0) {
      // Reseal one record so the mutation reaches the decoder.
      reseal(b, c.spans[rng() % c.spans.size()]);
    }
    const KlogFuzzResult res = klog_fuzz_one(b.data(), b.size(), k % 2 == 0);
    (void)res;
  }
}

}  // namespace
}  // namespace kestrel::test

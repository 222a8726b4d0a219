#include "kestrel/drivers/d4xx_metadata.hpp"

#include <cstring>

namespace kestrel::drivers::d4xx {
namespace {

uint16_t u16(const uint8_t* p) { return static_cast<uint16_t>(p[0] | (p[1] << 8)); }
uint32_t u32(const uint8_t* p) {
  return static_cast<uint32_t>(p[0]) | (static_cast<uint32_t>(p[1]) << 8) |
         (static_cast<uint32_t>(p[2]) << 16) | (static_cast<uint32_t>(p[3]) << 24);
}
uint64_t u64(const uint8_t* p) {
  return static_cast<uint64_t>(u32(p)) | (static_cast<uint64_t>(u32(p + 4)) << 32);
}
void put16(uint8_t* p, uint16_t v) {
  p[0] = static_cast<uint8_t>(v);
  p[1] = static_cast<uint8_t>(v >> 8);
}
void put32(uint8_t* p, uint32_t v) {
  for (int i = 0; i < 4; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
}
void put64(uint8_t* p, uint64_t v) {
  put32(p, static_cast<uint32_t>(v));
  put32(p + 4, static_cast<uint32_t>(v >> 32));
}

constexpr uint8_t kInfoPts = 1u << 2;
constexpr uint8_t kInfoScr = 1u << 3;
constexpr uint8_t kInfoEoh = 1u << 7;

}  // namespace

uint32_t FrameMetadata::exposure_us() const {
  if (timing.present && (timing.flags & kTimingExposureValid)) return timing.exposure_time_us;
  if (control.present) return control.exposure_us;
  return 0;
}

const char* parse_status_name(ParseStatus s) {
  switch (s) {
    case ParseStatus::kOk:
      return "ok";
    case ParseStatus::kEmpty:
      return "empty buffer";
    case ParseStatus::kTruncatedRecord:
      return "record shorter than its header length";
    case ParseStatus::kBadHeaderLength:
      return "UVC header length too short for its PTS/SCR";
    case ParseStatus::kBadBlock:
      return "metadata block size < 8 or past the header";
    case ParseStatus::kBadBlockSize:
      return "metadata block too short for its fields";
    case ParseStatus::kNoD4xxBlocks:
      return "no D4xx metadata blocks";
  }
  return "?";
}

ParseStatus parse_blocks(const uint8_t* p, size_t n, FrameMetadata& out) {
  size_t at = 0;
  while (n - at >= kBlockHeaderBytes) {
    const uint32_t id = u32(p + at);
    const uint32_t size = u32(p + at + 4);
    if (size < kBlockHeaderBytes || size > n - at) return ParseStatus::kBadBlock;
    const uint8_t* b = p + at;
    switch (static_cast<BlockId>(id)) {
      case BlockId::kCaptureTiming: {
        if (size < kCaptureTimingBytes) return ParseStatus::kBadBlockSize;
        CaptureTiming& t = out.timing;
        t.present = true;
        t.version = u32(b + 8);
        t.flags = u32(b + 12);
        t.frame_counter = u32(b + 16);
        t.sensor_timestamp_us = u32(b + 20);
        t.readout_time_us = u32(b + 24);
        t.exposure_time_us = u32(b + 28);
        t.frame_interval_us = u32(b + 32);
        t.pipe_latency_us = u32(b + 36);
        break;
      }
      // Control and configuration blocks: only the fields read must be there (their sizes
      // changed between firmware versions; the kernel's D4XX page says 60 for depth control
      // now, 56 in its first version).
      case BlockId::kConfiguration: {
        if (size < 34) return ParseStatus::kBadBlockSize;
        Configuration& c = out.configuration;
        c.present = true;
        c.flags = u32(b + 12);
        c.hw_type = b[16];
        c.sku_id = b[17];
        c.format = u16(b + 22);
        c.width = u16(b + 24);
        c.height = u16(b + 26);
        c.fps = u16(b + 28);
        c.calibration_count = u16(b + 32);
        break;
      }
      case BlockId::kDepthControl: {
        if (size < 28) return ParseStatus::kBadBlockSize;
        ControlExposure& c = out.control;
        c.present = true;
        c.rgb = false;
        c.flags = u32(b + 12);
        c.exposure_us = (c.flags & kDepthControlExposureValid) ? u32(b + 20) : 0;
        c.laser_power = u32(b + 24);
        break;
      }
      case BlockId::kRgbControl: {
        if (size < 60) return ParseStatus::kBadBlockSize;
        ControlExposure& c = out.control;
        c.present = true;
        c.rgb = true;
        c.flags = u32(b + 12);
        // 100 us units; a corrupt value cannot overflow the product in 64 bits, clamp to u32.
        const uint64_t e = (c.flags & kRgbControlManualExposureValid) ? 100ull * u32(b + 56) : 0;
        c.exposure_us = e > 0xFFFFFFFFull ? 0xFFFFFFFFu : static_cast<uint32_t>(e);
        break;
      }
      default:
        ++out.unknown_blocks;
        break;
    }
    ++out.blocks;
    at += size;
  }
  // Fewer than 8 trailing bytes: padding some firmware adds; not a block.
  return ParseStatus::kOk;
}

ParseStatus parse_record(const uint8_t* p, size_t n, FrameMetadata& out, size_t& consumed) {
  consumed = 0;
  if (n < kRecordPrefixBytes + 2) return n == 0 ? ParseStatus::kEmpty : ParseStatus::kTruncatedRecord;
  FrameMetadata m;
  m.host_ns = static_cast<int64_t>(u64(p));
  m.usb_sof = u16(p + 8);
  m.header_length = p[10];
  m.header_info = p[11];
  m.records = out.records;
  out.host_ns = m.host_ns;
  out.usb_sof = m.usb_sof;
  out.header_length = m.header_length;
  out.header_info = m.header_info;
  const size_t len = m.header_length;
  if (len < 2) return ParseStatus::kBadHeaderLength;
  if (n - kRecordPrefixBytes < len) return ParseStatus::kTruncatedRecord;
  const uint8_t* h = p + kRecordPrefixBytes;
  size_t at = 2;
  m.has_pts = (m.header_info & kInfoPts) != 0;
  m.has_scr = (m.header_info & kInfoScr) != 0;
  const size_t need = at + (m.has_pts ? 4 : 0) + (m.has_scr ? 6 : 0);
  if (len < need) return ParseStatus::kBadHeaderLength;
  if (m.has_pts) {
    m.pts_us = u32(h + at);
    at += 4;
  }
  if (m.has_scr) {
    m.scr_stc = u32(h + at);
    m.scr_sof = u16(h + at + 4);
    at += 6;
  }
  consumed = kRecordPrefixBytes + len;
  const ParseStatus st = len > at ? parse_blocks(h + at, len - at, m) : ParseStatus::kNoD4xxBlocks;
  out = m;
  if (st == ParseStatus::kOk && m.blocks == 0) return ParseStatus::kNoD4xxBlocks;
  return st;
}

ParseStatus parse_metadata_buffer(const uint8_t* p, size_t n, FrameMetadata& out) {
  out = FrameMetadata{};
  if (n == 0) return ParseStatus::kEmpty;
  size_t at = 0;
  int records = 0;
  bool have_d4xx = false;
  ParseStatus first = ParseStatus::kNoD4xxBlocks;
  while (at < n) {
    FrameMetadata r;
    size_t used = 0;
    const ParseStatus st = parse_record(p + at, n - at, r, used);
    if (st != ParseStatus::kOk && st != ParseStatus::kNoD4xxBlocks) {
      if (!have_d4xx && records == 0) out = r;
      out.records = records;
      return st;
    }
    ++records;
    if (st == ParseStatus::kOk && !have_d4xx) {
      out = r;
      have_d4xx = true;
      first = ParseStatus::kOk;
    } else if (records == 1) {
      out = r;
    }
    at += used;
  }
  out.records = records;
  return first;
}

size_t encode_record(const FrameMetadata& m, const EncodeOptions& o, uint8_t* out, size_t cap) {
  size_t hlen = 2 + (o.pts ? 4 : 0) + (o.scr ? 6 : 0);
  if (o.capture_timing) hlen += kCaptureTimingBytes;
  if (o.configuration) hlen += kConfigurationBytes;
  if (o.control) hlen += o.depth_control ? kDepthControlBytes : kRgbControlBytes;
  if (hlen > kUvcHeaderMaxBytes || kRecordPrefixBytes + hlen > cap) return 0;
  std::memset(out, 0, kRecordPrefixBytes + hlen);
  put64(out, static_cast<uint64_t>(m.host_ns));
  put16(out + 8, m.usb_sof);
  uint8_t* h = out + kRecordPrefixBytes;
  h[0] = static_cast<uint8_t>(hlen);
  h[1] = static_cast<uint8_t>((m.header_info & 0x03) | kInfoEoh | (o.pts ? kInfoPts : 0) |
                              (o.scr ? kInfoScr : 0));
  size_t at = 2;
  if (o.pts) {
    put32(h + at, m.pts_us);
    at += 4;
  }
  if (o.scr) {
    put32(h + at, m.scr_stc);
    put16(h + at + 4, m.scr_sof);
    at += 6;
  }
  auto block = [&](BlockId id, size_t size) {
    uint8_t* b = h + at;
    put32(b, static_cast<uint32_t>(id));
    put32(b + 4, static_cast<uint32_t>(size));
    put32(b + 8, 1);  // version
    at += size;
    return b;
  };
  if (o.capture_timing) {
    uint8_t* b = block(BlockId::kCaptureTiming, kCaptureTimingBytes);
    const CaptureTiming& t = m.timing;
    put32(b + 12, t.flags);
    put32(b + 16, t.frame_counter);
    put32(b + 20, t.sensor_timestamp_us);
    put32(b + 24, t.readout_time_us);
    put32(b + 28, t.exposure_time_us);
    put32(b + 32, t.frame_interval_us);
    put32(b + 36, t.pipe_latency_us);
  }
  if (o.configuration) {
    uint8_t* b = block(BlockId::kConfiguration, kConfigurationBytes);
    const Configuration& c = m.configuration;
    put32(b + 12, c.flags);
    b[16] = c.hw_type;
    b[17] = c.sku_id;
    put16(b + 22, c.format);
    put16(b + 24, c.width);
    put16(b + 26, c.height);
    put16(b + 28, c.fps);
    put16(b + 32, c.calibration_count);
  }
  if (o.control) {
    const ControlExposure& c = m.control;
    if (o.depth_control) {
      uint8_t* b = block(BlockId::kDepthControl, kDepthControlBytes);
      put32(b + 12, c.flags);
      put32(b + 20, c.exposure_us);
      put32(b + 24, c.laser_power);
    } else {
      uint8_t* b = block(BlockId::kRgbControl, kRgbControlBytes);
      put32(b + 12, c.flags);
      put32(b + 56, c.exposure_us / 100);
    }
  }
  return kRecordPrefixBytes + hlen;
}

}  // namespace kestrel::drivers::d4xx

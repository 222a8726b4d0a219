#include "kestrel/drivers/usb_bridge_protocol.hpp"

#include <zlib.h>

#include <cstring>

namespace kestrel::drivers::usb_bridge {
namespace {

void put16(uint8_t* p, uint16_t v) {
  p[0] = static_cast<uint8_t>(v);
  p[1] = static_cast<uint8_t>(v >> 8);
}
void put32(uint8_t* p, uint32_t v) {
  for (int i = 0; i < 4; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
}
void put64(uint8_t* p, uint64_t v) {
  for (int i = 0; i < 8; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
}
uint16_t get16(const uint8_t* p) { return static_cast<uint16_t>(p[0] | (p[1] << 8)); }
uint32_t get32(const uint8_t* p) {
  uint32_t v = 0;
  for (int i = 3; i >= 0; --i) v = (v << 8) | p[i];
  return v;
}
uint64_t get64(const uint8_t* p) {
  uint64_t v = 0;
  for (int i = 7; i >= 0; --i) v = (v << 8) | p[i];
  return v;
}

}  // namespace

// The wire CRC is zlib's (CRC-32/ISO-HDLC: reflected 0xEDB88320, init and
// final xor 0xFFFFFFFF, the same chaining argument), so zlib computes it; the
// firmware side uses the same definition (docs/drivers/usb-imu-bridge.md).
// zlib's tables are static: no allocation on the driver thread. Nothing to
// add leaves the running value as is (zlib would answer 0 for a null buffer).
uint32_t crc32(const uint8_t* data, size_t n, uint32_t crc) {
  if (n == 0) return crc;
  return static_cast<uint32_t>(::crc32_z(crc, data, n));
}

size_t encode_packet(PacketType type, uint16_t seq, uint64_t t_tx_us, const uint8_t* payload, size_t len,
                     uint8_t* out, size_t cap) {
  if (len > kMaxPayload || cap < kHeaderBytes + len + kCrcBytes) return 0;
  out[0] = kMagic0;
  out[1] = kMagic1;
  out[2] = kVersion;
  out[3] = static_cast<uint8_t>(type);
  put16(out + 4, seq);
  put16(out + 6, static_cast<uint16_t>(len));
  put64(out + 8, t_tx_us);
  if (len > 0) std::memcpy(out + kHeaderBytes, payload, len);
  put32(out + kHeaderBytes + len, crc32(out, kHeaderBytes + len));
  return kHeaderBytes + len + kCrcBytes;
}

size_t encode_imu_payload(const ImuWireSample* s, size_t count, uint8_t* out, size_t cap) {
  const size_t len = 4 + count * kImuSampleBytes;
  if (count > kMaxImuSamplesPerPacket || cap < len) return 0;
  out[0] = static_cast<uint8_t>(count);
  out[1] = 0;
  out[2] = out[3] = 0;
  for (size_t i = 0; i < count; ++i) {
    uint8_t* p = out + 4 + i * kImuSampleBytes;
    put64(p, s[i].t_us);
    for (int k = 0; k < 3; ++k) put16(p + 8 + 2 * k, static_cast<uint16_t>(s[i].gyro[k]));
    for (int k = 0; k < 3; ++k) put16(p + 14 + 2 * k, static_cast<uint16_t>(s[i].acc[k]));
    p[20] = static_cast<uint8_t>(s[i].temp_raw);
    p[21] = s[i].flags;
    put16(p + 22, s[i].sample_seq);
  }
  return len;
}

size_t encode_strobe_payload(const StrobeWire* s, size_t count, uint8_t* out, size_t cap) {
  const size_t len = 4 + count * kStrobeBytes;
  if (count > kMaxStrobesPerPacket || cap < len) return 0;
  out[0] = static_cast<uint8_t>(count);
  out[1] = out[2] = out[3] = 0;
  for (size_t i = 0; i < count; ++i) {
    uint8_t* p = out + 4 + i * kStrobeBytes;
    put64(p, s[i].t_us);
    put32(p + 8, s[i].strobe_seq);
    put32(p + 12, s[i].duration_us);
  }
  return len;
}

size_t encode_status_payload(const StatusWire& s, uint8_t* out, size_t cap) {
  if (cap < kStatusBytes) return 0;
  std::memset(out, 0, kStatusBytes);
  put32(out, s.boot_id);
  put16(out + 4, s.fw_version);
  out[6] = s.acc_range_code;
  out[7] = s.acc_bw_code;
  out[8] = s.gyro_range_code;
  out[9] = s.gyro_bw_code;
  out[10] = s.state;
  put32(out + 12, s.i2c_errors);
  put32(out + 16, s.samples_dropped);
  put32(out + 20, s.strobes_dropped);
  put32(out + 24, s.uptime_ms);
  return kStatusBytes;
}

bool decode_imu_payload(const uint8_t* p, size_t len, ImuWireSample* out, size_t max, size_t& count) {
  count = 0;
  if (len < 4 || p[1] != 0) return false;
  const size_t n = p[0];
  if (len != 4 + n * kImuSampleBytes || n > max) return false;
  for (size_t i = 0; i < n; ++i) {
    const uint8_t* q = p + 4 + i * kImuSampleBytes;
    ImuWireSample& s = out[i];
    s.t_us = get64(q);
    for (int k = 0; k < 3; ++k) s.gyro[k] = static_cast<int16_t>(get16(q + 8 + 2 * k));
    for (int k = 0; k < 3; ++k) s.acc[k] = static_cast<int16_t>(get16(q + 14 + 2 * k));
    s.temp_raw = static_cast<int8_t>(q[20]);
    s.flags = q[21];
    s.sample_seq = get16(q + 22);
  }
  count = n;
  return true;
}

bool decode_strobe_payload(const uint8_t* p, size_t len, StrobeWire* out, size_t max, size_t& count) {
  count = 0;
  if (len < 4) return false;
  const size_t n = p[0];
  if (len != 4 + n * kStrobeBytes || n > max) return false;
  for (size_t i = 0; i < n; ++i) {
    const uint8_t* q = p + 4 + i * kStrobeBytes;
    out[i].t_us = get64(q);
    out[i].strobe_seq = get32(q + 8);
    out[i].duration_us = get32(q + 12);
  }
  count = n;
  return true;
}

bool decode_status_payload(const uint8_t* p, size_t len, StatusWire& s) {
  if (len != kStatusBytes) return false;
  s.boot_id = get32(p);
  s.fw_version = get16(p + 4);
  s.acc_range_code = p[6];
  s.acc_bw_code = p[7];
  s.gyro_range_code = p[8];
  s.gyro_bw_code = p[9];
  s.state = p[10];
  s.i2c_errors = get32(p + 12);
  s.samples_dropped = get32(p + 16);
  s.strobes_dropped = get32(p + 20);
  s.uptime_ms = get32(p + 24);
  return true;
}

// ---- StreamParser -------------------------------------------------------------

size_t StreamParser::feed(const uint8_t* data, size_t n) {
  if (start_ > 0 && end_ + n > buf_.size()) {
    std::memmove(buf_.data(), buf_.data() + start_, end_ - start_);
    end_ -= start_;
    start_ = 0;
  }
  const size_t take = n < buf_.size() - end_ ? n : buf_.size() - end_;
  std::memcpy(buf_.data() + end_, data, take);
  end_ += take;
  counters_.overflow_bytes += n - take;
  return take;
}

void StreamParser::skip(size_t n) {
  start_ += n;
  counters_.bytes_skipped += n;
}

bool StreamParser::next(Packet& out) {
  for (;;) {
    // Find the magic.
    size_t i = start_;
    while (i + 1 < end_ && !(buf_[i] == kMagic0 && buf_[i + 1] == kMagic1)) ++i;
    if (i > start_) skip(i - start_);
    if (end_ - start_ < kHeaderBytes) {
      if (start_ == end_) start_ = end_ = 0;
      return false;
    }
    const uint8_t* h = buf_.data() + start_;
    const uint16_t len = get16(h + 6);
    if (h[2] != kVersion || len > kMaxPayload || h[3] < 1 || h[3] > 3) {
      // Not a header after all (or a future version): step past this magic.
      ++counters_.bad_headers;
      skip(1);
      continue;
    }
    const size_t total = kHeaderBytes + len + kCrcBytes;
    if (end_ - start_ < total) return false;
    const uint32_t want = get32(h + kHeaderBytes + len);
    if (crc32(h, kHeaderBytes + len) != want) {
      // Resynchronise from the byte after this magic: a corrupt length must
      // not swallow the packets behind it.
      ++counters_.crc_errors;
      skip(1);
      continue;
    }
    out.header.version = h[2];
    out.header.type = static_cast<PacketType>(h[3]);
    out.header.seq = get16(h + 4);
    out.header.payload_len = len;
    out.header.t_tx_us = get64(h + 8);
    out.payload = h + kHeaderBytes;
    start_ += total;
    ++counters_.packets;
    return true;
  }
}

}  // namespace kestrel::drivers::usb_bridge

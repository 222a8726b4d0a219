// The .klog byte layout (docs/log-format.md), as constants and payload codecs.
//
// Writer, reader, tests and the fuzz target share these so that the layout is
// written down once. Everything is little-endian and encoded field by field:
// no struct is ever memcpy'd, so padding and host byte order never reach disk.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>

#include "kestrel/drivers/klog_image_codec.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::drivers::klog {

constexpr char kMagic[4] = {'K', 'L', 'O', 'G'};
// Bytes A5 4B 52 5A on disk. Chosen so that zero runs, ASCII text and the
// magic never contain it; the CRC decides whether a candidate is a record.
constexpr uint32_t kSyncMarker = 0x5A524BA5u;

constexpr size_t kFileHeaderFixedBytes = 16;  // magic, version, header_length, rig_yaml_length
constexpr size_t kFileHeaderCrcBytes = 4;
constexpr uint32_t kMaxRigYamlBytes = 1u << 20;
constexpr size_t kRecordHeaderBytes = 16;  // sync, type, flags, payload_length, crc
// No legitimate record is larger (a 4K RGB frame is 25 MB); anything bigger is
// a corrupt length and must not turn into an allocation.
constexpr uint32_t kMaxPayloadBytes = 64u << 20;

constexpr size_t kImuPayloadBytes = 76;
constexpr size_t kImageHeaderBytes = 36;  // followed by the pixels (raw or compressed, v2)
constexpr size_t kImageCodecByte = 33;    // offsets in the image header (v2; zero in v1)
constexpr size_t kImageFilterByte = 34;
constexpr size_t kGroundTruthPayloadBytes = 89;
constexpr size_t kEventHeaderBytes = 16;  // followed by text_length bytes
constexpr uint32_t kMaxImageSide = 1u << 15;

bool is_known_record_type(uint16_t type);
bool is_valid_pixel_format(uint8_t format);

// CRC32 (zlib) over type, flags, payload_length (8 bytes, little-endian) and the payload.
uint32_t record_crc(uint16_t type, uint16_t flags, uint32_t payload_length, const uint8_t* payload);

// Appends little-endian fields to `out`.
class ByteWriter {
 public:
  explicit ByteWriter(std::string& out) : out_(out) {}
  void u8(uint8_t v) { out_.push_back(static_cast<char>(v)); }
  void u16(uint16_t v) { le(v, 2); }
  void u32(uint32_t v) { le(v, 4); }
  void u64(uint64_t v) { le(v, 8); }
  void i32(int32_t v) { u32(static_cast<uint32_t>(v)); }
  void i64(int64_t v) { u64(static_cast<uint64_t>(v)); }
  void f32(float v) {
    uint32_t b;
    std::memcpy(&b, &v, 4);
    u32(b);
  }
  void f64(double v) {
    uint64_t b;
    std::memcpy(&b, &v, 8);
    u64(b);
  }
  void bytes(const void* p, size_t n) { out_.append(static_cast<const char*>(p), n); }

 private:
  void le(uint64_t v, int n) {
    char b[8];
    for (int i = 0; i < n; ++i) b[i] = static_cast<char>((v >> (8 * i)) & 0xffu);
    out_.append(b, static_cast<size_t>(n));
  }
  std::string& out_;
};

// Reads little-endian fields; callers check sizes first, reads past the end
// return 0 and clear ok().
class ByteReader {
 public:
  ByteReader(const uint8_t* p, size_t n) : p_(p), n_(n) {}
  uint8_t u8() { return static_cast<uint8_t>(le(1)); }
  uint16_t u16() { return static_cast<uint16_t>(le(2)); }
  uint32_t u32() { return static_cast<uint32_t>(le(4)); }
  uint64_t u64() { return le(8); }
  int32_t i32() { return static_cast<int32_t>(u32()); }
  int64_t i64() { return static_cast<int64_t>(u64()); }
  float f32() {
    uint32_t b = u32();
    float v;
    std::memcpy(&v, &b, 4);
    return v;
  }
  double f64() {
    uint64_t b = u64();
    double v;
    std::memcpy(&v, &b, 8);
    return v;
  }
  const uint8_t* skip(size_t n) {
    if (n > n_ - pos_) {
      ok_ = false;
      pos_ = n_;
      return nullptr;
    }
    const uint8_t* at = p_ + pos_;
    pos_ += n;
    return at;
  }
  size_t remaining() const { return n_ - pos_; }
  bool ok() const { return ok_; }

 private:
  uint64_t le(int n) {
    const uint8_t* b = skip(static_cast<size_t>(n));
    if (!b) return 0;
    uint64_t v = 0;
    for (int i = 0; i < n; ++i) v |= static_cast<uint64_t>(b[i]) << (8 * i);
    return v;
  }
  const uint8_t* p_;
  size_t n_;
  size_t pos_ = 0;
  bool ok_ = true;
};

// Payload codecs. encode_* append to `out`; decode_* return false and say why
// when the payload does not have exactly the layout of its type.
void encode_imu(const ImuSample& s, std::string& out);
void encode_image_header(int64_t t_ns, int64_t t_recv_ns, uint32_t seq, int32_t exposure_us, int width,
                         int height, PixelFormat format, std::string& out,
                         ImageCodec codec = ImageCodec::kRaw, ImageFilter filter = ImageFilter::kNone);
void encode_ground_truth(const GroundTruthPose& gt, std::string& out);
void encode_event(const Event& e, std::string& out);

bool decode_imu(const uint8_t* p, size_t n, ImuSample& s, std::string& why);
// `version` is the file's: version 1 knows only raw pixels. Compressed pixels
// are decoded with `decoder` into img.pixels, never more than the header's
// width * height * bpp, which must itself fit kMaxPayloadBytes.
bool decode_image(const uint8_t* p, size_t n, LogImage& img, std::string& why, ImageDecoder& decoder,
                  uint32_t version);
bool decode_ground_truth(const uint8_t* p, size_t n, GroundTruthPose& gt, std::string& why);
bool decode_event(const uint8_t* p, size_t n, Event& e, std::string& why);

}  // namespace kestrel::drivers::klog

// Payload codecs of the .klog format; the layout is in docs/log-format.md.
#include "kestrel/drivers/klog_format.hpp"

#include <zlib.h>

namespace kestrel::drivers::klog {

bool is_known_record_type(uint16_t type) {
  return type >= static_cast<uint16_t>(RecordType::kImu) && type <= static_cast<uint16_t>(RecordType::kRight);
}

bool is_valid_pixel_format(uint8_t format) {
  return format >= static_cast<uint8_t>(PixelFormat::kGray8) &&
         format <= static_cast<uint8_t>(PixelFormat::kDepthU16);
}

uint32_t record_crc(uint16_t type, uint16_t flags, uint32_t payload_length, const uint8_t* payload) {
  std::string h;
  h.reserve(8);
  ByteWriter w(h);
  w.u16(type);
  w.u16(flags);
  w.u32(payload_length);
  uLong crc = crc32(0L, Z_NULL, 0);
  crc = crc32(crc, reinterpret_cast<const Bytef*>(h.data()), 8);
  // zlib's length is uInt; payloads are capped at 64 MiB, far below 4 GiB.
  if (payload_length > 0) crc = crc32(crc, payload, payload_length);
  return static_cast<uint32_t>(crc);
}

void encode_imu(const ImuSample& s, std::string& out) {
  ByteWriter w(out);
  w.i64(s.t_ns);
  w.i64(s.t_recv_ns);
  w.u32(s.seq);
  w.u32(s.flags);
  for (double v : s.gyro_rps) w.f64(v);
  for (double v : s.acc_mps2) w.f64(v);
  w.f32(s.temp_c);
}

void encode_image_header(int64_t t_ns, int64_t t_recv_ns, uint32_t seq, int32_t exposure_us, int width,
                         int height, PixelFormat format, std::string& out, ImageCodec codec,
                         ImageFilter filter) {
  ByteWriter w(out);
  w.i64(t_ns);
  w.i64(t_recv_ns);
  w.u32(seq);
  w.i32(exposure_us);
  w.u32(static_cast<uint32_t>(width));
  w.u32(static_cast<uint32_t>(height));
  w.u8(static_cast<uint8_t>(format));
  w.u8(static_cast<uint8_t>(codec));
  w.u8(static_cast<uint8_t>(filter));
  w.u8(0);
}

void encode_ground_truth(const GroundTruthPose& gt, std::string& out) {
  ByteWriter w(out);
  w.i64(gt.t_ns);
  for (double v : gt.p_WB) w.f64(v);
  for (double v : gt.q_WB) w.f64(v);
  w.u8(gt.has_velocity ? 1 : 0);
  for (double v : gt.v_WB) w.f64(v);
}

void encode_event(const Event& e, std::string& out) {
  ByteWriter w(out);
  w.i64(e.t_ns);
  w.u32(static_cast<uint32_t>(e.code));
  w.u32(static_cast<uint32_t>(e.text.size()));
  w.bytes(e.text.data(), e.text.size());
}

namespace {
bool size_is(size_t n, size_t want, const char* what, std::string& why) {
  if (n == want) return true;
  why = std::string(what) + " payload is " + std::to_string(n) + " bytes, expected " + std::to_string(want);
  return false;
}
}  // namespace

bool decode_imu(const uint8_t* p, size_t n, ImuSample& s, std::string& why) {
  if (!size_is(n, kImuPayloadBytes, "IMU", why)) return false;
  ByteReader r(p, n);
  s.t_ns = r.i64();
  s.t_recv_ns = r.i64();
  s.seq = r.u32();
  s.flags = r.u32();
  for (double& v : s.gyro_rps) v = r.f64();
  for (double& v : s.acc_mps2) v = r.f64();
  s.temp_c = r.f32();
  return r.ok();
}

bool decode_image(const uint8_t* p, size_t n, LogImage& img, std::string& why, ImageDecoder& decoder,
                  uint32_t version) {
  if (n < kImageHeaderBytes) {
    why = "image payload is " + std::to_string(n) + " bytes, shorter than its " +
          std::to_string(kImageHeaderBytes) + "-byte header";
    return false;
  }
  ByteReader r(p, n);
  const int64_t t_ns = r.i64();
  const int64_t t_recv_ns = r.i64();
  const uint32_t seq = r.u32();
  const int32_t exposure_us = r.i32();
  const uint32_t width = r.u32();
  const uint32_t height = r.u32();
  const uint8_t format = r.u8();
  const uint8_t codec = r.u8();
  const uint8_t filter = r.u8();
  r.skip(1);
  if (!is_valid_pixel_format(format)) {
    why = "unknown pixel format " + std::to_string(format);
    return false;
  }
  if (width > kMaxImageSide || height > kMaxImageSide) {
    why = "image size " + std::to_string(width) + "x" + std::to_string(height) + " out of range";
    return false;
  }
  if (version < 2 && (codec != 0 || filter != 0)) {
    why = "codec byte " + std::to_string(codec) + " / filter byte " + std::to_string(filter) +
          " in a version 1 log (version 1 images are raw)";
    return false;
  }
  if (!is_valid_codec(codec) || !is_valid_filter(filter)) {
    why = "unknown image codec " + std::to_string(codec) + " or pre-filter " + std::to_string(filter);
    return false;
  }
  const uint64_t bytes =
      uint64_t{width} * height * static_cast<uint64_t>(bytes_per_pixel(static_cast<PixelFormat>(format)));
  // A raw record could not hold more; a compressed one is not allowed to
  // decode to more, whatever its few bytes claim.
  if (bytes > kMaxPayloadBytes - kImageHeaderBytes) {
    why = "image " + std::to_string(width) + "x" + std::to_string(height) + " would decode to " +
          std::to_string(bytes) + " bytes, over the 64 MiB record limit";
    return false;
  }
  const uint8_t* px = r.skip(r.remaining());
  const size_t px_bytes = n - kImageHeaderBytes;
  if (static_cast<ImageCodec>(codec) == ImageCodec::kRaw && bytes != px_bytes) {
    why = "image " + std::to_string(width) + "x" + std::to_string(height) + " needs " +
          std::to_string(bytes) + " pixel bytes, payload has " + std::to_string(px_bytes);
    return false;
  }
  if (bytes > ImageDecoder::max_decoded_bytes(static_cast<ImageCodec>(codec), px_bytes)) {
    why = std::string(codec_name(static_cast<ImageCodec>(codec))) + " image " + std::to_string(width) + "x" +
          std::to_string(height) + " claims " + std::to_string(bytes) + " bytes from " +
          std::to_string(px_bytes) + " compressed bytes, more than the codec can produce";
    return false;
  }
  img.pixels.resize(static_cast<size_t>(bytes));
  if (!decoder.decode(static_cast<ImageCodec>(codec), static_cast<ImageFilter>(filter),
                      static_cast<PixelFormat>(format), static_cast<int>(width), static_cast<int>(height), px,
                      px_bytes, img.pixels.data(), why)) {
    why = std::string(codec_name(static_cast<ImageCodec>(codec))) + " image " + std::to_string(width) + "x" +
          std::to_string(height) + ": " + why;
    return false;
  }
  img.t_ns = t_ns;
  img.t_recv_ns = t_recv_ns;
  img.seq = seq;
  img.exposure_us = exposure_us;
  img.width = static_cast<int>(width);
  img.height = static_cast<int>(height);
  img.format = static_cast<PixelFormat>(format);
  return true;
}

bool decode_ground_truth(const uint8_t* p, size_t n, GroundTruthPose& gt, std::string& why) {
  if (!size_is(n, kGroundTruthPayloadBytes, "ground-truth", why)) return false;
  ByteReader r(p, n);
  gt.t_ns = r.i64();
  for (double& v : gt.p_WB) v = r.f64();
  for (double& v : gt.q_WB) v = r.f64();
  const uint8_t has_v = r.u8();
  if (has_v > 1) {
    why = "ground-truth has_velocity byte is " + std::to_string(has_v);
    return false;
  }
  gt.has_velocity = has_v == 1;
  for (double& v : gt.v_WB) v = r.f64();
  return r.ok();
}

bool decode_event(const uint8_t* p, size_t n, Event& e, std::string& why) {
  if (n < kEventHeaderBytes) {
    why = "event payload is " + std::to_string(n) + " bytes, shorter than its header";
    return false;
  }
  ByteReader r(p, n);
  e.t_ns = r.i64();
  e.code = static_cast<EventCode>(r.u32());
  const uint32_t len = r.u32();
  if (len != r.remaining()) {
    why = "event text length " + std::to_string(len) + " but " + std::to_string(r.remaining()) +
          " bytes follow";
    return false;
  }
  const uint8_t* t = r.skip(len);
  e.text.assign(reinterpret_cast<const char*>(t), len);
  return true;
}

}  // namespace kestrel::drivers::klog

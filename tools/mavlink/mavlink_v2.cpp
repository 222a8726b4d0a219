#include "kestrel/mavlink/mavlink_v2.hpp"

#include <cstring>

namespace kestrel::mavlink {
namespace {

// Little-endian on the wire whatever the host is.
uint8_t* put_u8(uint8_t* p, uint8_t v) {
  *p = v;
  return p + 1;
}
uint8_t* put_u64(uint8_t* p, uint64_t v) {
  for (int i = 0; i < 8; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
  return p + 8;
}
uint8_t* put_f32(uint8_t* p, float f) {
  uint32_t v;
  std::memcpy(&v, &f, 4);
  for (int i = 0; i < 4; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
  return p + 4;
}

}  // namespace

// MAVLink's checksum is the 16-bit CRC-16/MCRF4XX (X.25 polynomial 0x1021, reflected, no final xor),
// which zlib does not offer (it has CRC-32 only), so it stays written out, as MAVLink specifies it.
uint16_t crc_x25_accumulate(uint8_t byte, uint16_t crc) {
  uint8_t tmp = static_cast<uint8_t>(byte ^ static_cast<uint8_t>(crc & 0xFF));
  tmp = static_cast<uint8_t>(tmp ^ static_cast<uint8_t>(tmp << 4));
  return static_cast<uint16_t>((crc >> 8) ^ (static_cast<uint16_t>(tmp) << 8) ^
                               (static_cast<uint16_t>(tmp) << 3) ^ (tmp >> 4));
}

uint16_t crc_x25(const uint8_t* data, std::size_t n, uint16_t crc) {
  for (std::size_t i = 0; i < n; ++i) crc = crc_x25_accumulate(data[i], crc);
  return crc;
}

std::size_t pack_odometry_payload(const OdometryMsg& m, uint8_t* payload) {
  uint8_t* p = payload;
  p = put_u64(p, m.time_usec);
  p = put_f32(p, m.x);
  p = put_f32(p, m.y);
  p = put_f32(p, m.z);
  for (float v : m.q) p = put_f32(p, v);
  p = put_f32(p, m.vx);
  p = put_f32(p, m.vy);
  p = put_f32(p, m.vz);
  p = put_f32(p, m.rollspeed);
  p = put_f32(p, m.pitchspeed);
  p = put_f32(p, m.yawspeed);
  for (float v : m.pose_covariance) p = put_f32(p, v);
  for (float v : m.velocity_covariance) p = put_f32(p, v);
  p = put_u8(p, m.frame_id);
  p = put_u8(p, m.child_frame_id);
  p = put_u8(p, m.reset_counter);
  p = put_u8(p, m.estimator_type);
  p = put_u8(p, static_cast<uint8_t>(m.quality));
  return static_cast<std::size_t>(p - payload);
}

std::size_t frame_v2(uint32_t msgid, uint8_t crc_extra, const uint8_t* payload, std::size_t payload_len,
                     uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out) {
  if (payload_len > kMaxPayloadBytes) payload_len = kMaxPayloadBytes;
  // v2 drops trailing zeros; the receiver zero-fills to its own length, which
  // is also what lets old and new field sets talk to each other.
  std::size_t len = payload_len;
  while (len > 1 && payload[len - 1] == 0) --len;
  uint8_t* p = out;
  p = put_u8(p, kStxV2);
  p = put_u8(p, static_cast<uint8_t>(len));
  p = put_u8(p, 0);  // incompat flags: unsigned
  p = put_u8(p, 0);  // compat flags
  p = put_u8(p, seq);
  p = put_u8(p, sysid);
  p = put_u8(p, compid);
  p = put_u8(p, static_cast<uint8_t>(msgid));
  p = put_u8(p, static_cast<uint8_t>(msgid >> 8));
  p = put_u8(p, static_cast<uint8_t>(msgid >> 16));
  std::memcpy(p, payload, len);
  p += len;
  uint16_t crc = crc_x25(out + 1, kHeaderV2Bytes - 1 + len);
  crc = crc_x25_accumulate(crc_extra, crc);
  p = put_u8(p, static_cast<uint8_t>(crc & 0xFF));
  p = put_u8(p, static_cast<uint8_t>(crc >> 8));
  return static_cast<std::size_t>(p - out);
}

std::size_t encode_odometry(const OdometryMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out) {
  uint8_t payload[kOdometryPayloadBytes];
  const std::size_t n = pack_odometry_payload(m, payload);
  return frame_v2(kMsgIdOdometry, kOdometryCrcExtra, payload, n, seq, sysid, compid, out);
}

}  // namespace kestrel::mavlink

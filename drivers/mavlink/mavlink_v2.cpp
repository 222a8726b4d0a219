#include "kestrel/drivers/mavlink/mavlink_v2.hpp"

#include <cstring>

#include "kestrel/drivers/mavlink/mavlink_signing.hpp"

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
uint8_t* put_u32(uint8_t* p, uint32_t v) {
  for (int i = 0; i < 4; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
  return p + 4;
}
uint64_t get_u64(const uint8_t* p) {
  uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v |= static_cast<uint64_t>(p[i]) << (8 * i);
  return v;
}
uint8_t* put_f32(uint8_t* p, float f) {
  uint32_t v;
  std::memcpy(&v, &f, 4);
  for (int i = 0; i < 4; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
  return p + 4;
}
uint8_t* put_u16(uint8_t* p, uint16_t v) {
  p[0] = static_cast<uint8_t>(v);
  p[1] = static_cast<uint8_t>(v >> 8);
  return p + 2;
}
uint8_t* put_i16(uint8_t* p, int16_t v) { return put_u16(p, static_cast<uint16_t>(v)); }
uint32_t get_u32(const uint8_t* p) {
  return static_cast<uint32_t>(p[0]) | static_cast<uint32_t>(p[1]) << 8 | static_cast<uint32_t>(p[2]) << 16 |
         static_cast<uint32_t>(p[3]) << 24;
}
uint16_t get_u16(const uint8_t* p) { return static_cast<uint16_t>(p[0] | p[1] << 8); }
int16_t get_i16(const uint8_t* p) { return static_cast<int16_t>(get_u16(p)); }
float get_f32(const uint8_t* p) {
  const uint32_t v = get_u32(p);
  float f;
  std::memcpy(&f, &v, 4);
  return f;
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
                     uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out, MavlinkSigning* sign) {
  if (payload_len > kMaxPayloadBytes) payload_len = kMaxPayloadBytes;
  // v2 drops trailing zeros; the receiver zero-fills to its own length, which
  // is also what lets old and new field sets talk to each other.
  std::size_t len = payload_len;
  while (len > 1 && payload[len - 1] == 0) --len;
  uint8_t* p = out;
  p = put_u8(p, kStxV2);
  p = put_u8(p, static_cast<uint8_t>(len));
  p = put_u8(p, sign != nullptr ? kIncompatSigned : 0);  // the checksum covers the flag
  p = put_u8(p, 0);                                      // compat flags
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
  const std::size_t n = static_cast<std::size_t>(p - out);
  return sign != nullptr ? sign->sign(out, n) : n;
}

std::size_t encode_odometry(const OdometryMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                            MavlinkSigning* sign) {
  uint8_t payload[kOdometryPayloadBytes];
  const std::size_t n = pack_odometry_payload(m, payload);
  return frame_v2(kMsgIdOdometry, kOdometryCrcExtra, payload, n, seq, sysid, compid, out, sign);
}

std::size_t encode_heartbeat(const HeartbeatMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                             MavlinkSigning* sign) {
  uint8_t payload[kHeartbeatPayloadBytes];
  uint8_t* p = put_u32(payload, m.custom_mode);
  p = put_u8(p, m.type);
  p = put_u8(p, m.autopilot);
  p = put_u8(p, m.base_mode);
  p = put_u8(p, m.system_status);
  put_u8(p, m.mavlink_version);
  return frame_v2(kMsgIdHeartbeat, kHeartbeatCrcExtra, payload, sizeof payload, seq, sysid, compid, out,
                  sign);
}

std::size_t encode_timesync(const TimesyncMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                            MavlinkSigning* sign) {
  uint8_t payload[kTimesyncPayloadBytes];
  uint8_t* p = put_u64(payload, static_cast<uint64_t>(m.tc1));
  p = put_u64(p, static_cast<uint64_t>(m.ts1));
  p = put_u8(p, m.target_system);
  put_u8(p, m.target_component);
  return frame_v2(kMsgIdTimesync, kTimesyncCrcExtra, payload, sizeof payload, seq, sysid, compid, out, sign);
}

HeartbeatMsg unpack_heartbeat(const uint8_t* payload) {
  HeartbeatMsg m;
  m.custom_mode = static_cast<uint32_t>(payload[0]) | static_cast<uint32_t>(payload[1]) << 8 |
                  static_cast<uint32_t>(payload[2]) << 16 | static_cast<uint32_t>(payload[3]) << 24;
  m.type = payload[4];
  m.autopilot = payload[5];
  m.base_mode = payload[6];
  m.system_status = payload[7];
  m.mavlink_version = payload[8];
  return m;
}

TimesyncMsg unpack_timesync(const uint8_t* payload) {
  TimesyncMsg m;
  m.tc1 = static_cast<int64_t>(get_u64(payload));
  m.ts1 = static_cast<int64_t>(get_u64(payload + 8));
  m.target_system = payload[16];
  m.target_component = payload[17];
  return m;
}

std::size_t encode_command_long(const CommandLongMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid,
                                uint8_t* out, MavlinkSigning* sign) {
  uint8_t payload[kCommandLongPayloadBytes];
  uint8_t* p = payload;
  for (float v : m.param) p = put_f32(p, v);
  p = put_u16(p, m.command);
  p = put_u8(p, m.target_system);
  p = put_u8(p, m.target_component);
  put_u8(p, m.confirmation);
  return frame_v2(kMsgIdCommandLong, kCommandLongCrcExtra, payload, sizeof payload, seq, sysid, compid, out,
                  sign);
}

std::size_t encode_command_ack(const CommandAckMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid,
                               uint8_t* out, MavlinkSigning* sign) {
  uint8_t payload[kCommandAckPayloadBytes];
  uint8_t* p = put_u16(payload, m.command);
  p = put_u8(p, m.result);
  p = put_u8(p, m.progress);
  p = put_u32(p, static_cast<uint32_t>(m.result_param2));
  p = put_u8(p, m.target_system);
  put_u8(p, m.target_component);
  return frame_v2(kMsgIdCommandAck, kCommandAckCrcExtra, payload, sizeof payload, seq, sysid, compid, out,
                  sign);
}

std::size_t encode_highres_imu(const HighresImuMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid,
                               uint8_t* out, MavlinkSigning* sign) {
  uint8_t payload[kHighresImuPayloadBytes];
  uint8_t* p = put_u64(payload, m.time_usec);
  for (float v : {m.xacc, m.yacc, m.zacc, m.xgyro, m.ygyro, m.zgyro, m.xmag, m.ymag, m.zmag, m.abs_pressure,
                  m.diff_pressure, m.pressure_alt, m.temperature})
    p = put_f32(p, v);
  p = put_u16(p, m.fields_updated);
  put_u8(p, m.id);
  return frame_v2(kMsgIdHighresImu, kHighresImuCrcExtra, payload, sizeof payload, seq, sysid, compid, out,
                  sign);
}

std::size_t encode_scaled_imu(const ScaledImuMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                              MavlinkSigning* sign) {
  uint8_t payload[kScaledImuPayloadBytes];
  uint8_t* p = put_u32(payload, m.time_boot_ms);
  for (int16_t v : {m.xacc, m.yacc, m.zacc, m.xgyro, m.ygyro, m.zgyro, m.xmag, m.ymag, m.zmag, m.temperature})
    p = put_i16(p, v);
  return frame_v2(kMsgIdScaledImu, kScaledImuCrcExtra, payload, sizeof payload, seq, sysid, compid, out,
                  sign);
}

std::size_t encode_raw_imu(const RawImuMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                           MavlinkSigning* sign) {
  uint8_t payload[kRawImuPayloadBytes];
  uint8_t* p = put_u64(payload, m.time_usec);
  for (int16_t v : {m.xacc, m.yacc, m.zacc, m.xgyro, m.ygyro, m.zgyro, m.xmag, m.ymag, m.zmag})
    p = put_i16(p, v);
  p = put_u8(p, m.id);
  put_i16(p, m.temperature);
  return frame_v2(kMsgIdRawImu, kRawImuCrcExtra, payload, sizeof payload, seq, sysid, compid, out, sign);
}

HighresImuMsg unpack_highres_imu(const uint8_t* payload) {
  HighresImuMsg m;
  m.time_usec = get_u64(payload);
  float* f[] = {&m.xacc, &m.yacc, &m.zacc,         &m.xgyro,         &m.ygyro,        &m.zgyro,      &m.xmag,
                &m.ymag, &m.zmag, &m.abs_pressure, &m.diff_pressure, &m.pressure_alt, &m.temperature};
  for (int i = 0; i < 13; ++i) *f[i] = get_f32(payload + 8 + 4 * i);
  m.fields_updated = get_u16(payload + 60);
  m.id = payload[62];
  return m;
}

ScaledImuMsg unpack_scaled_imu(const uint8_t* payload) {
  ScaledImuMsg m;
  m.time_boot_ms = get_u32(payload);
  int16_t* v[] = {&m.xacc,  &m.yacc, &m.zacc, &m.xgyro, &m.ygyro,
                  &m.zgyro, &m.xmag, &m.ymag, &m.zmag,  &m.temperature};
  for (int i = 0; i < 10; ++i) *v[i] = get_i16(payload + 4 + 2 * i);
  return m;
}

RawImuMsg unpack_raw_imu(const uint8_t* payload) {
  RawImuMsg m;
  m.time_usec = get_u64(payload);
  int16_t* v[] = {&m.xacc, &m.yacc, &m.zacc, &m.xgyro, &m.ygyro, &m.zgyro, &m.xmag, &m.ymag, &m.zmag};
  for (int i = 0; i < 9; ++i) *v[i] = get_i16(payload + 8 + 2 * i);
  m.id = payload[26];
  m.temperature = get_i16(payload + 27);
  return m;
}

CommandLongMsg unpack_command_long(const uint8_t* payload) {
  CommandLongMsg m;
  for (int i = 0; i < 7; ++i) m.param[i] = get_f32(payload + 4 * i);
  m.command = get_u16(payload + 28);
  m.target_system = payload[30];
  m.target_component = payload[31];
  m.confirmation = payload[32];
  return m;
}

CommandAckMsg unpack_command_ack(const uint8_t* payload) {
  CommandAckMsg m;
  m.command = get_u16(payload);
  m.result = payload[2];
  m.progress = payload[3];
  m.result_param2 = static_cast<int32_t>(get_u32(payload + 4));
  m.target_system = payload[8];
  m.target_component = payload[9];
  return m;
}

bool message_spec(uint32_t msgid, uint8_t* crc_extra, std::size_t* payload_len) {
  switch (msgid) {
    case kMsgIdHeartbeat:
      *crc_extra = kHeartbeatCrcExtra, *payload_len = kHeartbeatPayloadBytes;
      return true;
    case kMsgIdTimesync:
      *crc_extra = kTimesyncCrcExtra, *payload_len = kTimesyncPayloadBytes;
      return true;
    case kMsgIdOdometry:
      *crc_extra = kOdometryCrcExtra, *payload_len = kOdometryPayloadBytes;
      return true;
    case kMsgIdHighresImu:
      *crc_extra = kHighresImuCrcExtra, *payload_len = kHighresImuPayloadBytes;
      return true;
    case kMsgIdScaledImu:
      *crc_extra = kScaledImuCrcExtra, *payload_len = kScaledImuPayloadBytes;
      return true;
    case kMsgIdRawImu:
      *crc_extra = kRawImuCrcExtra, *payload_len = kRawImuPayloadBytes;
      return true;
    case kMsgIdCommandLong:
      *crc_extra = kCommandLongCrcExtra, *payload_len = kCommandLongPayloadBytes;
      return true;
    case kMsgIdCommandAck:
      *crc_extra = kCommandAckCrcExtra, *payload_len = kCommandAckPayloadBytes;
      return true;
    default:
      return false;
  }
}

}  // namespace kestrel::mavlink

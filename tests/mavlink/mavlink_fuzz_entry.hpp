// The one entry point shared by the libFuzzer target and the unit-suite
// mutation test: any bytes through the decoder; every frame it hands out
// must be a frame this build knows, re-encodable to a frame that decodes the same.
// The same bytes then go through a decoder with signing on: what it hands out
// is a subset of the above, all signed, and every checked frame is accounted
// for by exactly one outcome of the signature check.
#pragma once

#include <cstdint>
#include <cstdlib>
#include <cstring>

#include "kestrel/drivers/mavlink/mavlink_decoder.hpp"

namespace kestrel::test {

// The key and the wall clock the signed fuzz pass and its seeds use (fixed, so a finding replays).
inline mavlink::SigningKey fuzz_signing_key() {
  mavlink::SigningKey k;
  for (std::size_t i = 0; i < k.bytes.size(); ++i) k.bytes[i] = static_cast<uint8_t>(0xA5 ^ (13 * i));
  return k;
}
inline int64_t fuzz_signing_clock() { return 1'750'000'000'000'000'000; }

inline uint64_t mavlink_fuzz_one(const uint8_t* data, std::size_t size) {
  mavlink::MavlinkDecoder d;
  uint64_t frames = 0;
  // Fed in two unequal pieces: a frame split across reads must not matter.
  const std::size_t cut = size / 3;
  auto check = [&](const mavlink::MavlinkFrame& f) {
    uint8_t crc_extra = 0;
    std::size_t len = 0;
    if (!mavlink::message_spec(f.msgid, &crc_extra, &len)) std::abort();
    if (f.payload_len > mavlink::kMaxPayloadBytes) std::abort();
    for (std::size_t i = len; i < mavlink::kMaxPayloadBytes; ++i)
      if (f.payload[i] != 0) std::abort();  // zero-extended past the message
    // Re-framed, it decodes to the same payload.
    uint8_t again[mavlink::kMaxFrameBytes];
    const std::size_t n =
        mavlink::frame_v2(f.msgid, crc_extra, f.payload, len, f.seq, f.sysid, f.compid, again);
    mavlink::MavlinkDecoder d2;
    int got = 0;
    d2.feed(again, n, [&](const mavlink::MavlinkFrame& g) {
      if (g.msgid != f.msgid || std::memcmp(g.payload, f.payload, sizeof g.payload) != 0) std::abort();
      ++got;
    });
    if (got != 1) std::abort();
    // The messages the link acts on are unpacked as the link does; every
    // payload byte is a field, so packing them again gives the same payload.
    uint8_t repacked[mavlink::kMaxFrameBytes];
    std::size_t rn = 0;
    if (f.msgid == mavlink::kMsgIdHeartbeat) {
      rn =
          mavlink::encode_heartbeat(mavlink::unpack_heartbeat(f.payload), f.seq, f.sysid, f.compid, repacked);
    } else if (f.msgid == mavlink::kMsgIdTimesync) {
      rn = mavlink::encode_timesync(mavlink::unpack_timesync(f.payload), f.seq, f.sysid, f.compid, repacked);
    } else if (f.msgid == mavlink::kMsgIdHighresImu) {
      rn = mavlink::encode_highres_imu(mavlink::unpack_highres_imu(f.payload), f.seq, f.sysid, f.compid,
                                       repacked);
    } else if (f.msgid == mavlink::kMsgIdScaledImu) {
      rn = mavlink::encode_scaled_imu(mavlink::unpack_scaled_imu(f.payload), f.seq, f.sysid, f.compid,
                                      repacked);
    } else if (f.msgid == mavlink::kMsgIdRawImu) {
      rn = mavlink::encode_raw_imu(mavlink::unpack_raw_imu(f.payload), f.seq, f.sysid, f.compid, repacked);
    } else if (f.msgid == mavlink::kMsgIdCommandLong) {
      rn = mavlink::encode_command_long(mavlink::unpack_command_long(f.payload), f.seq, f.sysid, f.compid,
                                        repacked);
    } else if (f.msgid == mavlink::kMsgIdCommandAck) {
      rn = mavlink::encode_command_ack(mavlink::unpack_command_ack(f.payload), f.seq, f.sysid, f.compid,
                                       repacked);
    }
    if (rn > 0) {
      mavlink::MavlinkDecoder d3;
      int same = 0;
      d3.feed(repacked, rn, [&](const mavlink::MavlinkFrame& g) {
        if (std::memcmp(g.payload, f.payload, sizeof g.payload) != 0) std::abort();
        ++same;
      });
      if (same != 1) std::abort();
    }
    ++frames;
  };
  d.feed(data, cut, check);
  d.feed(data + cut, size - cut, check);
  // Every frame costs at least its header and checksum.
  if (frames > size / (mavlink::kHeaderV2Bytes + mavlink::kChecksumBytes)) std::abort();

  // Signing on: same bytes, same framing, only verified frames out.
  mavlink::MavlinkSigning signing(fuzz_signing_key(), 0, &fuzz_signing_clock);
  mavlink::MavlinkDecoder ds;
  ds.set_signing(&signing);
  uint64_t verified = 0;
  auto check_signed = [&](const mavlink::MavlinkFrame& f) {
    if (!f.is_signed) std::abort();
    ++verified;
  };
  ds.feed(data, cut, check_signed);
  ds.feed(data + cut, size - cut, check_signed);
  const mavlink::SigningStats& st = signing.stats();
  if (verified > frames || verified != st.accepted) std::abort();
  if (ds.stats().frames + ds.stats().unauthenticated != frames) std::abort();
  if (st.accepted + st.unsigned_rejected + st.bad_signature + st.replayed + st.too_old != frames)
    std::abort();
  return frames;
}

}  // namespace kestrel::test

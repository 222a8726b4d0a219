// The one entry point shared by the libFuzzer target and the unit-suite
// mutation test: any bytes through the decoder; every frame it hands out
// must be a frame this build knows, re-encodable to a frame that decodes the same.
#pragma once

#include <cstdint>
#include <cstdlib>
#include <cstring>

#include "kestrel/drivers/mavlink/mavlink_decoder.hpp"

namespace kestrel::test {

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
    const std::size_t n = mavlink::frame_v2(f.msgid, crc_extra, f.payload, len, f.seq, f.sysid, f.compid, again);
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
      rn = mavlink::encode_heartbeat(mavlink::unpack_heartbeat(f.payload), f.seq, f.sysid, f.compid, repacked);
    } else if (f.msgid == mavlink::kMsgIdTimesync) {
      rn = mavlink::encode_timesync(mavlink::unpack_timesync(f.payload), f.seq, f.sysid, f.compid, repacked);
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
  return frames;
}

}  // namespace kestrel::test

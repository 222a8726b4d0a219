// Any byte stream from the USB IMU bridge (drivers/imu usb_bridge_protocol):
// the framer fed in uneven pieces as bulk transfers split it, then every
// packet's payload through its decoder. Invariants: the parser never stalls
// (a drained parser takes more bytes), a packet it hands out re-frames to the
// same packet, decoded counts stay within what the caller can take.
// Seeds: packets of each type as the fake bridge encodes them.
#include <cstring>

#include "fuzz_target.hpp"
#include "kestrel/drivers/usb_bridge_protocol.hpp"

namespace ub = kestrel::drivers::usb_bridge;

namespace {

void check_packet(const ub::StreamParser::Packet& pk) {
  const ub::Header& h = pk.header;
  if (h.payload_len > ub::kMaxPayload || h.version != ub::kVersion) std::abort();
  uint8_t again[ub::kMaxPacketBytes];
  const size_t n =
      ub::encode_packet(h.type, h.seq, h.t_tx_us, pk.payload, h.payload_len, again, sizeof again);
  if (n != ub::kHeaderBytes + h.payload_len + ub::kCrcBytes) std::abort();
  ub::StreamParser p2;
  ub::StreamParser::Packet q;
  if (p2.feed(again, n) != n || !p2.next(q)) std::abort();
  if (q.header.seq != h.seq || q.header.payload_len != h.payload_len ||
      std::memcmp(q.payload, pk.payload, h.payload_len) != 0)
    std::abort();
  size_t count = 0;
  switch (h.type) {
    case ub::PacketType::kImu: {
      ub::ImuWireSample s[ub::kMaxImuSamplesPerPacket];
      if (ub::decode_imu_payload(pk.payload, h.payload_len, s, ub::kMaxImuSamplesPerPacket, count) &&
          count > ub::kMaxImuSamplesPerPacket)
        std::abort();
      break;
    }
    case ub::PacketType::kStrobe: {
      ub::StrobeWire s[ub::kMaxStrobesPerPacket];
      if (ub::decode_strobe_payload(pk.payload, h.payload_len, s, ub::kMaxStrobesPerPacket, count) &&
          count > ub::kMaxStrobesPerPacket)
        std::abort();
      break;
    }
    case ub::PacketType::kStatus: {
      ub::StatusWire st;
      ub::decode_status_payload(pk.payload, h.payload_len, st);
      break;
    }
    default:
      break;  // an unknown type is the driver's to count
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  ub::StreamParser parser;
  ub::StreamParser::Packet pk;
  size_t at = 0;
  size_t piece = 1;
  while (at < size) {
    // Pieces of 1, 2, 4 ... 4096 bytes, cycling: small splits and large merges.
    const size_t n = std::min(piece, size - at);
    size_t taken = 0;
    while (taken < n) {
      const size_t t = parser.feed(data + at + taken, n - taken);
      while (parser.next(pk)) check_packet(pk);
      if (t == 0 && parser.buffered() >= ub::StreamParser::kBufferBytes) std::abort();  // stalled
      taken += t;
    }
    at += n;
    piece = piece >= 4096 ? 1 : piece * 2;
  }
  while (parser.next(pk)) check_packet(pk);
  const auto& c = parser.counters();
  if (c.packets > size / (ub::kHeaderBytes + ub::kCrcBytes)) std::abort();  // packets from nowhere
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  uint8_t payload[ub::kMaxPayload];
  uint8_t packet[ub::kMaxPacketBytes];
  std::string imu, mixed;
  ub::ImuWireSample s[5];
  for (int i = 0; i < 5; ++i) {
    s[i].t_us = 1000u * static_cast<unsigned>(i) + 17;
    s[i].gyro[0] = static_cast<int16_t>(-300 + i);
    s[i].acc[2] = 1024;
    s[i].flags = static_cast<uint8_t>(i == 0 ? ub::kBridgeAccFresh : 0);
    s[i].sample_seq = static_cast<uint16_t>(i);
  }
  uint16_t seq = 0;
  auto add = [&](std::string& out, ub::PacketType type, size_t len) {
    const size_t n = ub::encode_packet(type, seq, 1000u * seq, payload, len, packet, sizeof packet);
    ++seq;
    out.append(reinterpret_cast<const char*>(packet), n);
  };
  for (int k = 0; k < 3; ++k)
    add(imu, ub::PacketType::kImu, ub::encode_imu_payload(s, 5, payload, sizeof payload));
  mixed = imu;
  ub::StrobeWire w{0x0102030405060708ull, 7, 4000};
  add(mixed, ub::PacketType::kStrobe, ub::encode_strobe_payload(&w, 1, payload, sizeof payload));
  ub::StatusWire st;
  st.boot_id = 99;
  add(mixed, ub::PacketType::kStatus, ub::encode_status_payload(st, payload, sizeof payload));
  write_file(dir + "/imu.bin", imu);
  write_file(dir + "/mixed.bin", mixed);
  return 2;
}

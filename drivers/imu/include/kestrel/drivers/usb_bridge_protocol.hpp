// The USB IMU bridge wire protocol (version 1): framed, sequence-numbered,
// CRC-32-checked packets over a bulk IN endpoint. The normative text for
// firmware authors is docs/drivers/usb-imu-bridge.md; this header is its
// host-side encoding and a byte-stream parser (pure: bytes in, packets out).
//
// All multi-byte fields are little endian. Packet:
//   0  'K' 'B'       magic
//   2  u8  version   (1)
//   3  u8  type      (1 imu, 2 strobe, 3 status)
//   4  u16 seq       +1 per packet of any type, wraps
//   6  u16 len       payload bytes (<= kMaxPayload)
//   8  u64 t_tx_us   bridge microsecond counter when the packet was queued
//   16 payload
//   16+len u32 crc   CRC-32 (IEEE 802.3, as zlib crc32) over bytes 0 .. 16+len-1
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>

namespace kestrel::drivers::usb_bridge {

constexpr uint8_t kMagic0 = 'K';
constexpr uint8_t kMagic1 = 'B';
constexpr uint8_t kVersion = 1;
constexpr size_t kHeaderBytes = 16;
constexpr size_t kCrcBytes = 4;
constexpr size_t kMaxPayload = 1008;
constexpr size_t kMaxPacketBytes = kHeaderBytes + kMaxPayload + kCrcBytes;  // 1028

// pid.codes test VID/PID until the bridge has its own (override in the config).
constexpr uint16_t kDefaultVid = 0x1209;
constexpr uint16_t kDefaultPid = 0x0001;
constexpr uint8_t kDefaultEndpointIn = 0x81;

enum class PacketType : uint8_t { kImu = 1, kStrobe = 2, kStatus = 3 };

struct Header {
  uint8_t version = kVersion;
  PacketType type = PacketType::kImu;
  uint16_t seq = 0;
  uint16_t payload_len = 0;
  uint64_t t_tx_us = 0;
};

// IMU payload: u8 count, u8 format (0 = BMX055 raw counts), u16 reserved,
// then `count` samples of 24 bytes.
constexpr size_t kImuSampleBytes = 24;
constexpr size_t kMaxImuSamplesPerPacket = (kMaxPayload - 4) / kImuSampleBytes;  // 41
enum ImuSampleFlag : uint8_t {
  kBridgeAccFresh = 1u << 0,   // a new accelerometer sample since the previous packet sample
  kBridgeOverrun = 1u << 1,    // the bridge lost samples before this one (its queue or the sensor FIFO)
  kBridgeReadError = 1u << 2,  // the I2C read failed; values repeat the previous sample
};
struct ImuWireSample {
  uint64_t t_us = 0;        // gyro data-ready edge, bridge clock
  int16_t gyro[3] = {};     // BMX055 gyro counts, sensor axes
  int16_t acc[3] = {};      // BMX055 accel counts (12-bit, sign-extended), sensor axes
  int8_t temp_raw = 0;      // accel temperature register (0.5 K/LSB, 0 = 23 degC)
  uint8_t flags = 0;        // ImuSampleFlag
  uint16_t sample_seq = 0;  // +1 per sample, wraps
};

// Strobe payload: u8 count, 3 reserved, then `count` strobes of 16 bytes.
constexpr size_t kStrobeBytes = 16;
constexpr size_t kMaxStrobesPerPacket = (kMaxPayload - 4) / kStrobeBytes;
struct StrobeWire {
  uint64_t t_us = 0;         // rising edge = start of exposure, bridge clock
  uint32_t strobe_seq = 0;   // +1 per edge
  uint32_t duration_us = 0;  // high time (exposure) if the falling edge was seen, else 0
};

// Status payload (32 bytes), at least once a second and right after boot.
constexpr size_t kStatusBytes = 32;
struct StatusWire {
  uint32_t boot_id = 0;  // random per power-up: a change means the bridge rebooted
  uint16_t fw_version = 0;
  uint8_t acc_range_code = 0;  // PMU_RANGE as programmed (bmx055_regs.hpp)
  uint8_t acc_bw_code = 0;
  uint8_t gyro_range_code = 0;
  uint8_t gyro_bw_code = 0;
  uint8_t state = 0;  // 0 init, 1 streaming, 2 sensor fault
  uint8_t reserved = 0;
  uint32_t i2c_errors = 0;
  uint32_t samples_dropped = 0;  // never sent (queue full)
  uint32_t strobes_dropped = 0;
  uint32_t uptime_ms = 0;
  uint32_t reserved2 = 0;
  uint32_t reserved3 = 0;
};

// The packet CRC (zlib's crc32, CRC-32/ISO-HDLC). `crc` continues a running
// value: crc32(b, nb, crc32(a, na)) is the CRC of a followed by b.
uint32_t crc32(const uint8_t* data, size_t n, uint32_t crc = 0);

// Encoders (the fake bridge and the docs' examples use them). Return bytes
// written, 0 if `cap` is too small or the payload too long.
size_t encode_packet(PacketType type, uint16_t seq, uint64_t t_tx_us, const uint8_t* payload, size_t len,
                     uint8_t* out, size_t cap);
size_t encode_imu_payload(const ImuWireSample* s, size_t count, uint8_t* out, size_t cap);
size_t encode_strobe_payload(const StrobeWire* s, size_t count, uint8_t* out, size_t cap);
size_t encode_status_payload(const StatusWire& s, uint8_t* out, size_t cap);

// Decoders: false when the payload length does not match its count.
bool decode_imu_payload(const uint8_t* p, size_t len, ImuWireSample* out, size_t max, size_t& count);
bool decode_strobe_payload(const uint8_t* p, size_t len, StrobeWire* out, size_t max, size_t& count);
bool decode_status_payload(const uint8_t* p, size_t len, StatusWire& out);

// Byte-stream framer: bulk transfers may split or merge packets, and a
// corrupt byte must cost one packet, not the stream. Fixed buffer, no
// allocation.
class StreamParser {
 public:
  static constexpr size_t kBufferBytes = 8192;
  struct Packet {
    Header header;
    const uint8_t* payload = nullptr;  // valid until the next feed()/next()
  };
  struct Counters {
    uint64_t packets = 0;
    uint64_t crc_errors = 0;
    uint64_t bad_headers = 0;     // wrong version or impossible length
    uint64_t bytes_skipped = 0;   // resynchronisation
    uint64_t overflow_bytes = 0;  // fed while the buffer was full (caller did not drain)
  };

  // Appends bytes; returns how many were taken.
  size_t feed(const uint8_t* data, size_t n);
  // The next complete, CRC-clean packet; false when more bytes are needed.
  bool next(Packet& out);
  const Counters& counters() const { return counters_; }
  size_t buffered() const { return end_ - start_; }
  void clear() { start_ = end_ = 0; }

 private:
  void skip(size_t n);
  std::array<uint8_t, kBufferBytes> buf_{};
  size_t start_ = 0;
  size_t end_ = 0;
  Counters counters_;
};

}  // namespace kestrel::drivers::usb_bridge

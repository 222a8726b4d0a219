// A MAVLink v2 frame decoder for what the flight controller sends us
// (TIMESYNC, HEARTBEAT): bytes in, checked frames out. Fixed memory (one
// frame buffer), no allocation, any byte sequence accepted: garbage is
// skipped up to the next start byte, a frame whose CRC (with its message's
// CRC_EXTRA) fails is dropped and the bytes after its start byte are scanned
// again, so a start byte inside a payload cannot swallow the frame after it.
// Messages this build has no CRC_EXTRA for cannot be checked: they are
// counted and scanned past byte by byte like damage (their start byte may be
// a false one). Without a signing object, signed frames are accepted with the
// signature skipped (not verified); with one (set_signing), only frames it
// verifies come out: unsigned, wrongly signed and replayed ones are dropped
// whole and counted (MavlinkSigning::stats(), and `unauthenticated` here).
// tests/mavlink fuzzes it.
#pragma once

#include <cstddef>
#include <cstdint>

#include "kestrel/drivers/mavlink/mavlink_signing.hpp"
#include "kestrel/drivers/mavlink/mavlink_v2.hpp"

namespace kestrel::mavlink {

struct MavlinkFrame {
  uint32_t msgid = 0;
  uint8_t seq = 0, sysid = 0, compid = 0;
  uint8_t payload_len = 0;  // as received (trailing zeros trimmed by the sender)
  bool is_signed = false;
  // Zero-extended to the message's full length: unpack_*() read it directly.
  uint8_t payload[kMaxPayloadBytes] = {};
};

struct MavlinkDecoderStats {
  uint64_t frames = 0;  // checked and handed out
  uint64_t bad_crc = 0;
  uint64_t unknown_msgid = 0;    // headers of messages we cannot check
  uint64_t bad_header = 0;       // unknown incompatibility flags
  uint64_t bytes_skipped = 0;    // outside any frame
  uint64_t unauthenticated = 0;  // checked frames the signing object refused (signing on)
};

class MavlinkDecoder {
 public:
  // Calls on_frame(const MavlinkFrame&) for every checked frame in `data`.
  template <class F>
  void feed(const uint8_t* data, std::size_t n, F&& on_frame) {
    for (std::size_t i = 0; i < n; ++i) {
      buf_[n_++] = data[i];
      while (scan()) on_frame(frame_);
    }
  }
  const MavlinkDecoderStats& stats() const { return stats_; }
  // Verify every frame with `s` (owned by the caller, outliving the decoder); nullptr: off.
  void set_signing(MavlinkSigning* s) { signing_ = s; }

 private:
  static constexpr std::size_t kCapacity =
      kHeaderV2Bytes + kMaxPayloadBytes + kChecksumBytes + kSignatureBlockBytes;
  // Works on the buffered bytes; true when a frame was completed into frame_.
  bool scan();
  // Drops buf_[0, from) and any bytes up to the next start byte.
  void resync(std::size_t from);

  uint8_t buf_[kCapacity] = {};
  std::size_t n_ = 0;
  MavlinkFrame frame_;
  MavlinkDecoderStats stats_;
  MavlinkSigning* signing_ = nullptr;
};

}  // namespace kestrel::mavlink

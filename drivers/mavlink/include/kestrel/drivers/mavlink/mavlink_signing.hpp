// MAVLink 2 message signing (https://mavlink.io/en/guide/message_signing.html),
// written from the specification: a signed frame has incompat flag 0x01 and 13
// more bytes after its checksum,
//   link_id (1) | timestamp (6, LE, 10 us units since 2015-01-01 00:00:00 UTC) | signature (6)
// where signature = the first 6 bytes of SHA-256(secret_key (32) | the frame
// from its start byte to the timestamp's last byte).
//
// Sending: each frame gets the next timestamp of our stream (the wall clock,
// or one more than the last one used when the clock has not moved on).
// Receiving: a frame is accepted only when its signature matches our key, its
// timestamp is newer than the last one accepted on its (sysid, compid,
// link_id) stream, and it is no more than one minute older than our own
// timestamp (which follows the newest accepted one, so a companion without a
// real-time clock still works once the autopilot has spoken). What fails is
// counted by reason and never reaches the caller.
//
// Fixed memory (a table of the last streams seen), no allocation, no lock: one
// object per link, used from one thread.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>

#include "kestrel/drivers/mavlink/mavlink_v2.hpp"

namespace kestrel::mavlink {

constexpr uint8_t kIncompatSigned = 0x01;
constexpr std::size_t kSigningKeyBytes = 32;
// 2015-01-01 00:00:00 UTC in Unix seconds.
constexpr int64_t kSigningEpochUnixS = 1'420'070'400;
// Timestamps may lag ours by this much (10 us units: one minute).
constexpr uint64_t kSigningMaxAge = 60ull * 100'000ull;

struct SigningKey {
  std::array<uint8_t, kSigningKeyBytes> bytes{};
};

// A key file holds the 32 bytes raw, or as 64 hexadecimal digits (a trailing
// newline allowed; `sha256sum` of a passphrase gives such a line, the way
// MAVProxy and QGroundControl derive the key from one). Throws
// std::runtime_error naming the file when it is missing, short or malformed.
SigningKey load_signing_key(const std::string& path);

// Unix time (CLOCK_REALTIME ns) -> signing timestamp (10 us since 2015); 0 before 2015.
uint64_t signing_timestamp_of_unix_ns(int64_t unix_ns);
int64_t realtime_ns() noexcept;

enum class SignatureCheck : uint8_t { kOk, kUnsigned, kBadSignature, kReplayed, kTooOld };
const char* to_string(SignatureCheck c);

struct SigningStats {
  uint64_t signed_sent = 0;
  uint64_t accepted = 0;
  uint64_t unsigned_rejected = 0;  // unsigned frames while signing is on
  uint64_t bad_signature = 0;      // wrong key, or altered in transit
  uint64_t replayed = 0;           // timestamp not newer than the stream's last one
  uint64_t too_old = 0;            // more than a minute behind our timestamp
  uint64_t streams_evicted = 0;    // stream table full: the least recently used forgotten
};

class MavlinkSigning {
 public:
  // clock: the wall clock in Unix ns (tests inject one).
  MavlinkSigning(const SigningKey& key, uint8_t link_id, int64_t (*clock_unix_ns)() = &realtime_ns);

  // `frame` holds a complete v2 frame of n bytes whose incompat byte has the
  // signed flag set and whose checksum covers it; appends the 13 signature
  // bytes (the buffer needs n + kSignatureBlockBytes). Returns the new length.
  std::size_t sign(uint8_t* frame, std::size_t n) noexcept;
  // A complete frame of n bytes as received (its checksum already checked).
  SignatureCheck verify(const uint8_t* frame, std::size_t n) noexcept;

  uint8_t link_id() const { return link_id_; }
  uint64_t timestamp() const { return timestamp_; }
  const SigningStats& stats() const { return stats_; }

 private:
  void signature_of(const uint8_t* frame, std::size_t n_to_timestamp, uint8_t out[6]) const noexcept;
  uint64_t now_timestamp() const noexcept;

  SigningKey key_;
  uint8_t link_id_;
  int64_t (*clock_)();
  uint64_t timestamp_ = 0;  // ours: the last one sent or the newest accepted
  SigningStats stats_;
  struct Stream {
    uint8_t sysid = 0, compid = 0, link_id = 0;
    bool used = false;
    uint64_t timestamp = 0;
    uint64_t last_use = 0;
  };
  static constexpr int kStreams = 32;
  std::array<Stream, kStreams> streams_{};
  uint64_t uses_ = 0;
};

}  // namespace kestrel::mavlink

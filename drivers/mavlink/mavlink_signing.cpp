#include "kestrel/drivers/mavlink/mavlink_signing.hpp"

#include <time.h>

#include <cerrno>
#include <cstring>
#include <fstream>
#include <iterator>
#include <stdexcept>

#include "kestrel/drivers/mavlink/mavlink_v2.hpp"
#include "kestrel/drivers/mavlink/sha256.hpp"

namespace kestrel::mavlink {
namespace {

int hex_digit(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

}  // namespace

SigningKey load_signing_key(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error(path + ": cannot open MAVLink signing key file: " + std::strerror(errno));
  const std::string s((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  SigningKey k;
  if (s.size() == kSigningKeyBytes) {
    std::memcpy(k.bytes.data(), s.data(), kSigningKeyBytes);
    return k;
  }
  std::string hex = s;
  while (!hex.empty() && (hex.back() == '\n' || hex.back() == '\r')) hex.pop_back();
  // `sha256sum` prints "<hex>  -": the digest is the first word.
  const auto space = hex.find_first_of(" \t");
  if (space != std::string::npos) hex.resize(space);
  if (hex.size() == 2 * kSigningKeyBytes) {
    bool ok = true;
    for (std::size_t i = 0; i < kSigningKeyBytes && ok; ++i) {
      const int hi = hex_digit(hex[2 * i]), lo = hex_digit(hex[2 * i + 1]);
      ok = hi >= 0 && lo >= 0;
      k.bytes[i] = static_cast<uint8_t>(hi * 16 + lo);
    }
    if (ok) return k;
  }
  throw std::runtime_error(path +
                           ": MAVLink signing key: expected 32 raw bytes or 64 hexadecimal digits, got " +
                           std::to_string(s.size()) + " bytes");
}

int64_t realtime_ns() noexcept {
  timespec ts{};
  clock_gettime(CLOCK_REALTIME, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

uint64_t signing_timestamp_of_unix_ns(int64_t unix_ns) {
  const int64_t since = unix_ns - kSigningEpochUnixS * 1'000'000'000;
  return since > 0 ? static_cast<uint64_t>(since / 10'000) : 0;
}

const char* to_string(SignatureCheck c) {
  switch (c) {
    case SignatureCheck::kOk:
      return "ok";
    case SignatureCheck::kUnsigned:
      return "unsigned";
    case SignatureCheck::kBadSignature:
      return "bad signature";
    case SignatureCheck::kReplayed:
      return "replayed timestamp";
    case SignatureCheck::kTooOld:
      return "timestamp too old";
  }
  return "?";
}

MavlinkSigning::MavlinkSigning(const SigningKey& key, uint8_t link_id, int64_t (*clock_unix_ns)())
    : key_(key), link_id_(link_id), clock_(clock_unix_ns) {}

uint64_t MavlinkSigning::now_timestamp() const noexcept { return signing_timestamp_of_unix_ns(clock_()); }

void MavlinkSigning::signature_of(const uint8_t* frame, std::size_t n_to_timestamp,
                                  uint8_t out[6]) const noexcept {
  Sha256 h;
  h.update(key_.bytes.data(), key_.bytes.size());
  h.update(frame, n_to_timestamp);
  uint8_t d[Sha256::kDigestBytes];
  h.finish(d);
  std::memcpy(out, d, 6);
}

std::size_t MavlinkSigning::sign(uint8_t* frame, std::size_t n) noexcept {
  // Monotonic per stream even when the wall clock stands still or steps back.
  const uint64_t now = now_timestamp();
  timestamp_ = now > timestamp_ ? now : timestamp_ + 1;
  uint8_t* p = frame + n;
  p[0] = link_id_;
  for (int i = 0; i < 6; ++i) p[1 + i] = static_cast<uint8_t>(timestamp_ >> (8 * i));
  signature_of(frame, n + 7, p + 7);
  ++stats_.signed_sent;
  return n + kSignatureBlockBytes;
}

SignatureCheck MavlinkSigning::verify(const uint8_t* frame, std::size_t n) noexcept {
  if (n < kHeaderV2Bytes + kChecksumBytes + kSignatureBlockBytes || (frame[2] & kIncompatSigned) == 0) {
    ++stats_.unsigned_rejected;
    return SignatureCheck::kUnsigned;
  }
  const uint8_t* sig = frame + n - kSignatureBlockBytes;
  uint8_t expect[6];
  signature_of(frame, n - 6, expect);
  // Constant time: how many bytes matched must not show in the timing.
  uint8_t diff = 0;
  for (int i = 0; i < 6; ++i) diff = static_cast<uint8_t>(diff | (expect[i] ^ sig[7 + i]));
  if (diff != 0) {
    ++stats_.bad_signature;
    return SignatureCheck::kBadSignature;
  }
  uint64_t ts = 0;
  for (int i = 0; i < 6; ++i) ts |= static_cast<uint64_t>(sig[1 + i]) << (8 * i);
  const uint8_t sysid = frame[5], compid = frame[6], link = sig[0];
  const uint64_t now = now_timestamp() > timestamp_ ? now_timestamp() : timestamp_;
  if (ts + kSigningMaxAge < now) {
    ++stats_.too_old;
    return SignatureCheck::kTooOld;
  }
  Stream* s = nullptr;
  Stream* oldest = &streams_[0];
  for (Stream& c : streams_) {
    if (c.used && c.sysid == sysid && c.compid == compid && c.link_id == link) s = &c;
    if (!c.used || (oldest->used && c.last_use < oldest->last_use)) oldest = &c;
  }
  if (s != nullptr && ts <= s->timestamp) {
    ++stats_.replayed;
    return SignatureCheck::kReplayed;
  }
  if (s == nullptr) {
    if (oldest->used) ++stats_.streams_evicted;
    s = oldest;
    *s = Stream{};
    s->used = true, s->sysid = sysid, s->compid = compid, s->link_id = link;
  }
  s->timestamp = ts;
  s->last_use = ++uses_;
  if (ts > timestamp_) timestamp_ = ts;
  ++stats_.accepted;
  return SignatureCheck::kOk;
}

}  // namespace kestrel::mavlink

// SHA-256 (FIPS 180-4) in fixed memory, for MAVLink 2 signing on the driver's
// receive thread: OpenSSL 3's one-shot SHA256() goes through EVP_Q_digest,
// which allocates a context per call, and the low-level SHA256_Init family is
// deprecated there. Checked against OpenSSL's EVP digest in tests/mavlink.
#pragma once

#include <cstddef>
#include <cstdint>

namespace kestrel::mavlink {

class Sha256 {
 public:
  static constexpr std::size_t kDigestBytes = 32;
  Sha256() { reset(); }
  void reset() noexcept;
  void update(const uint8_t* data, std::size_t n) noexcept;
  void finish(uint8_t out[kDigestBytes]) noexcept;

 private:
  void block(const uint8_t* p) noexcept;
  uint32_t h_[8]{};
  uint8_t buf_[64]{};
  std::size_t buf_n_ = 0;
  uint64_t total_bytes_ = 0;
};

}  // namespace kestrel::mavlink

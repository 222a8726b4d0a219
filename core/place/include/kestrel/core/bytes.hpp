// Little-endian byte streams with a CRC-32, for the files core serialises
// (vocabulary, map) without doing I/O itself: core turns objects into bytes
// and back, tools read and write the files. A reader never reads past the
// end: every get fails (and stays failed) instead, so a truncated or damaged
// file gives an error, never a crash.
#pragma once

#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

namespace kestrel::core {

// CRC-32 (IEEE 802.3): zlib's crc32(), chained through crc.
uint32_t crc32(const uint8_t* data, size_t n, uint32_t crc = 0);

class ByteWriter {
 public:
  explicit ByteWriter(std::vector<uint8_t>& out) : out_(out) {}
  void bytes(const void* p, size_t n) {
    const auto* b = static_cast<const uint8_t*>(p);
    out_.insert(out_.end(), b, b + n);
  }
  void u8(uint8_t v) { out_.push_back(v); }
  void u16(uint16_t v) { le(v); }
  void u32(uint32_t v) { le(v); }
  void u64(uint64_t v) { le(v); }
  void i32(int32_t v) { le(static_cast<uint32_t>(v)); }
  void i64(int64_t v) { le(static_cast<uint64_t>(v)); }
  void f32(float v) {
    uint32_t u;
    std::memcpy(&u, &v, 4);
    le(u);
  }
  void f64(double v) {
    uint64_t u;
    std::memcpy(&u, &v, 8);
    le(u);
  }
  size_t size() const { return out_.size(); }
  std::vector<uint8_t>& buffer() { return out_; }

 private:
  template <class T>
  void le(T v) {
    for (size_t i = 0; i < sizeof(T); ++i) out_.push_back(static_cast<uint8_t>(v >> (8 * i)));
  }
  std::vector<uint8_t>& out_;
};

class ByteReader {
 public:
  ByteReader(const uint8_t* data, size_t n) : p_(data), n_(n) {}
  bool ok() const { return ok_; }
  size_t offset() const { return off_; }
  size_t remaining() const { return ok_ ? n_ - off_ : 0; }
  bool bytes(void* out, size_t n) {
    if (!ok_ || n > n_ - off_) return fail();
    std::memcpy(out, p_ + off_, n);
    off_ += n;
    return true;
  }
  uint8_t u8() { return get<uint8_t>(); }
  uint16_t u16() { return get<uint16_t>(); }
  uint32_t u32() { return get<uint32_t>(); }
  uint64_t u64() { return get<uint64_t>(); }
  int32_t i32() { return static_cast<int32_t>(get<uint32_t>()); }
  int64_t i64() { return static_cast<int64_t>(get<uint64_t>()); }
  float f32() {
    const uint32_t u = get<uint32_t>();
    float v;
    std::memcpy(&v, &u, 4);
    return v;
  }
  double f64() {
    const uint64_t u = get<uint64_t>();
    double v;
    std::memcpy(&v, &u, 8);
    return v;
  }

 private:
  bool fail() {
    ok_ = false;
    return false;
  }
  template <class T>
  T get() {
    if (!ok_ || sizeof(T) > n_ - off_) {
      fail();
      return T{};
    }
    T v = 0;
    for (size_t i = 0; i < sizeof(T); ++i)
      v = static_cast<T>(v | static_cast<T>(static_cast<T>(p_[off_ + i]) << (8 * i)));
    off_ += sizeof(T);
    return v;
  }
  const uint8_t* p_;
  size_t n_;
  size_t off_ = 0;
  bool ok_ = true;
};

// A file image: magic (4 bytes), format version (u32), payload length (u64),
// payload, CRC-32 of the payload (u32). seal() writes it; open() checks it
// and returns "" with the payload's place, or what is wrong.
std::vector<uint8_t> seal(const char magic[4], uint32_t version, const std::vector<uint8_t>& payload);
std::string open_sealed(const uint8_t* data, size_t n, const char magic[4], uint32_t version,
                        const uint8_t** payload, size_t* payload_n);

}  // namespace kestrel::core

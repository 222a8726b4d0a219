#include "kestrel/core/bytes.hpp"

#include <zlib.h>

#include <algorithm>

namespace kestrel::core {

// zlib's CRC-32, the one the .klog files and the USB bridge use.
uint32_t crc32(const uint8_t* data, size_t n, uint32_t crc) {
  uLong c = crc;
  while (n > 0) {  // zlib takes uInt lengths
    const uInt chunk = static_cast<uInt>(std::min<size_t>(n, 1u << 30));
    c = ::crc32(c, data, chunk);
    data += chunk;
    n -= chunk;
  }
  return static_cast<uint32_t>(c);
}

std::vector<uint8_t> seal(const char magic[4], uint32_t version, const std::vector<uint8_t>& payload) {
  std::vector<uint8_t> out;
  ByteWriter w(out);
  w.bytes(magic, 4);
  w.u32(version);
  w.u64(payload.size());
  w.bytes(payload.data(), payload.size());
  w.u32(crc32(payload.data(), payload.size()));
  return out;
}

std::string open_sealed(const uint8_t* data, size_t n, const char magic[4], uint32_t version,
                        const uint8_t** payload, size_t* payload_n) {
  ByteReader r(data, n);
  char m[4] = {};
  if (!r.bytes(m, 4)) return "too short to be a Kestrel file (" + std::to_string(n) + " bytes)";
  if (std::memcmp(m, magic, 4) != 0)
    return std::string("not a ") + std::string(magic, 4) + " file (magic '" + std::string(m, 4) + "')";
  const uint32_t v = r.u32();
  const uint64_t len = r.u64();
  if (!r.ok()) return "truncated header";
  if (v != version)
    return "format version " + std::to_string(v) + ", this build reads version " + std::to_string(version);
  if (len > r.remaining() || r.remaining() - len < 4) {
    return "truncated: the header promises " + std::to_string(len) + " bytes of payload, the file has " +
           std::to_string(r.remaining() >= 4 ? r.remaining() - 4 : 0);
  }
  if (r.remaining() - len != 4) return "trailing bytes after the checksum";
  const uint8_t* p = data + r.offset();
  ByteReader tail(p + len, 4);
  const uint32_t stored = tail.u32();
  const uint32_t actual = crc32(p, static_cast<size_t>(len));
  if (stored != actual) return "checksum mismatch (damaged file)";
  *payload = p;
  *payload_n = static_cast<size_t>(len);
  return "";
}

}  // namespace kestrel::core

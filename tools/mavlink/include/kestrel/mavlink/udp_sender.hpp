// A non-blocking UDP datagram sender for the flight-controller link. A send
// that would block (socket buffer full, no route yet) is dropped and counted:
// a stale pose is worth less than the next one, and the caller may sit on the
// pose-output path.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

namespace kestrel::mavlink {

struct UdpSenderStats {
  uint64_t sent = 0;
  uint64_t failed = 0;  // sendto() errors, EAGAIN included
  int last_errno = 0;
};

class UdpSender {
 public:
  // "HOST:PORT" (an IPv4 address or a name resolved once, here). Throws
  // std::invalid_argument naming the endpoint when it cannot be parsed or resolved.
  explicit UdpSender(const std::string& endpoint);
  ~UdpSender();
  UdpSender(const UdpSender&) = delete;
  UdpSender& operator=(const UdpSender&) = delete;

  // sendto(..., MSG_DONTWAIT); never blocks, never allocates.
  bool send(const uint8_t* data, std::size_t n) noexcept;
  const UdpSenderStats& stats() const { return stats_; }
  const std::string& endpoint() const { return endpoint_; }

 private:
  std::string endpoint_;
  int fd_ = -1;
  alignas(8) unsigned char addr_[128] = {};  // sockaddr_storage without the header in ours
  unsigned addr_len_ = 0;
  UdpSenderStats stats_;
};

// Splits "HOST:PORT"; false when malformed (no colon, port not 1..65535).
bool parse_endpoint(const std::string& endpoint, std::string& host, uint16_t& port);

}  // namespace kestrel::mavlink

// A non-blocking UDP link to the flight controller. A send
// that would block (socket buffer full, no route yet) is dropped and counted:
// a stale pose is worth less than the next one, and the caller may sit on the
// pose-output path.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "kestrel/drivers/mavlink/link.hpp"

namespace kestrel::mavlink {

class UdpSender final : public Link {
 public:
  // "HOST:PORT" (an IPv4 address or a name resolved once, here). Throws
  // std::invalid_argument naming the endpoint when it cannot be parsed or resolved.
  explicit UdpSender(const std::string& endpoint);
  ~UdpSender() override;
  UdpSender(const UdpSender&) = delete;
  UdpSender& operator=(const UdpSender&) = delete;

  // sendto(..., MSG_DONTWAIT); never blocks, never allocates.
  bool send(const uint8_t* data, std::size_t n) noexcept override;
  // Datagrams back to our port (an autopilot or mavlink-router answers the
  // address it hears from), recv(MSG_DONTWAIT).
  std::size_t receive(uint8_t* buf, std::size_t cap) noexcept override;
  const std::string& endpoint() const override { return endpoint_; }
  int fd() const noexcept override { return fd_; }

 private:
  std::string endpoint_;
  int fd_ = -1;
  alignas(8) unsigned char addr_[128] = {};  // sockaddr_storage without the header in ours
  unsigned addr_len_ = 0;
};

// Splits "HOST:PORT"; false when malformed (no colon, port not 1..65535).
bool parse_endpoint(const std::string& endpoint, std::string& host, uint16_t& port);

}  // namespace kestrel::mavlink

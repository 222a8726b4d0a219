#include "kestrel/drivers/mavlink/udp_sender.hpp"

#include <netdb.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <stdexcept>

namespace kestrel::mavlink {

bool parse_endpoint(const std::string& endpoint, std::string& host, uint16_t& port) {
  const auto colon = endpoint.rfind(':');
  if (colon == std::string::npos || colon == 0 || colon + 1 >= endpoint.size()) return false;
  host = endpoint.substr(0, colon);
  const std::string p = endpoint.substr(colon + 1);
  if (p.find_first_not_of("0123456789") != std::string::npos || p.size() > 5) return false;
  const long v = std::strtol(p.c_str(), nullptr, 10);
  if (v < 1 || v > 65535) return false;
  port = static_cast<uint16_t>(v);
  return true;
}

UdpSender::UdpSender(const std::string& endpoint) : endpoint_(endpoint) {
  std::string host;
  uint16_t port = 0;
  if (!parse_endpoint(endpoint, host, port)) {
    throw std::invalid_argument("MAVLink endpoint '" + endpoint +
                                "': expected HOST:PORT with PORT in 1..65535");
  }
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_DGRAM;
  addrinfo* res = nullptr;
  const int rc = getaddrinfo(host.c_str(), std::to_string(port).c_str(), &hints, &res);
  if (rc != 0 || res == nullptr) {
    throw std::invalid_argument("MAVLink endpoint '" + endpoint + "': cannot resolve '" + host +
                                "': " + gai_strerror(rc));
  }
  fd_ = ::socket(res->ai_family, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (fd_ < 0 || res->ai_addrlen > sizeof addr_) {
    const int e = errno;
    freeaddrinfo(res);
    throw std::invalid_argument("MAVLink endpoint '" + endpoint + "': socket: " + std::strerror(e));
  }
  std::memcpy(addr_, res->ai_addr, res->ai_addrlen);
  addr_len_ = static_cast<unsigned>(res->ai_addrlen);
  freeaddrinfo(res);
}

UdpSender::~UdpSender() {
  if (fd_ >= 0) ::close(fd_);
}

bool UdpSender::send(const uint8_t* data, std::size_t n) noexcept {
  const ssize_t r = ::sendto(fd_, data, n, MSG_DONTWAIT | MSG_NOSIGNAL,
                             reinterpret_cast<const sockaddr*>(addr_), static_cast<socklen_t>(addr_len_));
  if (r == static_cast<ssize_t>(n)) {
    ++stats_.sent;
    return true;
  }
  ++stats_.failed;
  stats_.last_errno = r < 0 ? errno : EMSGSIZE;
  return false;
}

}  // namespace kestrel::mavlink

namespace kestrel::mavlink {

std::size_t UdpSender::receive(uint8_t* buf, std::size_t cap) noexcept {
  const ssize_t r = ::recv(fd_, buf, cap, MSG_DONTWAIT);
  if (r <= 0) return 0;
  stats_.bytes_received += static_cast<uint64_t>(r);
  return static_cast<std::size_t>(r);
}

}  // namespace kestrel::mavlink

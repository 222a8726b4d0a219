// A byte link to the flight controller (UDP datagrams or a serial port):
// non-blocking both ways, never allocates after construction. A frame that
// cannot go out now is dropped and counted: the next pose replaces it.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

namespace kestrel::mavlink {

struct LinkStats {
  uint64_t sent = 0;
  uint64_t failed = 0;  // frames not sent (EAGAIN, no route, serial buffer full)
  uint64_t bytes_received = 0;
  int last_errno = 0;
};
using UdpSenderStats = LinkStats;

class Link {
 public:
  virtual ~Link() = default;
  // One whole frame, or nothing (counted in stats().failed).
  virtual bool send(const uint8_t* data, std::size_t n) noexcept = 0;
  // Whatever arrived, up to cap bytes; 0 when nothing did.
  virtual std::size_t receive(uint8_t* buf, std::size_t cap) noexcept = 0;
  virtual const std::string& endpoint() const = 0;
  // The descriptor a reader may block on (poll) for the next bytes; -1 when there is none.
  virtual int fd() const noexcept { return -1; }
  const LinkStats& stats() const { return stats_; }

 protected:
  LinkStats stats_;
};

}  // namespace kestrel::mavlink

// A serial port to the flight controller (most companion computers reach the
// autopilot's TELEM port over a UART): raw 8N1, no flow control, the baud
// from the config. Non-blocking: a frame goes into a fixed outgoing buffer
// whole or not at all (a half-written frame would corrupt the stream), and
// the buffer drains as the UART takes it; when it is full the frame is
// dropped and counted. ODOMETRY is ~240 bytes: 30 Hz needs > 72 kbit/s of
// the line, so use 460800 or 921600 baud (docs/px4.md).
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "kestrel/drivers/mavlink/link.hpp"

namespace kestrel::mavlink {

class SerialLink final : public Link {
 public:
  // Throws std::invalid_argument naming the device when it cannot be opened
  // or configured, or the baud is not one termios offers (the list is in
  // the message).
  SerialLink(const std::string& device, int baud);
  ~SerialLink() override;
  SerialLink(const SerialLink&) = delete;
  SerialLink& operator=(const SerialLink&) = delete;

  bool send(const uint8_t* data, std::size_t n) noexcept override;
  std::size_t receive(uint8_t* buf, std::size_t cap) noexcept override;
  const std::string& endpoint() const override { return endpoint_; }
  int fd() const noexcept override { return fd_; }
  std::size_t queued_bytes() const { return out_n_; }

 private:
  void drain() noexcept;

  std::string endpoint_;
  int fd_ = -1;
  static constexpr std::size_t kOutBytes = 4096;
  uint8_t out_[kOutBytes] = {};
  std::size_t out_n_ = 0;
};

// "DEVICE[:BAUD]" -> device and baud (default_baud when absent); false when
// the baud is not a positive number.
bool parse_serial_spec(const std::string& spec, int default_baud, std::string& device, int& baud);
// The bauds SerialLink accepts, "9600, 19200, ..." (for messages).
std::string serial_bauds();

}  // namespace kestrel::mavlink

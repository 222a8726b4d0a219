#include "kestrel/drivers/mavlink/serial_link.hpp"

#include <fcntl.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <stdexcept>

namespace kestrel::mavlink {
namespace {

struct Baud {
  int bps;
  speed_t code;
};
constexpr Baud kBauds[] = {{9600, B9600},       {19200, B19200},     {38400, B38400},     {57600, B57600},
                           {115200, B115200},   {230400, B230400},   {460800, B460800},   {500000, B500000},
                           {576000, B576000},   {921600, B921600},   {1000000, B1000000}, {1152000, B1152000},
                           {1500000, B1500000}, {2000000, B2000000}, {2500000, B2500000}, {3000000, B3000000},
                           {3500000, B3500000}, {4000000, B4000000}};

}  // namespace

std::string serial_bauds() {
  std::string s;
  for (const Baud& b : kBauds) s += (s.empty() ? "" : ", ") + std::to_string(b.bps);
  return s;
}

bool parse_serial_spec(const std::string& spec, int default_baud, std::string& device, int& baud) {
  const auto colon = spec.rfind(':');
  if (colon == std::string::npos) {
    device = spec;
    baud = default_baud;
    return !device.empty();
  }
  device = spec.substr(0, colon);
  const std::string b = spec.substr(colon + 1);
  if (device.empty() || b.empty() || b.size() > 8 || b.find_first_not_of("0123456789") != std::string::npos)
    return false;
  baud = std::stoi(b);
  return baud > 0;
}

SerialLink::SerialLink(const std::string& device, int baud) : endpoint_(device + ":" + std::to_string(baud)) {
  speed_t code = 0;
  bool known = false;
  for (const Baud& b : kBauds)
    if (b.bps == baud) code = b.code, known = true;
  if (!known) {
    throw std::invalid_argument("MAVLink serial " + device + ": baud " + std::to_string(baud) +
                                " not supported (expected one of: " + serial_bauds() + ")");
  }
  fd_ = ::open(device.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (fd_ < 0) {
    throw std::invalid_argument("MAVLink serial " + device + ": cannot open: " + std::strerror(errno) +
                                (errno == EACCES ? " (add the user to the dialout group)" : ""));
  }
  termios t{};
  if (::tcgetattr(fd_, &t) != 0) {
    const int e = errno;
    ::close(fd_);
    throw std::invalid_argument("MAVLink serial " + device + ": not a terminal device: " + std::strerror(e));
  }
  // Raw bytes, 8N1, no flow control, reads return at once.
  ::cfmakeraw(&t);
  t.c_cflag |= CLOCAL | CREAD;
  t.c_cflag &= ~(CSTOPB | PARENB | CRTSCTS);
  t.c_cc[VMIN] = 0;
  t.c_cc[VTIME] = 0;
  if (::cfsetispeed(&t, code) != 0 || ::cfsetospeed(&t, code) != 0 || ::tcsetattr(fd_, TCSANOW, &t) != 0) {
    const int e = errno;
    ::close(fd_);
    throw std::invalid_argument("MAVLink serial " + device + ": cannot set " + std::to_string(baud) +
                                " baud 8N1: " + std::strerror(e));
  }
  ::tcflush(fd_, TCIOFLUSH);
}

SerialLink::~SerialLink() {
  if (fd_ >= 0) ::close(fd_);
}

void SerialLink::drain() noexcept {
  while (out_n_ > 0) {
    const ssize_t w = ::write(fd_, out_, out_n_);
    if (w <= 0) {
      if (w < 0 && errno != EAGAIN && errno != EINTR) stats_.last_errno = errno;
      return;
    }
    std::memmove(out_, out_ + w, out_n_ - static_cast<std::size_t>(w));
    out_n_ -= static_cast<std::size_t>(w);
  }
}

bool SerialLink::send(const uint8_t* data, std::size_t n) noexcept {
  drain();
  if (n > kOutBytes - out_n_) {
    ++stats_.failed;
    stats_.last_errno = EAGAIN;
    return false;
  }
  std::memcpy(out_ + out_n_, data, n);
  out_n_ += n;
  drain();
  ++stats_.sent;
  return true;
}

std::size_t SerialLink::receive(uint8_t* buf, std::size_t cap) noexcept {
  drain();  // called often: keeps the outgoing bytes moving between poses
  const ssize_t r = ::read(fd_, buf, cap);
  if (r <= 0) return 0;
  stats_.bytes_received += static_cast<uint64_t>(r);
  return static_cast<std::size_t>(r);
}

}  // namespace kestrel::mavlink

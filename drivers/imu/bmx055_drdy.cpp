#include "kestrel/drivers/bmx055_drdy.hpp"

#include <cerrno>
#include <cstring>

#include "kestrel/rt/clock.hpp"

#if KESTREL_WITH_GPIO_CDEV
#include <fcntl.h>
#include <linux/gpio.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <unistd.h>
#endif

namespace kestrel::drivers::bmx055 {

#if KESTREL_WITH_GPIO_CDEV

bool gpio_cdev_built() { return true; }

GpioDataReadyLine::~GpioDataReadyLine() { close(); }

std::string GpioDataReadyLine::open(const std::string& chip_path, unsigned line_offset, bool rising_edge) {
  close();
  const int chip = ::open(chip_path.c_str(), O_RDWR | O_CLOEXEC);
  if (chip < 0) return chip_path + ": " + std::strerror(errno);
  gpio_v2_line_request req{};
  std::memset(&req, 0, sizeof req);
  req.offsets[0] = line_offset;
  req.num_lines = 1;
  std::strncpy(req.consumer, "kestrel-bmx055", sizeof req.consumer - 1);
  req.config.flags = GPIO_V2_LINE_FLAG_INPUT |
                     (rising_edge ? GPIO_V2_LINE_FLAG_EDGE_RISING : GPIO_V2_LINE_FLAG_EDGE_FALLING);
  req.event_buffer_size = 16;
  const int rc = ioctl(chip, GPIO_V2_GET_LINE_IOCTL, &req);
  const int err = errno;
  ::close(chip);
  if (rc < 0) return chip_path + " line " + std::to_string(line_offset) + ": " + std::strerror(err);
  fd_ = req.fd;
  return "";
}

void GpioDataReadyLine::close() {
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
}

int GpioDataReadyLine::wait(int64_t deadline_ns, int64_t& edge_t_ns) {
  if (fd_ < 0) return -1;
  for (;;) {
    const int64_t left = deadline_ns - rt::now_ns();
    if (left <= 0) return 0;
    pollfd p{fd_, POLLIN, 0};
    timespec ts{static_cast<time_t>(left / 1'000'000'000), static_cast<long>(left % 1'000'000'000)};
    const int rc = ppoll(&p, 1, &ts, nullptr);
    if (rc < 0 && errno == EINTR) continue;
    if (rc < 0) return -1;
    if (rc == 0) return 0;
    gpio_v2_line_event ev[8];
    const ssize_t got = ::read(fd_, ev, sizeof ev);
    if (got < static_cast<ssize_t>(sizeof(gpio_v2_line_event))) return -1;
    const size_t n = static_cast<size_t>(got) / sizeof(gpio_v2_line_event);
    coalesced_ += n - 1;
    edge_t_ns = static_cast<int64_t>(ev[n - 1].timestamp_ns);
    return 1;
  }
}

#else

bool gpio_cdev_built() { return false; }
GpioDataReadyLine::~GpioDataReadyLine() = default;
std::string GpioDataReadyLine::open(const std::string& chip_path, unsigned, bool) {
  return chip_path + ": GPIO character device support not built (no <linux/gpio.h> v2 uAPI)";
}
void GpioDataReadyLine::close() {}
int GpioDataReadyLine::wait(int64_t, int64_t&) { return -1; }

#endif

}  // namespace kestrel::drivers::bmx055

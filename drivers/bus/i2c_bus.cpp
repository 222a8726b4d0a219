#include "kestrel/drivers/i2c_bus.hpp"

#include <cerrno>
#include <cstring>

#if KESTREL_WITH_I2C_DEV
#include <fcntl.h>
#include <linux/i2c-dev.h>
#include <linux/i2c.h>
#include <sys/ioctl.h>
#include <unistd.h>
#endif

namespace kestrel::drivers {

const char* to_string(I2cStatus s) {
  switch (s) {
    case I2cStatus::kOk:
      return "ok";
    case I2cStatus::kNack:
      return "nack";
    case I2cStatus::kTimeout:
      return "timeout";
    case I2cStatus::kIoError:
      return "io-error";
    case I2cStatus::kNotOpen:
      return "not-open";
  }
  return "?";
}

#if KESTREL_WITH_I2C_DEV

bool i2c_dev_built() { return true; }

LinuxI2cBus::~LinuxI2cBus() { close(); }

std::string LinuxI2cBus::open(const std::string& path) {
  close();
  path_ = path;
  fd_ = ::open(path.c_str(), O_RDWR | O_CLOEXEC);
  if (fd_ < 0) return path + ": " + std::strerror(errno);
  unsigned long funcs = 0;
  if (ioctl(fd_, I2C_FUNCS, &funcs) < 0 || (funcs & I2C_FUNC_I2C) == 0) {
    close();
    return path + ": adapter does not support plain I2C transfers (I2C_RDWR)";
  }
  return "";
}

void LinuxI2cBus::close() {
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
}

namespace {
I2cStatus from_errno(int e) {
  // i2c-dev reports a missing ACK as ENXIO (most adapters) or EREMOTEIO.
  if (e == ENXIO || e == EREMOTEIO) return I2cStatus::kNack;
  if (e == ETIMEDOUT || e == EAGAIN) return I2cStatus::kTimeout;
  return I2cStatus::kIoError;
}
}  // namespace

I2cStatus LinuxI2cBus::read_regs(uint8_t addr7, uint8_t reg, uint8_t* dst, size_t n) {
  if (fd_ < 0) return I2cStatus::kNotOpen;
  // Register address write + repeated-start read in one I2C_RDWR call.
  i2c_msg msgs[2];
  msgs[0].addr = addr7;
  msgs[0].flags = 0;
  msgs[0].len = 1;
  msgs[0].buf = &reg;
  msgs[1].addr = addr7;
  msgs[1].flags = I2C_M_RD;
  msgs[1].len = static_cast<uint16_t>(n);
  msgs[1].buf = dst;
  i2c_rdwr_ioctl_data data{msgs, 2};
  if (ioctl(fd_, I2C_RDWR, &data) < 0) return from_errno(errno);
  return I2cStatus::kOk;
}

I2cStatus LinuxI2cBus::write_reg(uint8_t addr7, uint8_t reg, uint8_t value) {
  if (fd_ < 0) return I2cStatus::kNotOpen;
  uint8_t buf[2] = {reg, value};
  i2c_msg msg{};
  msg.addr = addr7;
  msg.flags = 0;
  msg.len = 2;
  msg.buf = buf;
  i2c_rdwr_ioctl_data data{&msg, 1};
  if (ioctl(fd_, I2C_RDWR, &data) < 0) return from_errno(errno);
  return I2cStatus::kOk;
}

#else

bool i2c_dev_built() { return false; }
LinuxI2cBus::~LinuxI2cBus() = default;
std::string LinuxI2cBus::open(const std::string& path) {
  path_ = path;
  return path + ": I2C support not built (no <linux/i2c-dev.h> at build time)";
}
void LinuxI2cBus::close() {}
I2cStatus LinuxI2cBus::read_regs(uint8_t, uint8_t, uint8_t*, size_t) { return I2cStatus::kNotOpen; }
I2cStatus LinuxI2cBus::write_reg(uint8_t, uint8_t, uint8_t) { return I2cStatus::kNotOpen; }

#endif

}  // namespace kestrel::drivers

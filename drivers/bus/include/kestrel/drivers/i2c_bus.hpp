// I2C transport: the interface the BMX055 protocol talks to, and its Linux
// implementation over i2c-dev (ioctl I2C_RDWR: a register-address write and a
// repeated-start read in one kernel call, so no other master can slip between).
//
// Real-time contract: read_regs / write_reg never allocate and return a
// status instead of throwing; the protocol state machine counts and recovers.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

namespace kestrel::drivers {

enum class I2cStatus : uint8_t {
  kOk = 0,
  kNack,     // address or data not acknowledged (device absent, busy, resetting)
  kTimeout,  // bus stuck / arbitration lost / controller timeout
  kIoError,  // any other transport failure
  kNotOpen,
};
const char* to_string(I2cStatus s);

class I2cBus {
 public:
  virtual ~I2cBus() = default;
  // Reads n consecutive registers starting at `reg` (auto-increment; for a
  // FIFO data register the device keeps returning the next FIFO frame).
  virtual I2cStatus read_regs(uint8_t addr7, uint8_t reg, uint8_t* dst, size_t n) = 0;
  virtual I2cStatus write_reg(uint8_t addr7, uint8_t reg, uint8_t value) = 0;
  // Human-readable name for messages ("/dev/i2c-1", "fake").
  virtual std::string name() const = 0;
};

// Linux i2c-dev. open() reports why it failed; the bus stays closed then and
// every transfer returns kNotOpen. Without <linux/i2c-dev.h> at build time
// open() fails with "not built".
class LinuxI2cBus final : public I2cBus {
 public:
  LinuxI2cBus() = default;
  ~LinuxI2cBus() override;
  LinuxI2cBus(const LinuxI2cBus&) = delete;
  LinuxI2cBus& operator=(const LinuxI2cBus&) = delete;

  // "" on success, else a message naming the path and the OS error.
  std::string open(const std::string& path);
  void close();
  bool is_open() const { return fd_ >= 0; }

  I2cStatus read_regs(uint8_t addr7, uint8_t reg, uint8_t* dst, size_t n) override;
  I2cStatus write_reg(uint8_t addr7, uint8_t reg, uint8_t value) override;
  std::string name() const override { return path_; }

 private:
  int fd_ = -1;
  std::string path_;
};

bool i2c_dev_built();  // compiled with <linux/i2c-dev.h>

}  // namespace kestrel::drivers

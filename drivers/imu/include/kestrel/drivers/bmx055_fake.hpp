// A register-file BMX055 behind the I2cBus interface, for tests and for
// `kestrel record --fake-imu`-style dry runs. It keeps the registers the
// driver touches, produces FIFO frames at the configured ODR on its own
// (skewed) oscillators, and injects faults on request: NACKs, bit flips on
// reads, FIFO overruns, brown-outs, stalled data, failing self-tests.
//
// Not real-time: it allocates (deques, std::function). Single thread.
#pragma once

#include <array>
#include <cstdint>
#include <deque>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "kestrel/drivers/bmx055_regs.hpp"
#include "kestrel/drivers/clock_sync.hpp"
#include "kestrel/drivers/i2c_bus.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::drivers::bmx055 {

class FakeBmx055 final : public I2cBus {
 public:
  // `clock` is advanced by the modelled bus time of each transfer when
  // bus_hz > 0 (so a long FIFO burst takes time, as on a real 400 kHz bus).
  FakeBmx055(ManualClock& clock, uint64_t seed = 1);

  // ---- device model ----
  uint8_t acc_addr = kAccAddrDefault;
  uint8_t gyro_addr = kGyroAddrDefault;
  bool mag_fitted = false;
  uint8_t mag_addr = kMagAddrFirst;
  double gyro_clock_error = 0.0;  // actual period = nominal * (1 + error)
  double acc_clock_error = 0.0;
  double bus_hz = 0.0;               // 0 = transfers take no time
  int64_t drdy_latency_ns = 20'000;  // interrupt edge after the frame lands
  // True motion in the sensor frame at time t (default: at rest, z up).
  std::function<void(int64_t t_ns, Vec3d& gyro_rps, Vec3d& acc_mps2)> motion;

  // ---- fault injection ----
  void nack_next(int transactions) { nack_next_ += transactions; }
  void set_nack_probability(double p) { nack_p_ = p; }
  void set_absent(bool absent) { absent_ = absent; }
  // XOR `mask` into the next read of (addr, reg) (the first byte returned).
  void flip_next_read(uint8_t addr, uint8_t reg, uint8_t mask);
  void set_flip_probability(double p) { flip_p_ = p; }  // one random bit per read transaction
  // Fills the FIFO beyond capacity now: frames lost, overrun flag set.
  void force_overrun(bool gyro, bool acc);
  void brown_out();  // every register back to its reset value
  void stall_data(bool stalled) { stalled_ = stalled; }
  void set_self_test_fail(bool acc_fail, bool gyro_fail) {
    st_fail_acc_ = acc_fail;
    st_fail_gyro_ = gyro_fail;
  }

  // ---- I2cBus ----
  I2cStatus read_regs(uint8_t addr7, uint8_t reg, uint8_t* dst, size_t n) override;
  I2cStatus write_reg(uint8_t addr7, uint8_t reg, uint8_t value) override;
  std::string name() const override { return "fake-bmx055"; }

  // Produce frames up to the clock's now (called by every transfer; tests
  // call it to learn about watermark edges between transfers).
  void advance();
  // A gyro FIFO watermark edge since the last call: its host time.
  bool take_watermark_edge(int64_t& t_ns);

  // ---- inspection ----
  uint8_t reg(uint8_t addr7, uint8_t r) const;
  size_t gyro_fifo_level() const { return gyro_fifo_.size(); }
  size_t acc_fifo_level() const { return acc_fifo_.size(); }
  const std::vector<int64_t>& gyro_sample_times() const { return gyro_times_; }  // every frame produced
  uint64_t gyro_frames_lost() const { return gyro_lost_; }
  uint64_t nacks_injected() const { return nacks_; }
  uint64_t flips_injected() const { return flips_; }
  uint64_t transactions() const { return transactions_; }

 private:
  struct Frame {
    std::array<uint8_t, 6> bytes{};
  };
  enum Dev { kAcc = 0, kGyro = 1, kMag = 2, kNone = 3 };
  Dev dev_of(uint8_t addr) const;
  void reset_part(Dev d);
  bool streaming(Dev d) const;
  double gyro_lsb_rps() const;
  double acc_lsb_mps2() const;
  Frame make_gyro_frame(int64_t t) const;
  Frame make_acc_frame(int64_t t) const;
  bool inject_nack();
  void bus_time(size_t bytes);

  ManualClock& clock_;
  std::mt19937_64 rng_;
  std::array<std::array<uint8_t, 256>, 3> regs_{};
  std::deque<Frame> gyro_fifo_, acc_fifo_;
  bool gyro_overrun_ = false, acc_overrun_ = false;
  Frame gyro_latest_, acc_latest_;
  int64_t next_gyro_t_ = -1, next_acc_t_ = -1;
  int64_t boot_until_[3] = {0, 0, 0};
  std::vector<int64_t> gyro_times_;
  bool edge_pending_ = false;
  int64_t edge_t_ = 0;
  int nack_next_ = 0;
  double nack_p_ = 0, flip_p_ = 0;
  bool absent_ = false, stalled_ = false;
  bool st_fail_acc_ = false, st_fail_gyro_ = false;
  bool flip_armed_ = false;
  uint8_t flip_addr_ = 0, flip_reg_ = 0, flip_mask_ = 0;
  uint64_t nacks_ = 0, flips_ = 0, transactions_ = 0, gyro_lost_ = 0;
};

}  // namespace kestrel::drivers::bmx055

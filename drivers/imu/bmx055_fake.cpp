#include "kestrel/drivers/bmx055_fake.hpp"

#include <algorithm>
#include <cmath>

namespace kestrel::drivers::bmx055 {
namespace {
constexpr double kG = 9.80665;
constexpr int64_t kBootNs = 2'000'000;  // transfers NACK this long after a soft reset
}  // namespace

FakeBmx055::FakeBmx055(ManualClock& clock, uint64_t seed) : clock_(clock), rng_(seed) {
  motion = [](int64_t, Vec3d& g, Vec3d& a) {
    g = {0, 0, 0};
    a = {0, 0, kG};
  };
  reset_part(kAcc);
  reset_part(kGyro);
  reset_part(kMag);
}

FakeBmx055::Dev FakeBmx055::dev_of(uint8_t addr) const {
  if (absent_) return kNone;
  if (addr == acc_addr) return kAcc;
  if (addr == gyro_addr) return kGyro;
  if (mag_fitted && addr == mag_addr) return kMag;
  return kNone;
}

void FakeBmx055::reset_part(Dev d) {
  auto& r = regs_[static_cast<size_t>(d)];
  r.fill(0);
  if (d == kAcc) {
    r[acc::kChipIdReg] = acc::kChipId;
    r[acc::kPmuRange] = 0x03;
    r[acc::kPmuBw] = 0x0F;
    acc_fifo_.clear();
    acc_overrun_ = false;
    next_acc_t_ = -1;
  } else if (d == kGyro) {
    r[gyro::kChipIdReg] = gyro::kChipId;
    r[gyro::kIntEn1] = 0x0F;
    gyro_fifo_.clear();
    gyro_overrun_ = false;
    next_gyro_t_ = -1;
  }
}

void FakeBmx055::brown_out() {
  reset_part(kAcc);
  reset_part(kGyro);
}

bool FakeBmx055::streaming(Dev d) const {
  const auto& r = regs_[static_cast<size_t>(d)];
  return (r[0x3E] & 0xC0) == 0x80 && !stalled_;
}

double FakeBmx055::gyro_lsb_rps() const {
  return gyro::lsb_mdps(static_cast<gyro::Range>(regs_[kGyro][gyro::kRange] & 0x07)) * 1e-3 * M_PI / 180.0;
}
double FakeBmx055::acc_lsb_mps2() const {
  return acc::lsb_mg(static_cast<acc::Range>(regs_[kAcc][acc::kPmuRange] & 0x0F)) * 1e-3 * kG;
}

FakeBmx055::Frame FakeBmx055::make_gyro_frame(int64_t t) const {
  Vec3d g, a;
  motion(t, g, a);
  Frame f;
  for (int i = 0; i < 3; ++i) {
    const double c = std::round(g[static_cast<size_t>(i)] / gyro_lsb_rps());
    const auto v = static_cast<int16_t>(std::clamp(c, -32768.0, 32767.0));
    f.bytes[static_cast<size_t>(2 * i)] = static_cast<uint8_t>(static_cast<uint16_t>(v) & 0xFF);
    f.bytes[static_cast<size_t>(2 * i + 1)] = static_cast<uint8_t>(static_cast<uint16_t>(v) >> 8);
  }
  return f;
}

FakeBmx055::Frame FakeBmx055::make_acc_frame(int64_t t) const {
  Vec3d g, a;
  motion(t, g, a);
  Frame f;
  const uint8_t st = regs_[kAcc][acc::kSelfTest];
  for (int i = 0; i < 3; ++i) {
    double mps2 = a[static_cast<size_t>(i)];
    if ((st & 0x03) == i + 1) {
      // Self-test excitation: ~+-1.2 g on x/y, +-0.6 g on z; a failing part barely moves.
      const double amp = (st_fail_acc_ ? 0.05 : (i == 2 ? 0.6 : 1.2)) * kG;
      mps2 += (st & 0x04) ? amp : -amp;
    }
    const double c = std::round(mps2 / acc_lsb_mps2());
    const auto v = static_cast<int16_t>(std::clamp(c, -2048.0, 2047.0));
    const auto u = static_cast<uint16_t>(static_cast<uint16_t>(v) << 4);
    f.bytes[static_cast<size_t>(2 * i)] = static_cast<uint8_t>((u & 0xF0) | 0x01);  // new_data bit
    f.bytes[static_cast<size_t>(2 * i + 1)] = static_cast<uint8_t>(u >> 8);
  }
  return f;
}

void FakeBmx055::advance() {
  const int64_t now = clock_.now_ns();
  const double gyro_period = 1e9 /
                             gyro::odr_hz(static_cast<gyro::Bandwidth>(regs_[kGyro][gyro::kBw] & 0x07)) *
                             (1.0 + gyro_clock_error);
  const double acc_period =
      1e9 /
      acc::odr_hz(static_cast<acc::Bandwidth>(std::clamp<int>(regs_[kAcc][acc::kPmuBw] & 0x1F, 0x08, 0x0F))) *
      (1.0 + acc_clock_error);
  if (next_gyro_t_ < 0) next_gyro_t_ = now + static_cast<int64_t>(gyro_period);
  if (next_acc_t_ < 0) next_acc_t_ = now + static_cast<int64_t>(acc_period * 0.37);
  const size_t wm = regs_[kGyro][gyro::kFifoConfig0] & 0x7F;
  while (next_gyro_t_ <= now) {
    const Frame f = make_gyro_frame(next_gyro_t_);
    gyro_latest_ = f;
    if (streaming(kGyro)) {
      gyro_times_.push_back(next_gyro_t_);
      if (gyro_fifo_.size() >= static_cast<size_t>(gyro::kFifoDepthFrames)) {
        gyro_fifo_.pop_front();  // stream mode: oldest discarded
        gyro_overrun_ = true;
        ++gyro_lost_;
      }
      gyro_fifo_.push_back(f);
      if (wm > 0 && gyro_fifo_.size() == wm && (regs_[kGyro][gyro::kFifoWmEn] & 0x80)) {
        edge_pending_ = true;
        edge_t_ = next_gyro_t_ + drdy_latency_ns;
      }
    }
    next_gyro_t_ += static_cast<int64_t>(std::llround(gyro_period));
  }
  while (next_acc_t_ <= now) {
    const Frame f = make_acc_frame(next_acc_t_);
    acc_latest_ = f;
    if (streaming(kAcc)) {
      if (acc_fifo_.size() >= static_cast<size_t>(acc::kFifoDepthFrames)) {
        acc_fifo_.pop_front();
        acc_overrun_ = true;
      }
      acc_fifo_.push_back(f);
    }
    next_acc_t_ += static_cast<int64_t>(std::llround(acc_period));
  }
}

bool FakeBmx055::take_watermark_edge(int64_t& t_ns) {
  advance();
  if (!edge_pending_ || edge_t_ > clock_.now_ns()) return false;
  edge_pending_ = false;
  t_ns = edge_t_;
  return true;
}

void FakeBmx055::force_overrun(bool gyro, bool acc) {
  advance();
  if (gyro) {
    const size_t extra = gyro::kFifoDepthFrames + 5 - gyro_fifo_.size();
    gyro_lost_ += 5;
    for (size_t i = 0; i < extra; ++i) gyro_fifo_.push_back(gyro_latest_);
    while (gyro_fifo_.size() > static_cast<size_t>(gyro::kFifoDepthFrames)) gyro_fifo_.pop_front();
    gyro_overrun_ = true;
  }
  if (acc) {
    while (acc_fifo_.size() < static_cast<size_t>(acc::kFifoDepthFrames)) acc_fifo_.push_back(acc_latest_);
    acc_overrun_ = true;
  }
}

void FakeBmx055::flip_next_read(uint8_t addr, uint8_t reg, uint8_t mask) {
  flip_armed_ = true;
  flip_addr_ = addr;
  flip_reg_ = reg;
  flip_mask_ = mask;
}

bool FakeBmx055::inject_nack() {
  if (nack_next_ > 0) {
    --nack_next_;
    ++nacks_;
    return true;
  }
  if (nack_p_ > 0 && std::uniform_real_distribution<double>(0, 1)(rng_) < nack_p_) {
    ++nacks_;
    return true;
  }
  return false;
}

void FakeBmx055::bus_time(size_t bytes) {
  if (bus_hz <= 0) return;
  // start + address + register + repeated start + address, then 9 clocks a byte.
  const double bits = 9.0 * (3 + static_cast<double>(bytes));
  clock_.advance(static_cast<int64_t>(bits / bus_hz * 1e9));
}

uint8_t FakeBmx055::reg(uint8_t addr7, uint8_t r) const {
  const Dev d = addr7 == acc_addr ? kAcc : addr7 == gyro_addr ? kGyro : kMag;
  return regs_[static_cast<size_t>(d)][r];
}

I2cStatus FakeBmx055::read_regs(uint8_t addr7, uint8_t reg, uint8_t* dst, size_t n) {
  ++transactions_;
  bus_time(n);
  advance();
  const Dev d = dev_of(addr7);
  if (d == kNone || clock_.now_ns() < boot_until_[d] || inject_nack()) return I2cStatus::kNack;
  auto& r = regs_[static_cast<size_t>(d)];
  if (d == kMag && (r[mag::kPowerCtrl] & 0x01) == 0) return I2cStatus::kNack;  // suspended BMM150
  if (reg == 0x3F && d != kMag) {
    auto& fifo = d == kAcc ? acc_fifo_ : gyro_fifo_;
    size_t i = 0;
    while (i < n) {
      Frame f{};
      if (!fifo.empty()) {
        f = fifo.front();
        fifo.pop_front();
      }
      for (size_t j = 0; j < 6 && i < n; ++j) dst[i++] = f.bytes[j];
    }
  } else {
    for (size_t i = 0; i < n; ++i) {
      const uint8_t a = static_cast<uint8_t>(reg + i);
      uint8_t v = r[a];
      if (d == kAcc && a >= acc::kDataXLsb && a <= 0x07) v = acc_latest_.bytes[a - acc::kDataXLsb];
      if (d == kGyro && a >= gyro::kRateXLsb && a <= 0x07) v = gyro_latest_.bytes[a - gyro::kRateXLsb];
      if (d == kAcc && a == acc::kTemp) v = 4;  // 25 degC
      if (d == kAcc && a == acc::kFifoStatus)
        v = static_cast<uint8_t>((acc_overrun_ ? 0x80 : 0) | std::min<size_t>(acc_fifo_.size(), 0x7F));
      if (d == kGyro && a == gyro::kFifoStatus)
        v = static_cast<uint8_t>((gyro_overrun_ ? 0x80 : 0) | std::min<size_t>(gyro_fifo_.size(), 0x7F));
      if (d == kGyro && a == gyro::kBw) v |= gyro::kBwReadOnlyMask;
      if (d == kMag && a == mag::kChipIdReg) v = mag::kChipId;
      dst[i] = v;
    }
  }
  if (flip_armed_ && addr7 == flip_addr_ && reg == flip_reg_ && n > 0) {
    flip_armed_ = false;
    dst[0] ^= flip_mask_;
    ++flips_;
  } else if (flip_p_ > 0 && n > 0 && std::uniform_real_distribution<double>(0, 1)(rng_) < flip_p_) {
    const size_t byte = std::uniform_int_distribution<size_t>(0, n - 1)(rng_);
    dst[byte] ^= static_cast<uint8_t>(1u << std::uniform_int_distribution<int>(0, 7)(rng_));
    ++flips_;
  }
  return I2cStatus::kOk;
}

I2cStatus FakeBmx055::write_reg(uint8_t addr7, uint8_t reg, uint8_t value) {
  ++transactions_;
  bus_time(1);
  advance();
  const Dev d = dev_of(addr7);
  if (d == kNone || clock_.now_ns() < boot_until_[d] || inject_nack()) return I2cStatus::kNack;
  auto& r = regs_[static_cast<size_t>(d)];
  if (d != kMag && reg == 0x14 && value == kSoftResetValue) {
    reset_part(d);
    boot_until_[d] = clock_.now_ns() + kBootNs;
    return I2cStatus::kOk;
  }
  if (d == kMag && reg == mag::kPowerCtrl && (value & 0x82) == 0x82) {
    reset_part(kMag);
    return I2cStatus::kOk;
  }
  r[reg] = value;
  if (d == kGyro && reg == gyro::kBw) r[reg] = value & 0x7F;
  if (reg == 0x3E && d != kMag) {  // FIFO_CONFIG_1 write clears the FIFO
    if (d == kAcc) {
      acc_fifo_.clear();
      acc_overrun_ = false;
    } else {
      gyro_fifo_.clear();
      gyro_overrun_ = false;
      edge_pending_ = false;
    }
  }
  if (d == kGyro && reg == gyro::kBist && (value & gyro::kBistTrigger)) {
    r[reg] = static_cast<uint8_t>(gyro::kBistReady | (st_fail_gyro_ ? gyro::kBistFail : 0) | 0x10);
  }
  return I2cStatus::kOk;
}

}  // namespace kestrel::drivers::bmx055

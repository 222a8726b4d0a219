// The flight controller's IMU driver's whole receive path (decoder, signing,
// TIMESYNC, IMU unpacking and stamping) on any bytes, shared by the libFuzzer
// target fuzz_mavlink_imu and the unit suite's mutation test. The first byte
// picks the message kind and whether signing is on; the rest arrives through
// a link that hands it out in uneven pieces. The host clock stands still at
// kFuzzHostNs, so the TIMESYNC answers in the seeds (ts1 = kFuzzHostNs) bring
// the driver to stamping samples. Invariants: pushed samples have finite
// values and strictly increasing stamps; counters add up.
#pragma once

#include <unistd.h>

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>

#include "kestrel/drivers/mavlink_imu.hpp"
#include "mavlink_fuzz_entry.hpp"

namespace kestrel::test {

constexpr int64_t kFuzzHostNs = 1'000'000'000'000;

// A link over a byte string; its descriptor is a pipe kept readable, so the driver's wait returns at once.
class FuzzLink final : public mavlink::Link {
 public:
  FuzzLink(const uint8_t* d, std::size_t n) : d_(d), n_(n) {
    if (::pipe(p_) == 0) (void)!::write(p_[1], "x", 1);
  }
  ~FuzzLink() override {
    ::close(p_[0]);
    ::close(p_[1]);
  }
  bool send(const uint8_t*, std::size_t) noexcept override { return true; }
  std::size_t receive(uint8_t* buf, std::size_t cap) noexcept override {
    if (pos_ >= n_ || calls_++ % 2 == 1) return 0;  // 0 ends one step's read loop
    std::size_t take = 1 + (pos_ * 7 + n_) % 97;
    if (take > cap) take = cap;
    if (take > n_ - pos_) take = n_ - pos_;
    std::memcpy(buf, d_ + pos_, take);
    pos_ += take;
    return take;
  }
  const std::string& endpoint() const override { return name_; }
  int fd() const noexcept override { return p_[0]; }
  bool done() const { return pos_ >= n_; }

 private:
  const uint8_t* d_;
  std::size_t n_, pos_ = 0;
  unsigned calls_ = 0;
  int p_[2] = {-1, -1};
  std::string name_ = "fuzz";
};

struct FuzzImuSink final : drivers::ImuSink {
  int64_t last_t = INT64_MIN;
  uint64_t n = 0;
  bool push(const ImuSample& s) noexcept override {
    if (s.t_ns <= last_t) std::abort();
    for (int a = 0; a < 3; ++a)
      if (!std::isfinite(s.acc_mps2[a]) || !std::isfinite(s.gyro_rps[a])) std::abort();
    last_t = s.t_ns;
    return ++n % 17 != 0;  // now and then the ring is full
  }
};

inline drivers::MavlinkImuConfig fuzz_imu_config(uint8_t mode) {
  drivers::MavlinkImuConfig c;
  c.message = static_cast<drivers::MavlinkImuMessage>((mode & 3) % 3);  // bit 2: signing
  c.raw_acc_mps2_per_lsb = 0.001;
  c.raw_gyro_rad_s_per_lsb = 0.001;
  c.max_latency_ns = INT64_MAX / 4;  // the clock stands still: every plausible stamp is in
  c.signing = (mode & 4) != 0;
  c.key = fuzz_signing_key();
  c.signing_clock_unix_ns = &fuzz_signing_clock;
  return c;
}

inline uint64_t mavlink_imu_fuzz_one(const uint8_t* data, std::size_t size) {
  if (size == 0) return 0;
  drivers::ManualClock clock(kFuzzHostNs);
  auto owned = std::make_unique<FuzzLink>(data + 1, size - 1);
  FuzzLink* link = owned.get();
  drivers::MavlinkImuDriver d(std::move(owned), fuzz_imu_config(data[0]), clock);
  FuzzImuSink sink;
  for (int guard = 0; !link->done() && guard < 100000; ++guard) d.step(sink, 0);
  const auto& c = d.counters();
  if (c.samples + c.sink_drops != sink.n) std::abort();
  if (c.samples + c.sink_drops + c.before_sync + c.out_of_order + c.nonfinite + c.stamp_outliers !=
      c.imu_messages)
    std::abort();
  return c.samples;
}

}  // namespace kestrel::test

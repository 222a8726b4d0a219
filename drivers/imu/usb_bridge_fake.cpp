#include "kestrel/drivers/usb_bridge_fake.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>

namespace kestrel::drivers::usb_bridge {

FakeUsbBridge::FakeUsbBridge(ManualClock& clock, const FakeBridgeOptions& o)
    : clock_(clock), o_(o), rng_(o.seed) {
  motion = [](int64_t, double g[3], double a[3]) {
    g[0] = g[1] = g[2] = 0;
    a[0] = a[1] = 0;
    a[2] = 9.80665;
  };
  h0_ = clock_.now_ns();
  d0_us_ = o_.device_t0_us;
  next_frame_host_ = h0_ + o_.usb_frame_ns;
  next_imu_host_ = h0_ + 1'234'567 % static_cast<int64_t>(1e9 / o_.imu_rate_hz);
  next_strobe_host_ = h0_ + 7'000'000;
  next_status_host_ = h0_;
  last_arrival_ = h0_;
}

uint64_t FakeUsbBridge::device_us_at(int64_t host_ns) const {
  const double dt_us = static_cast<double>(host_ns - h0_) / (1.0 + o_.skew) / 1000.0;
  return d0_us_ + static_cast<uint64_t>(std::floor(dt_us));
}

int64_t FakeUsbBridge::true_host_ns(uint64_t t_us) const {
  const double dd_ns = (static_cast<double>(t_us) - static_cast<double>(d0_us_)) * 1000.0;
  return h0_ + static_cast<int64_t>(std::llround(dd_ns * (1.0 + o_.skew)));
}

int64_t FakeUsbBridge::latency() {
  std::uniform_real_distribution<double> u01(0, 1);
  double j;
  if (u01(rng_) < o_.jitter_uniform_fraction) {
    j = u01(rng_) * static_cast<double>(o_.jitter_max_ns);
  } else {
    j = std::min(std::exponential_distribution<double>(1.0 / o_.jitter_exp_mean_ns)(rng_),
                 static_cast<double>(o_.jitter_max_ns));
  }
  return o_.latency_floor_ns + static_cast<int64_t>(j);
}

void FakeUsbBridge::emit(PacketType type, const uint8_t* payload, size_t len, uint64_t t_tx_us,
                         int64_t t_tx_host) {
  std::vector<uint8_t> bytes(kMaxPacketBytes);
  bytes.resize(encode_packet(type, seq_++, t_tx_us, payload, len, bytes.data(), bytes.size()));
  ++packets_sent_;
  std::uniform_real_distribution<double> u01(0, 1);
  const bool stalled = stall_from_ >= 0 && t_tx_host >= stall_from_ && t_tx_host < stall_to_;
  if (stalled || (o_.loss > 0 && u01(rng_) < o_.loss)) {
    ++dropped_;
    return;
  }
  if (o_.crc_error > 0 && u01(rng_) < o_.crc_error) {
    const size_t i = std::uniform_int_distribution<size_t>(2, bytes.size() - 1)(rng_);
    bytes[i] ^= static_cast<uint8_t>(1u << std::uniform_int_distribution<int>(0, 7)(rng_));
    ++corrupted_;
  }
  if (o_.garbage > 0 && u01(rng_) < o_.garbage) {
    const size_t n = std::uniform_int_distribution<size_t>(1, 40)(rng_);
    std::vector<uint8_t> g(n);
    for (auto& b : g) b = static_cast<uint8_t>(rng_());
    if (n >= 2) g[n / 2] = kMagic0, g[n / 2 + 1 < n ? n / 2 + 1 : n / 2] = kMagic1;  // a false magic, too
    bytes.insert(bytes.begin(), g.begin(), g.end());
    ++garbage_;
  }
  // The pipe is FIFO: a late transfer holds back the ones behind it.
  const int64_t arrival = std::max(last_arrival_, t_tx_host + latency());
  last_arrival_ = arrival;
  if (o_.reorder > 0 && !pipe_.empty() && pipe_.size() >= 2 && u01(rng_) < o_.reorder) {
    // Both arrive together, the newer first: reordering never delivers a
    // packet before it was sent.
    Pending& prev = pipe_.back();
    prev.arrival_ns = arrival;
    pipe_.push_back(Pending{arrival, std::move(prev.bytes)});
    pipe_[pipe_.size() - 2].bytes = std::move(bytes);
    ++reordered_;
    return;
  }
  pipe_.push_back(Pending{arrival, std::move(bytes)});
}

void FakeUsbBridge::generate_until(int64_t host_ns) {
  const int64_t imu_period = static_cast<int64_t>(std::llround(1e9 / o_.imu_rate_hz));
  const int64_t cam_period = static_cast<int64_t>(std::llround(1e9 / o_.camera_rate_hz));
  uint8_t payload[kMaxPayload];
  while (next_frame_host_ <= host_ns) {
    const int64_t frame = next_frame_host_;
    if (reboot_at_ >= 0 && frame >= reboot_at_) {
      h0_ = frame;
      d0_us_ = 1000;  // a fresh counter
      ++boot_id_;
      seq_ = 0;
      sample_seq_ = 0;
      strobe_seq_ = 0;
      imu_q_.clear();
      strobe_q_.clear();
      next_status_host_ = frame;
      reboot_at_ = -1;
    }
    while (next_imu_host_ <= frame) {
      ImuWireSample s;
      s.t_us = device_us_at(next_imu_host_);
      double g[3], a[3];
      motion(next_imu_host_, g, a);
      const double glsb = 2000.0 / 32768.0 * 3.14159265358979323846 / 180.0;
      const double alsb = 16.0 / 2048.0 * 9.80665;
      for (int k = 0; k < 3; ++k) {
        s.gyro[k] = static_cast<int16_t>(std::clamp(std::round(g[k] / glsb), -32768.0, 32767.0));
        s.acc[k] = static_cast<int16_t>(std::clamp(std::round(a[k] / alsb), -2048.0, 2047.0));
      }
      s.temp_raw = 6;
      s.flags = kBridgeAccFresh;
      s.sample_seq = sample_seq_++;
      imu_truth_.push_back(TrueSample{s.sample_seq, true_host_ns(s.t_us)});
      imu_q_.push_back(s);
      next_imu_host_ += imu_period;
    }
    while (next_strobe_host_ <= frame) {
      StrobeWire w;
      w.t_us = device_us_at(next_strobe_host_);
      w.strobe_seq = strobe_seq_++;
      w.duration_us = static_cast<uint32_t>(o_.exposure_us);
      strobe_truth_.push_back(true_host_ns(w.t_us));
      strobe_q_.push_back(w);
      next_strobe_host_ += cam_period;
    }
    const uint64_t t_tx = device_us_at(frame);
    if (frame >= next_status_host_) {
      StatusWire st;
      st.boot_id = boot_id_;
      st.fw_version = 0x0100;
      st.acc_range_code = o_.acc_range_code;
      st.acc_bw_code = 0x0D;
      st.gyro_range_code = o_.gyro_range_code;
      st.gyro_bw_code = 0x03;
      st.state = 1;
      st.uptime_ms = static_cast<uint32_t>((frame - h0_) / 1'000'000);
      emit(PacketType::kStatus, payload, encode_status_payload(st, payload, sizeof payload), t_tx, frame);
      next_status_host_ = frame + 1'000'000'000;
    }
    if (!imu_q_.empty()) {
      emit(PacketType::kImu, payload,
           encode_imu_payload(imu_q_.data(), imu_q_.size(), payload, sizeof payload), t_tx, frame);
      imu_q_.clear();
    }
    if (!strobe_q_.empty()) {
      emit(PacketType::kStrobe, payload,
           encode_strobe_payload(strobe_q_.data(), strobe_q_.size(), payload, sizeof payload), t_tx, frame);
      strobe_q_.clear();
    }
    next_frame_host_ += o_.usb_frame_ns;
  }
}

UsbStatus FakeUsbBridge::bulk_read(uint8_t* buf, size_t cap, size_t& got, int timeout_ms) {
  got = 0;
  if (disconnected_) {
    clock_.advance(static_cast<int64_t>(timeout_ms) * 1'000'000);
    return UsbStatus::kDisconnected;
  }
  const int64_t timeout_ns = static_cast<int64_t>(timeout_ms) * 1'000'000;
  int64_t now = clock_.now_ns();
  generate_until(now + timeout_ns);
  if (pipe_.empty() || pipe_.front().arrival_ns > now) {
    if (!pipe_.empty() && pipe_.front().arrival_ns <= now + timeout_ns) {
      now = pipe_.front().arrival_ns;
      clock_.set(now);
    } else {
      clock_.advance(timeout_ns);
      return UsbStatus::kTimeout;
    }
  }
  const size_t limit = std::min(cap, o_.max_transfer_bytes);
  while (!pipe_.empty() && pipe_.front().arrival_ns <= now && got < limit) {
    Pending& p = pipe_.front();
    const size_t n = std::min(limit - got, p.bytes.size() - front_off_);
    std::memcpy(buf + got, p.bytes.data() + front_off_, n);
    got += n;
    front_off_ += n;
    if (front_off_ == p.bytes.size()) {
      pipe_.pop_front();
      front_off_ = 0;
    }
  }
  return UsbStatus::kOk;
}

}  // namespace kestrel::drivers::usb_bridge

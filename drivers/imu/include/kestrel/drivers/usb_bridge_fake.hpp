// A simulated USB IMU bridge behind UsbEndpoint: a device clock with offset
// and drift, IMU samples and exposure strobes stamped on it, packets flushed
// once per USB frame and delivered to the host after a jittered latency, with
// injected loss, reordering, CRC errors, garbage bytes, stalls and reboots.
// It drives a ManualClock: a bulk_read with nothing due advances the clock to
// the next arrival (or by the timeout), as a blocking read would.
//
// Not real-time (allocates); single thread.
#pragma once

#include <cstdint>
#include <deque>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "kestrel/drivers/clock_sync.hpp"
#include "kestrel/drivers/usb_bridge.hpp"
#include "kestrel/drivers/usb_bridge_protocol.hpp"

namespace kestrel::drivers::usb_bridge {

struct FakeBridgeOptions {
  double imu_rate_hz = 400.0;
  double camera_rate_hz = 30.0;
  int32_t exposure_us = 4000;
  double skew = 100e-6;                 // host = h0 + device * (1 + skew): the bridge clock runs slow
  uint64_t device_t0_us = 123'456'789;  // bridge counter at host time 0 of the run
  int64_t usb_frame_ns = 1'000'000;     // the bridge flushes its queue once per (full-speed) frame
  int64_t latency_floor_ns = 120'000;
  int64_t jitter_max_ns = 2'000'000;
  double jitter_exp_mean_ns = 150'000;   // most transfers
  double jitter_uniform_fraction = 0.2;  // the rest: uniform over [0, jitter_max]
  double loss = 0;                       // per packet
  double reorder = 0;                    // per packet: swapped with the one before
  double crc_error = 0;                  // per packet: one byte flipped
  double garbage = 0;                    // per packet: 1..40 random bytes inserted before it
  size_t max_transfer_bytes = 4096;      // smaller values split packets across transfers
  uint8_t acc_range_code = 0x0C;         // reported in status packets
  uint8_t gyro_range_code = 0x00;
  uint64_t seed = 1;
};

class FakeUsbBridge final : public UsbEndpoint {
 public:
  FakeUsbBridge(ManualClock& clock, const FakeBridgeOptions& o);

  UsbStatus bulk_read(uint8_t* buf, size_t cap, size_t& got, int timeout_ms) override;
  std::string name() const override { return "fake-usb-bridge"; }

  // Motion in sensor axes at host time t (default: at rest, z up).
  std::function<void(int64_t t_ns, double gyro_rps[3], double acc_mps2[3])> motion;
  // No packet leaves the bridge between these host times (cable glitch).
  void stall(int64_t from_ns, int64_t to_ns) {
    stall_from_ = from_ns;
    stall_to_ = to_ns;
  }
  // The bridge reboots at this host time: counter, sequences and boot id restart.
  void reboot_at(int64_t t_ns) { reboot_at_ = t_ns; }
  void set_disconnected(bool d) { disconnected_ = d; }
  FakeBridgeOptions& options() { return o_; }

  // ---- truth ----
  // True host time of a bridge counter value (current boot).
  int64_t true_host_ns(uint64_t t_us) const;
  struct TrueSample {
    uint16_t sample_seq;
    int64_t t_host_ns;  // true host time of the sample's stamp
  };
  const std::vector<TrueSample>& imu_truth() const { return imu_truth_; }
  const std::vector<int64_t>& strobe_truth() const { return strobe_truth_; }  // by strobe_seq
  uint64_t packets_sent() const { return packets_sent_; }
  uint64_t packets_dropped() const { return dropped_; }
  uint64_t packets_corrupted() const { return corrupted_; }
  uint64_t packets_reordered() const { return reordered_; }
  uint64_t garbage_inserted() const { return garbage_; }

 private:
  struct Pending {
    int64_t arrival_ns;
    std::vector<uint8_t> bytes;
  };
  void generate_until(int64_t host_ns);
  void emit(PacketType type, const uint8_t* payload, size_t len, uint64_t t_tx_us, int64_t t_tx_host);
  int64_t latency();
  uint64_t device_us_at(int64_t host_ns) const;

  ManualClock& clock_;
  FakeBridgeOptions o_;
  std::mt19937_64 rng_;
  int64_t h0_ = 0;      // host time of the current boot's reference
  uint64_t d0_us_ = 0;  // device counter at h0_
  uint32_t boot_id_ = 0x1234ABCD;
  int64_t next_frame_host_ = 0;
  int64_t next_imu_host_ = 0;
  int64_t next_strobe_host_ = 0;
  int64_t next_status_host_ = 0;
  uint16_t seq_ = 0;
  uint16_t sample_seq_ = 0;
  uint32_t strobe_seq_ = 0;
  int64_t last_arrival_ = 0;
  std::vector<ImuWireSample> imu_q_;
  std::vector<StrobeWire> strobe_q_;
  std::deque<Pending> pipe_;
  size_t front_off_ = 0;
  int64_t stall_from_ = -1, stall_to_ = -1, reboot_at_ = -1;
  bool disconnected_ = false;
  std::vector<TrueSample> imu_truth_;
  std::vector<int64_t> strobe_truth_;
  uint64_t packets_sent_ = 0, dropped_ = 0, corrupted_ = 0, reordered_ = 0, garbage_ = 0;
};

}  // namespace kestrel::drivers::usb_bridge

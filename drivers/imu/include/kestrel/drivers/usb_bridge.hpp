// USB IMU bridge: transport (UsbEndpoint: libusb bulk IN, or a fake), and the
// protocol layer (UsbBridgeDriver) that turns the framed packet stream into
// ImuSamples on the host clock and exposure strobes for the camera side.
//
// The bridge stamps every sample and strobe with its own microsecond counter;
// ClockSync maps that counter onto CLOCK_MONOTONIC using each packet's
// transmit stamp against the host time its bulk transfer completed.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/drivers/bmx055.hpp"
#include "kestrel/drivers/clock_sync.hpp"
#include "kestrel/drivers/usb_bridge_protocol.hpp"

namespace kestrel::drivers {

enum class UsbStatus : uint8_t { kOk, kTimeout, kDisconnected, kError, kNotOpen };
const char* to_string(UsbStatus s);

class UsbEndpoint {
 public:
  virtual ~UsbEndpoint() = default;
  // One bulk IN transfer into buf (<= cap bytes). kOk with got = 0 is legal.
  virtual UsbStatus bulk_read(uint8_t* buf, size_t cap, size_t& got, int timeout_ms) = 0;
  virtual std::string name() const = 0;
};

struct UsbDeviceInfo {
  uint16_t vid = 0, pid = 0;
  int bus = 0, address = 0;
  std::string serial;  // "" when unreadable without permissions
};

// libusb-1.0 synchronous bulk transfers. open() reports why it failed
// (not built, no device with vid:pid, permission denied, interface busy).
class LibusbEndpoint final : public UsbEndpoint {
 public:
  LibusbEndpoint();
  ~LibusbEndpoint() override;
  LibusbEndpoint(const LibusbEndpoint&) = delete;
  LibusbEndpoint& operator=(const LibusbEndpoint&) = delete;

  std::string open(uint16_t vid, uint16_t pid, uint8_t endpoint_in, int interface_number = 0);
  void close();
  bool is_open() const { return handle_ != nullptr; }
  UsbStatus bulk_read(uint8_t* buf, size_t cap, size_t& got, int timeout_ms) override;
  std::string name() const override { return name_; }

 private:
  void* ctx_ = nullptr;     // libusb_context*
  void* handle_ = nullptr;  // libusb_device_handle*
  uint8_t ep_ = 0;
  int iface_ = 0;
  std::string name_;
};

bool libusb_built();
// Devices with this vid:pid (all of them when pid == 0). Empty when libusb is
// not built; `error` says why the bus could not be listed.
std::vector<UsbDeviceInfo> list_usb_devices(uint16_t vid, uint16_t pid, std::string* error = nullptr);

// Exposure strobes, mapped to host time, for the camera thread.
class StrobeSink {
 public:
  virtual ~StrobeSink() = default;
  virtual bool push(const StrobeStamp& s) noexcept = 0;
};

struct UsbBridgeConfig {
  uint16_t vid = usb_bridge::kDefaultVid;
  uint16_t pid = usb_bridge::kDefaultPid;
  uint8_t endpoint_in = usb_bridge::kDefaultEndpointIn;
  // Ranges the bridge firmware programs; status packets override (counted if different).
  bmx055::acc::Range acc_range = bmx055::acc::Range::k16g;
  bmx055::gyro::Range gyro_range = bmx055::gyro::Range::k2000dps;
  std::array<int8_t, 3> axis_remap{1, 2, 3};
  int read_timeout_ms = 20;
  int64_t no_data_timeout_ns = 200'000'000;
  ClockSyncOptions clock;  // defaults suit a full-speed bulk endpoint
  void validate() const;   // throws std::invalid_argument naming the field
};

enum class UsbBridgeState : uint8_t { kWaiting, kStreaming, kStalled, kDisconnected };
const char* to_string(UsbBridgeState s);

struct UsbBridgeCounters {
  uint64_t transfers = 0;
  uint64_t packets = 0;
  uint64_t crc_errors = 0;
  uint64_t bad_headers = 0;
  uint64_t bytes_skipped = 0;
  uint64_t bad_payloads = 0;  // CRC fine, payload length inconsistent with its count
  uint64_t packets_lost = 0;  // packet sequence gaps
  uint64_t packets_late = 0;  // sequence behind the newest (reordered / duplicated)
  uint64_t samples = 0;
  uint64_t samples_lost = 0;     // sample sequence gaps
  uint64_t samples_late = 0;     // arrived after a newer one (already counted lost): dropped
  uint64_t time_clamped = 0;     // a mapped time not after the previous one (clock refit)
  uint64_t bridge_overruns = 0;  // samples the bridge flagged kBridgeOverrun
  uint64_t bridge_read_errors = 0;
  uint64_t strobes = 0;
  uint64_t strobes_lost = 0;
  uint64_t sink_drops = 0;
  uint64_t config_mismatches = 0;
  uint64_t bridge_reboots = 0;
  uint64_t sequence_restarts = 0;  // many consecutive late packets: followed as a restart
  uint64_t clock_jumps = 0;
  uint64_t timeouts = 0;
  uint64_t usb_errors = 0;
};

class UsbBridgeDriver {
 public:
  UsbBridgeDriver(UsbEndpoint& ep, const HostClock& clock, const UsbBridgeConfig& cfg);

  // One bulk read (blocking up to read_timeout_ms), parse, deliver. Never
  // waits on a sink. Returns the state after the step.
  UsbBridgeState step(ImuSink& imu, StrobeSink* strobes);

  UsbBridgeState state() const { return state_; }
  const UsbBridgeCounters& counters() const { return counters_; }
  const ClockSync& clock_sync() const { return sync_; }
  bool have_status() const { return have_status_; }
  const usb_bridge::StatusWire& status() const { return status_; }

 private:
  void on_packet(const usb_bridge::StreamParser::Packet& p, int64_t t_rx_ns, ImuSink& imu,
                 StrobeSink* strobes);
  void on_imu(const uint8_t* payload, size_t len, int64_t t_rx_ns, ImuSink& imu);
  void on_strobes(const uint8_t* payload, size_t len, StrobeSink* strobes);
  void on_status(const uint8_t* payload, size_t len, int64_t t_rx_ns, ImuSink& imu);
  void restart(int64_t t_ns, ImuSink& imu, const char* why);

  UsbEndpoint& ep_;
  const HostClock& clock_;
  UsbBridgeConfig cfg_;
  bmx055::Scales scales_;
  usb_bridge::StreamParser parser_;
  ClockSync sync_;
  UsbBridgeState state_ = UsbBridgeState::kWaiting;
  UsbBridgeCounters counters_;
  usb_bridge::StatusWire status_;
  bool have_status_ = false;
  bool have_seq_ = false;
  int consecutive_late_ = 0;
  static constexpr int kMaxConsecutiveLate = 8;
  uint16_t next_seq_ = 0;
  bool have_sample_ = false;
  uint32_t sample_seq_ext_ = 0;  // 16-bit wire sequence extended
  uint16_t last_sample_seq_ = 0;
  int64_t last_sample_t_ns_ = 0;
  bool have_strobe_ = false;
  uint32_t last_strobe_seq_ = 0;
  int64_t last_data_ns_ = 0;
  std::array<uint8_t, 4096> xfer_{};
  std::array<usb_bridge::ImuWireSample, usb_bridge::kMaxImuSamplesPerPacket> wire_{};
  std::array<usb_bridge::StrobeWire, usb_bridge::kMaxStrobesPerPacket> strobe_wire_{};
};

}  // namespace kestrel::drivers

#include "kestrel/drivers/usb_bridge.hpp"

#include <cstdio>
#include <stdexcept>

#if KESTREL_WITH_LIBUSB
#include <libusb.h>
#endif

namespace kestrel::drivers {

using namespace usb_bridge;

const char* to_string(UsbStatus s) {
  switch (s) {
    case UsbStatus::kOk:
      return "ok";
    case UsbStatus::kTimeout:
      return "timeout";
    case UsbStatus::kDisconnected:
      return "disconnected";
    case UsbStatus::kError:
      return "error";
    case UsbStatus::kNotOpen:
      return "not-open";
  }
  return "?";
}

const char* to_string(UsbBridgeState s) {
  switch (s) {
    case UsbBridgeState::kWaiting:
      return "waiting";
    case UsbBridgeState::kStreaming:
      return "streaming";
    case UsbBridgeState::kStalled:
      return "stalled";
    case UsbBridgeState::kDisconnected:
      return "disconnected";
  }
  return "?";
}

void UsbBridgeConfig::validate() const {
  bool seen[3] = {false, false, false};
  for (int8_t r : axis_remap) {
    const int a = r < 0 ? -r : r;
    if (a < 1 || a > 3 || seen[a - 1])
      throw std::invalid_argument("axis_remap: must be a signed permutation of x, y, z");
    seen[a - 1] = true;
  }
  if ((endpoint_in & 0x80) == 0)
    throw std::invalid_argument("endpoint_in: must be an IN endpoint (0x81..0x8F)");
  if (read_timeout_ms <= 0) throw std::invalid_argument("read_timeout_ms: must be > 0");
  if (no_data_timeout_ns <= 0) throw std::invalid_argument("no_data_timeout_ms: must be > 0");
}

namespace {
bool acc_range_code_ok(uint8_t c) { return c == 0x03 || c == 0x05 || c == 0x08 || c == 0x0C; }
bool gyro_range_code_ok(uint8_t c) { return c <= 0x04; }
}  // namespace

UsbBridgeDriver::UsbBridgeDriver(UsbEndpoint& ep, const HostClock& clock, const UsbBridgeConfig& cfg)
    : ep_(ep), clock_(clock), cfg_(cfg), sync_(cfg.clock) {
  cfg_.validate();
  scales_ = bmx055::make_scales(cfg_.acc_range, cfg_.gyro_range, cfg_.axis_remap);
  last_data_ns_ = clock_.now_ns();
}

void UsbBridgeDriver::restart(int64_t t_ns, ImuSink& imu, const char* why) {
  sync_.reset();
  parser_.clear();
  have_seq_ = false;
  have_sample_ = false;
  have_strobe_ = false;
  imu.event(t_ns, EventCode::kDriverReset, why);
}

UsbBridgeState UsbBridgeDriver::step(ImuSink& imu, StrobeSink* strobes) {
  size_t got = 0;
  const UsbStatus st = ep_.bulk_read(xfer_.data(), xfer_.size(), got, cfg_.read_timeout_ms);
  const int64_t t_rx = clock_.now_ns();
  if (st == UsbStatus::kDisconnected || st == UsbStatus::kNotOpen) {
    if (state_ != UsbBridgeState::kDisconnected) {
      ++counters_.usb_errors;
      imu.event(t_rx, EventCode::kDriverFault, "usb bridge: disconnected");
    }
    state_ = UsbBridgeState::kDisconnected;
    return state_;
  }
  if (st == UsbStatus::kError) ++counters_.usb_errors;
  if (got > 0) {
    ++counters_.transfers;
    last_data_ns_ = t_rx;
    size_t off = 0;
    while (off < got) {
      off += parser_.feed(xfer_.data() + off, got - off);
      StreamParser::Packet p;
      while (parser_.next(p)) on_packet(p, t_rx, imu, strobes);
    }
    const auto& pc = parser_.counters();
    counters_.packets = pc.packets;
    counters_.crc_errors = pc.crc_errors;
    counters_.bad_headers = pc.bad_headers;
    counters_.bytes_skipped = pc.bytes_skipped;
  } else if (t_rx - last_data_ns_ > cfg_.no_data_timeout_ns && state_ != UsbBridgeState::kStalled) {
    ++counters_.timeouts;
    state_ = UsbBridgeState::kStalled;
    imu.event(t_rx, EventCode::kDriverFault, "usb bridge: no data within the timeout");
  }
  return state_;
}

void UsbBridgeDriver::on_packet(const StreamParser::Packet& p, int64_t t_rx_ns, ImuSink& imu,
                                StrobeSink* strobes) {
  bool late = false;
  if (have_seq_) {
    const auto d = static_cast<int16_t>(static_cast<uint16_t>(p.header.seq - next_seq_));
    if (d > 0) counters_.packets_lost += static_cast<uint64_t>(d);
    if (d < 0) {
      ++counters_.packets_late;
      late = true;
      // A run of "late" packets is a sequence that restarted (a reboot whose
      // status packet was lost), not reordering: follow it.
      if (++consecutive_late_ > kMaxConsecutiveLate) {
        ++counters_.sequence_restarts;
        restart(t_rx_ns, imu, "usb bridge: packet sequence restarted");
        late = false;
      }
    }
  }
  if (!late) consecutive_late_ = 0;
  if (!late) {
    have_seq_ = true;
    next_seq_ = static_cast<uint16_t>(p.header.seq + 1);
    // Only in-order packets feed the clock: a late one would look like the
    // device clock running backwards.
    if (!sync_.add(static_cast<int64_t>(p.header.t_tx_us) * 1000, t_rx_ns)) {
      ++counters_.clock_jumps;
      imu.event(t_rx_ns, EventCode::kClockJump, "usb bridge: bridge clock jumped; clock sync restarted");
    }
  }
  if (state_ != UsbBridgeState::kStreaming) state_ = UsbBridgeState::kStreaming;
  switch (p.header.type) {
    case PacketType::kImu:
      on_imu(p.payload, p.header.payload_len, t_rx_ns, imu);
      break;
    case PacketType::kStrobe:
      on_strobes(p.payload, p.header.payload_len, strobes);
      break;
    case PacketType::kStatus:
      on_status(p.payload, p.header.payload_len, t_rx_ns, imu);
      break;
  }
}

void UsbBridgeDriver::on_imu(const uint8_t* payload, size_t len, int64_t t_rx_ns, ImuSink& imu) {
  size_t n = 0;
  if (!decode_imu_payload(payload, len, wire_.data(), wire_.size(), n)) {
    ++counters_.bad_payloads;
    return;
  }
  for (size_t i = 0; i < n; ++i) {
    const ImuWireSample& w = wire_[i];
    uint32_t flags = 0;
    if (have_sample_) {
      const auto d = static_cast<int16_t>(
          static_cast<uint16_t>(w.sample_seq - static_cast<uint16_t>(last_sample_seq_ + 1)));
      if (d < 0) {
        ++counters_.samples_late;
        continue;
      }
      if (d > 0) {
        counters_.samples_lost += static_cast<uint64_t>(d);
        flags |= kImuGapBefore;
      }
      sample_seq_ext_ += static_cast<uint32_t>(d) + 1;
    } else {
      sample_seq_ext_ = w.sample_seq;
    }
    last_sample_seq_ = w.sample_seq;
    if (w.flags & kBridgeOverrun) {
      ++counters_.bridge_overruns;
      flags |= kImuGapBefore;
    }
    if (w.flags & kBridgeReadError) {
      // The values repeat the previous sample: not a measurement.
      ++counters_.bridge_read_errors;
      have_sample_ = true;
      continue;
    }
    ImuSample s;
    s.t_ns = sync_.to_host_ns(static_cast<int64_t>(w.t_us) * 1000);
    if (have_sample_ && s.t_ns <= last_sample_t_ns_) {
      ++counters_.time_clamped;
      s.t_ns = last_sample_t_ns_ + 1;
    }
    s.t_recv_ns = t_rx_ns;
    s.seq = sample_seq_ext_;
    s.flags = flags;
    bmx055::convert(bmx055::RawXyz{w.gyro[0], w.gyro[1], w.gyro[2]},
                    bmx055::RawXyz{w.acc[0], w.acc[1], w.acc[2]}, scales_, s);
    s.temp_c = bmx055::temp_c_from_raw(w.temp_raw);
    have_sample_ = true;
    last_sample_t_ns_ = s.t_ns;
    if (imu.push(s)) {
      ++counters_.samples;
    } else {
      ++counters_.sink_drops;
    }
  }
}

void UsbBridgeDriver::on_strobes(const uint8_t* payload, size_t len, StrobeSink* strobes) {
  size_t n = 0;
  if (!decode_strobe_payload(payload, len, strobe_wire_.data(), strobe_wire_.size(), n)) {
    ++counters_.bad_payloads;
    return;
  }
  for (size_t i = 0; i < n; ++i) {
    const StrobeWire& w = strobe_wire_[i];
    if (have_strobe_) {
      const int64_t d = static_cast<int64_t>(w.strobe_seq) - static_cast<int64_t>(last_strobe_seq_) - 1;
      if (d < 0) continue;  // late duplicate
      counters_.strobes_lost += static_cast<uint64_t>(d);
    }
    have_strobe_ = true;
    last_strobe_seq_ = w.strobe_seq;
    ++counters_.strobes;
    StrobeStamp s;
    s.t_host_ns = sync_.to_host_ns(static_cast<int64_t>(w.t_us) * 1000);
    s.seq = w.strobe_seq;
    s.duration_us = static_cast<int32_t>(w.duration_us);
    if (strobes != nullptr && !strobes->push(s)) ++counters_.sink_drops;
  }
}

void UsbBridgeDriver::on_status(const uint8_t* payload, size_t len, int64_t t_rx_ns, ImuSink& imu) {
  StatusWire s;
  if (!decode_status_payload(payload, len, s)) {
    ++counters_.bad_payloads;
    return;
  }
  if (have_status_ && s.boot_id != status_.boot_id) {
    ++counters_.bridge_reboots;
    restart(t_rx_ns, imu, "usb bridge: rebooted (new boot id)");
  }
  if (!acc_range_code_ok(s.acc_range_code) || !gyro_range_code_ok(s.gyro_range_code)) {
    ++counters_.bad_payloads;
    return;
  }
  const bool differs = s.acc_range_code != static_cast<uint8_t>(cfg_.acc_range) ||
                       s.gyro_range_code != static_cast<uint8_t>(cfg_.gyro_range);
  const bool changed = !have_status_ || s.acc_range_code != status_.acc_range_code ||
                       s.gyro_range_code != status_.gyro_range_code;
  if (differs && changed) {
    // The bridge's ranges are what the sensor was programmed with: trust them.
    ++counters_.config_mismatches;
    imu.event(t_rx_ns, EventCode::kDriverFault,
              "usb bridge: sensor ranges differ from the config; using the bridge's");
  }
  scales_ = bmx055::make_scales(static_cast<bmx055::acc::Range>(s.acc_range_code),
                                static_cast<bmx055::gyro::Range>(s.gyro_range_code), cfg_.axis_remap);
  status_ = s;
  have_status_ = true;
}

// ---- libusb transport ------------------------------------------------------------

#if KESTREL_WITH_LIBUSB

bool libusb_built() { return true; }

LibusbEndpoint::LibusbEndpoint() = default;
LibusbEndpoint::~LibusbEndpoint() {
  close();
  if (ctx_ != nullptr) libusb_exit(static_cast<libusb_context*>(ctx_));
}

std::string LibusbEndpoint::open(uint16_t vid, uint16_t pid, uint8_t endpoint_in, int interface_number) {
  close();
  char id[16];
  std::snprintf(id, sizeof id, "%04x:%04x", vid, pid);
  name_ = std::string("usb ") + id;
  if (ctx_ == nullptr) {
    libusb_context* c = nullptr;
    const int rc = libusb_init(&c);
    if (rc != 0) return std::string("libusb_init failed: ") + libusb_strerror(static_cast<libusb_error>(rc));
    ctx_ = c;
  }
  auto* ctx = static_cast<libusb_context*>(ctx_);
  libusb_device** list = nullptr;
  const ssize_t n = libusb_get_device_list(ctx, &list);
  if (n < 0) return std::string("cannot list USB devices: ") + libusb_strerror(static_cast<libusb_error>(n));
  libusb_device_handle* h = nullptr;
  std::string err = std::string("no USB device ") + id + " found (is the IMU bridge plugged in?)";
  for (ssize_t i = 0; i < n; ++i) {
    libusb_device_descriptor d{};
    if (libusb_get_device_descriptor(list[i], &d) != 0 || d.idVendor != vid || d.idProduct != pid) continue;
    const int rc = libusb_open(list[i], &h);
    if (rc == 0) break;
    err = std::string("USB device ") + id +
          " found but cannot be opened: " + libusb_strerror(static_cast<libusb_error>(rc)) +
          (rc == LIBUSB_ERROR_ACCESS ? " (udev rule / permissions)" : "");
    h = nullptr;
  }
  libusb_free_device_list(list, 1);
  if (h == nullptr) return err;
  libusb_set_auto_detach_kernel_driver(h, 1);
  const int rc = libusb_claim_interface(h, interface_number);
  if (rc != 0) {
    libusb_close(h);
    return std::string("USB device ") + id + ": cannot claim interface " + std::to_string(interface_number) +
           ": " + libusb_strerror(static_cast<libusb_error>(rc));
  }
  handle_ = h;
  ep_ = endpoint_in;
  iface_ = interface_number;
  return "";
}

void LibusbEndpoint::close() {
  if (handle_ != nullptr) {
    auto* h = static_cast<libusb_device_handle*>(handle_);
    libusb_release_interface(h, iface_);
    libusb_close(h);
  }
  handle_ = nullptr;
}

UsbStatus LibusbEndpoint::bulk_read(uint8_t* buf, size_t cap, size_t& got, int timeout_ms) {
  got = 0;
  if (handle_ == nullptr) return UsbStatus::kNotOpen;
  int transferred = 0;
  const int rc = libusb_bulk_transfer(static_cast<libusb_device_handle*>(handle_), ep_, buf,
                                      static_cast<int>(cap), &transferred, timeout_ms);
  got = transferred > 0 ? static_cast<size_t>(transferred) : 0;
  if (rc == 0) return UsbStatus::kOk;
  if (rc == LIBUSB_ERROR_TIMEOUT) return got > 0 ? UsbStatus::kOk : UsbStatus::kTimeout;
  if (rc == LIBUSB_ERROR_NO_DEVICE) return UsbStatus::kDisconnected;
  return UsbStatus::kError;
}

std::vector<UsbDeviceInfo> list_usb_devices(uint16_t vid, uint16_t pid, std::string* error) {
  std::vector<UsbDeviceInfo> out;
  libusb_context* ctx = nullptr;
  if (libusb_init(&ctx) != 0) {
    if (error) *error = "libusb_init failed";
    return out;
  }
  libusb_device** list = nullptr;
  const ssize_t n = libusb_get_device_list(ctx, &list);
  if (n < 0 && error)
    *error = std::string("cannot list USB devices: ") + libusb_strerror(static_cast<libusb_error>(n));
  for (ssize_t i = 0; i < n; ++i) {
    libusb_device_descriptor d{};
    if (libusb_get_device_descriptor(list[i], &d) != 0) continue;
    if (d.idVendor != vid || (pid != 0 && d.idProduct != pid)) continue;
    UsbDeviceInfo info;
    info.vid = d.idVendor;
    info.pid = d.idProduct;
    info.bus = libusb_get_bus_number(list[i]);
    info.address = libusb_get_device_address(list[i]);
    libusb_device_handle* h = nullptr;
    if (d.iSerialNumber != 0 && libusb_open(list[i], &h) == 0) {
      unsigned char s[128] = {};
      if (libusb_get_string_descriptor_ascii(h, d.iSerialNumber, s, sizeof s) > 0)
        info.serial = reinterpret_cast<char*>(s);
      libusb_close(h);
    }
    out.push_back(info);
  }
  if (n >= 0) libusb_free_device_list(list, 1);
  libusb_exit(ctx);
  return out;
}

#else

bool libusb_built() { return false; }
LibusbEndpoint::LibusbEndpoint() = default;
LibusbEndpoint::~LibusbEndpoint() = default;
std::string LibusbEndpoint::open(uint16_t, uint16_t, uint8_t, int) {
  return "USB bridge support not built (libusb-1.0 was not found at build time)";
}
void LibusbEndpoint::close() {}
UsbStatus LibusbEndpoint::bulk_read(uint8_t*, size_t, size_t& got, int) {
  got = 0;
  return UsbStatus::kNotOpen;
}
std::vector<UsbDeviceInfo> list_usb_devices(uint16_t, uint16_t, std::string* error) {
  if (error) *error = "libusb not built";
  return {};
}

#endif

}  // namespace kestrel::drivers

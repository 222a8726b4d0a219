// Linux IIO: the transport. Finds a device by name under a sysfs root, reads
// its scales, offsets and sampling frequencies, enables the scan elements and
// the buffer with the chosen timestamp clock, and opens its character device
// (/dev/iio:deviceN) for non-blocking reads. Every error names the sysfs file
// or node it came from.
//
// Start-up only (allocates, touches files); the steady state is the protocol's
// poll()/read() on fd().
#pragma once

#include <string>
#include <string_view>
#include <vector>

#include "kestrel/drivers/iio_scan.hpp"

namespace kestrel::drivers::iio {

constexpr const char* kDefaultSysfsRoot = "/sys/bus/iio/devices";
constexpr const char* kDefaultDevRoot = "/dev";

// ---- sysfs attribute helpers (pure where they can be) ----------------------------

// Reads a whole attribute file; trailing white space removed. false when it cannot be read.
bool read_attr(const std::string& path, std::string& out);
// Writes a value; returns "" or "PATH: cannot write \"v\": reason".
std::string write_attr(const std::string& path, const std::string& value);
// A sysfs number: decimal, optional sign, fraction and exponent ("0.000598550", "1e-3").
bool parse_number(std::string_view text, double& out);

// sampling_frequency_available: "12.5 25 50 100" or a range "[min step max]".
struct AvailableRates {
  std::vector<double> list_hz;  // sorted ascending
  bool is_range = false;
  double min_hz = 0, step_hz = 0, max_hz = 0;
};
// Returns nullptr or a static message.
const char* parse_available_rates(std::string_view text, AvailableRates& out);
// The slowest available rate >= requested, else the fastest (a range clamps
// and rounds up to its step). requested <= 0: 0 (leave the device's).
double choose_rate(const AvailableRates& a, double requested_hz);

struct DeviceEntry {
  int number = -1;         // N of iio:deviceN
  std::string dir;         // ROOT/iio:deviceN
  std::string name;        // its `name` attribute
  bool has_accel = false;  // scan_elements/in_accel_x_en present
  bool has_gyro = false;
  bool has_timestamp = false;
  bool has_buffer = false;
};
// Every iio:deviceN under root, by N. `error` says why the root cannot be listed.
std::vector<DeviceEntry> list_devices(const std::string& sysfs_root, std::string* error = nullptr);

// ---- one device -------------------------------------------------------------------

struct DeviceOptions {
  std::string sysfs_root = kDefaultSysfsRoot;
  std::string dev_root = kDefaultDevRoot;
  std::string name;  // the `name` attribute to find
  bool want_accel = false;
  bool want_gyro = false;
  double rate_hz = 0;                         // <= 0: leave the device's sampling frequency
  std::string timestamp_clock = "monotonic";  // written to current_timestamp_clock when the file exists
  int buffer_length_samples = 512;
  int watermark_samples = 1;
};

class Device {
 public:
  Device() = default;
  ~Device();
  Device(const Device&) = delete;
  Device& operator=(const Device&) = delete;

  // "" when streaming, else an error naming the file. Re-opening closes first.
  std::string open(const DeviceOptions& o);
  // Disables the buffer and closes the node (best effort; never throws).
  void close();
  bool is_open() const { return fd_ >= 0; }
  int fd() const { return fd_; }

  const ScanLayout& layout() const { return layout_; }
  double rate_hz() const { return rate_hz_; }  // read back; 0 when the device has no such attribute
  const std::string& timestamp_clock() const {
    return clock_;
  }  // read back; "realtime" without the file (kernel default)
  bool timestamp_clock_settable() const { return clock_file_; }
  const std::string& dir() const { return dir_; }
  const std::string& node() const { return node_; }
  const std::string& name() const { return name_; }
  // Assumptions made while opening (no timestamp clock file, rate not settable, ...).
  const std::vector<std::string>& notes() const { return notes_; }
  std::string describe() const;  // "accel_3d (iio:device0) 100 Hz, le:s16/16>>0 x3 + ts, 16 B/record"

 private:
  std::string configure_rate(const DeviceOptions& o);
  std::string read_scale(const std::string& type, const char* axis, double& scale, double& offset) const;

  int fd_ = -1;
  std::string dir_, node_, name_, clock_;
  bool clock_file_ = false;
  double rate_hz_ = 0;
  ScanLayout layout_;
  std::vector<std::string> notes_;
};

}  // namespace kestrel::drivers::iio

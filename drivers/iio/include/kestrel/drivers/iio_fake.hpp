// A fake Linux IIO tree in a folder: sysfs attribute files, scan_elements
// descriptions and, standing for each /dev/iio:deviceN, a named FIFO the test
// writes scan records into. The driver under test opens it exactly as it
// opens the kernel's (ImuConfig::sysfs_root / dev_root point here), so the
// transport code that runs is the real one.
//
// The record encoder does not use the parser: it reads back what the driver
// left in the en / index / type files and lays the record out itself, so the
// two only agree when both follow the kernel's rules.
//
// Test support: allocates, throws std::runtime_error on a setup failure.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/msgs.hpp"

namespace kestrel::drivers::iio {

struct FakeDeviceSpec {
  std::string name = "icm42688";
  bool accel = true;
  bool gyro = true;
  std::string accel_type = "le:s16/16>>0";
  std::string gyro_type = "le:s16/16>>0";
  std::string timestamp_type = "le:s64/64>>0";
  bool gyro_first = false;                  // scan index order: gyro before accel
  std::string accel_scale = "0.004788403";  // m/s^2 per count (+-16 g at 16 bits); "" = no file
  std::string gyro_scale = "0.001065264";   // rad/s per count (+-2000 dps at 16 bits); "" = no file
  std::string accel_offset;                 // counts; "" = no file
  std::string gyro_offset;
  bool per_axis_scale = false;                   // in_accel_x_scale ... instead of in_accel_scale
  std::string rate_attr = "sampling_frequency";  // "" = none; or in_accel_sampling_frequency ...
  std::string rate_hz = "100";
  std::string available_hz = "25 50 100 200 400 800";  // "" = no _available file
  bool timestamp_clock_file = true;
  std::string timestamp_clock = "realtime";               // the kernel's default
  std::vector<std::string> extra_elements = {"in_temp"};  // enabled at start; the driver should turn them off
  bool has_buffer = true;
};

class FakeIioTree {
 public:
  // Builds the tree under dir (created; must be empty or absent).
  FakeIioTree(const std::string& dir, std::vector<FakeDeviceSpec> specs);
  ~FakeIioTree();
  FakeIioTree(const FakeIioTree&) = delete;
  FakeIioTree& operator=(const FakeIioTree&) = delete;

  const std::string& sysfs_root() const { return sysfs_root_; }
  const std::string& dev_root() const { return dev_root_; }
  std::string device_dir(int i) const;
  std::string read(int i, const std::string& rel) const;  // "" when absent
  void write(int i, const std::string& rel, const std::string& value) const;
  void remove(int i, const std::string& rel) const;

  // Opens the FIFOs for writing (after the driver opened them for reading)
  // and freezes each device's record layout from its scan_elements files.
  void open_writers();
  void close_writers();
  size_t record_bytes(int i) const { return layouts_.at(static_cast<size_t>(i)).record_bytes; }
  // One record: SI values -> counts with the device's scale and offset
  // (rounded, clamped to the real bits); channels the device lacks are ignored.
  size_t encode(int i, int64_t t_ns, const Vec3d& acc_mps2, const Vec3d& gyro_rps, uint8_t* out,
                size_t cap) const;
  // Non-blocking: returns the bytes the FIFO took.
  size_t write_bytes(int i, const uint8_t* p, size_t n);
  double accel_scale(int i) const;
  double gyro_scale(int i) const;

 private:
  struct Field {
    int kind = -1;  // 0..2 accel, 3..5 gyro, 6 timestamp, -1 other
    bool be = false, is_signed = true;
    unsigned real = 0, storage = 0, shift = 0;
    size_t offset = 0;
  };
  struct Layout {
    std::vector<Field> fields;
    size_t record_bytes = 0;
    double acc_scale = 0, gyro_scale = 0, acc_offset = 0, gyro_offset = 0;
  };
  Layout freeze(int i) const;

  std::string dir_, sysfs_root_, dev_root_;
  std::vector<FakeDeviceSpec> specs_;
  std::vector<int> fds_;
  std::vector<Layout> layouts_;
};

}  // namespace kestrel::drivers::iio

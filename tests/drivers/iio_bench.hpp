// The IIO IMU driver against a fake IIO tree (drivers/iio_fake.hpp): a
// ManualClock for the host, the fake's FIFOs for /dev/iio:deviceN, and
// device specs of the two kinds the driver is for.
#pragma once

#include <gtest/gtest.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/drivers/iio_fake.hpp"
#include "kestrel/drivers/iio_imu.hpp"
#include "test_data.hpp"

namespace kestrel::test {

namespace iio = drivers::iio;

// A combined IMU as an SPI IMU's IIO driver shows it (BMI088 / ICM-42688
// style): accel and anglvel s16 in one scan, sampling_frequency shared.
inline iio::FakeDeviceSpec combined_imu_spec(const std::string& rate_hz = "200") {
  iio::FakeDeviceSpec s;
  s.name = "icm42688";
  s.rate_hz = rate_hz;
  s.available_hz = "25 50 100 200 400 800 1600";
  return s;
}

// The RealSense D4xx IMU as the kernel's HID sensor drivers show it: two
// devices, s32 channels, their own rate attribute without an _available list,
// and (the HID timestamp usage) the device's hardware clock in the stamps.
inline iio::FakeDeviceSpec d4xx_accel_spec() {
  iio::FakeDeviceSpec s;
  s.name = "accel_3d";
  s.gyro = false;
  s.accel_type = "le:s32/32>>0";
  s.accel_scale = "0.009806650";  // 1 mg per count
  s.rate_attr = "in_accel_sampling_frequency";
  s.rate_hz = "63";
  s.available_hz = "";
  s.extra_elements = {};
  return s;
}
inline iio::FakeDeviceSpec d4xx_gyro_spec() {
  iio::FakeDeviceSpec s;
  s.name = "gyro_3d";
  s.accel = false;
  s.gyro_type = "le:s32/32>>0";
  s.gyro_scale = "0.000174533";  // 0.01 deg/s per count
  s.rate_attr = "in_anglvel_sampling_frequency";
  s.rate_hz = "200";
  s.available_hz = "";
  s.extra_elements = {};
  return s;
}

struct IioBench {
  drivers::ManualClock clock{100'000'000'000};
  std::unique_ptr<iio::FakeIioTree> tree;
  iio::ImuConfig cfg;
  std::unique_ptr<iio::ImuDriver> drv;

  IioBench(const std::string& name, std::vector<iio::FakeDeviceSpec> specs) {
    tree = std::make_unique<iio::FakeIioTree>(temp_dir("iio_" + name), std::move(specs));
    cfg.sysfs_root = tree->sysfs_root();
    cfg.dev_root = tree->dev_root();
    cfg.read_timeout_ms = 1;  // a step with nothing to read costs 1 ms of real time
  }
  // Combined device named `name` (or accel + gyro devices).
  std::string open() {
    drv = std::make_unique<iio::ImuDriver>(clock, cfg);
    const std::string e = drv->open();
    if (e.empty()) tree->open_writers();
    return e;
  }
  // One record into device `dev`'s FIFO.
  void put(int dev, int64_t t_dev_ns, const Vec3d& acc, const Vec3d& gyro) {
    uint8_t b[iio::kMaxRecordBytes];
    const size_t n = tree->encode(dev, t_dev_ns, acc, gyro, b, sizeof b);
    ASSERT_GT(n, 0u);
    ASSERT_EQ(tree->write_bytes(dev, b, n), n);
  }
  void put_bytes(int dev, const uint8_t* b, size_t n) { ASSERT_EQ(tree->write_bytes(dev, b, n), n); }
  iio::ImuState step_at(int64_t host_ns, drivers::ImuSink& sink) {
    clock.set(host_ns);
    return drv->step(sink);
  }
};

}  // namespace kestrel::test

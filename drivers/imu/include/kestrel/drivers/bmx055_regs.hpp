// Bosch BMX055 register map: the accelerometer part (BMA2x2 family), the
// gyroscope part (BMG160 family) and the optional magnetometer (BMM150).
//
// Numbers are from the BMX055 datasheet (BST-BMX055-DS000); the unit each code
// stands for sits next to it so a reviewer can check a table entry against the
// datasheet without a calculator. docs/drivers/bmx055.md explains the choices.
#pragma once

#include <cstdint>

namespace kestrel::drivers::bmx055 {

// ---- I2C addresses (7-bit) ----------------------------------------------------
constexpr uint8_t kAccAddrDefault = 0x18;   // SDO1 low
constexpr uint8_t kAccAddrAlt = 0x19;       // SDO1 high
constexpr uint8_t kGyroAddrDefault = 0x68;  // SDO2 low
constexpr uint8_t kGyroAddrAlt = 0x69;      // SDO2 high
constexpr uint8_t kMagAddrFirst = 0x10;     // CSB3/SDO3 select 0x10..0x13
constexpr uint8_t kMagAddrLast = 0x13;

constexpr uint8_t kSoftResetValue = 0xB6;  // BGW_SOFTRESET magic, both parts

// ---- accelerometer (BMA2x2-style) ----------------------------------------------
namespace acc {
constexpr uint8_t kChipIdReg = 0x00;
constexpr uint8_t kChipId = 0xFA;
constexpr uint8_t kDataXLsb = 0x02;    // x<3:0> in bits 7:4, new_data in bit 0; 0x03 = x<11:4>; then y, z
constexpr uint8_t kTemp = 0x08;        // int8, 0.5 K/LSB, 0 LSB = 23 degC
constexpr uint8_t kIntStatus1 = 0x0A;  // bit 7 data, bit 6 fifo watermark, bit 5 fifo full
constexpr uint8_t kFifoStatus = 0x0E;  // bit 7 overrun, bits 6:0 frame count
constexpr uint8_t kPmuRange = 0x0F;
constexpr uint8_t kPmuBw = 0x10;
constexpr uint8_t kPmuLpw = 0x11;   // 0x00 = normal mode
constexpr uint8_t kAccdHbw = 0x13;  // bit 7 data_high_bw (unfiltered), bit 6 shadow_dis
constexpr uint8_t kSoftReset = 0x14;
constexpr uint8_t kIntEn1 = 0x17;       // bit 4 data, bit 5 fifo full, bit 6 fifo watermark
constexpr uint8_t kIntMap1 = 0x1A;      // bit 0 int1_data, bit 1 int1_fwm, bit 2 int1_ffull
constexpr uint8_t kIntOutCtrl = 0x20;   // bit 0 int1 active high, bit 1 int1 open drain
constexpr uint8_t kIntRstLatch = 0x21;  // bits 3:0 latch mode (0 = non-latched), bit 7 reset latch
constexpr uint8_t kFifoConfig0 = 0x30;  // bits 5:0 watermark level (frames)
constexpr uint8_t kSelfTest =
    0x32;                       // bits 1:0 axis (1 x, 2 y, 3 z), bit 2 sign (1 = positive), bit 4 amplitude
constexpr uint8_t kWdt = 0x34;  // bit 2 i2c watchdog enable, bit 1 select 50 ms (else 1 ms)
constexpr uint8_t kFifoConfig1 = 0x3E;  // bits 7:6 mode (0 bypass, 1 fifo, 2 stream), bits 1:0 data select (0
                                        // = xyz); a write clears the FIFO
constexpr uint8_t kFifoData = 0x3F;

constexpr int kFifoDepthFrames = 32;
constexpr int kFrameBytes = 6;  // x, y, z as (lsb, msb)
constexpr int kResolutionBits = 12;

// PMU_RANGE codes and the sensitivity they give (datasheet table "Resolution").
enum class Range : uint8_t { k2g = 0x03, k4g = 0x05, k8g = 0x08, k16g = 0x0C };
constexpr double range_g(Range r) {
  return r == Range::k2g ? 2.0 : r == Range::k4g ? 4.0 : r == Range::k8g ? 8.0 : 16.0;
}
// 0.98 / 1.95 / 3.91 / 7.81 mg/LSB: full scale over 2^11 counts.
constexpr double lsb_mg(Range r) { return range_g(r) * 1000.0 / 2048.0; }

// PMU_BW codes: filter bandwidth; the data rate (ODR) is twice the bandwidth.
enum class Bandwidth : uint8_t {
  k7_81Hz = 0x08,
  k15_63Hz = 0x09,
  k31_25Hz = 0x0A,
  k62_5Hz = 0x0B,
  k125Hz = 0x0C,
  k250Hz = 0x0D,
  k500Hz = 0x0E,
  k1000Hz = 0x0F
};
constexpr double bandwidth_hz(Bandwidth b) {
  return 7.8125 * static_cast<double>(1u << (static_cast<unsigned>(b) - 0x08));
}
constexpr double odr_hz(Bandwidth b) { return 2.0 * bandwidth_hz(b); }

constexpr uint8_t kFifoModeStream = 0x80;  // FIFO_CONFIG_1 bits 7:6 = 2
constexpr uint8_t kSelfTestAmpHigh = 0x10;
// Self-test: minimum |positive - negative| per axis at +-8 g (datasheet "Self-test").
constexpr double kSelfTestMinDiffMg[3] = {800.0, 800.0, 400.0};
}  // namespace acc

// ---- gyroscope (BMG160-style) ----------------------------------------------------
namespace gyro {
constexpr uint8_t kChipIdReg = 0x00;
constexpr uint8_t kChipId = 0x0F;
constexpr uint8_t kRateXLsb = 0x02;    // int16 LE x, y, z at 0x02..0x07
constexpr uint8_t kIntStatus1 = 0x0A;  // bit 7 data, bit 4 fifo
constexpr uint8_t kFifoStatus = 0x0E;  // bit 7 overrun, bits 6:0 frame count
constexpr uint8_t kRange = 0x0F;
constexpr uint8_t kBw = 0x10;       // reads back with bit 7 set (datasheet: "bit 7 read-only, reads 1")
constexpr uint8_t kLpm1 = 0x11;     // 0x00 = normal mode
constexpr uint8_t kRateHbw = 0x13;  // bit 7 data_high_bw, bit 6 shadow_dis
constexpr uint8_t kSoftReset = 0x14;
constexpr uint8_t kIntEn0 = 0x15;    // bit 7 data, bit 6 fifo
constexpr uint8_t kIntEn1 = 0x16;    // bit 0 int3 active high, bit 1 int3 open drain
constexpr uint8_t kIntMap1 = 0x18;   // bit 0 int3_data, bit 2 int3_fifo
constexpr uint8_t kFifoWmEn = 0x1E;  // bit 7 fifo watermark interrupt enable
constexpr uint8_t kIntRstLatch = 0x21;
constexpr uint8_t kWdt = 0x34;          // bit 2 i2c watchdog enable, bit 1 select 50 ms
constexpr uint8_t kBist = 0x3C;         // bit 0 trigger, bit 1 ready, bit 2 fail, bit 4 rate_ok
constexpr uint8_t kFifoConfig0 = 0x3D;  // bit 7 tag, bits 6:0 watermark level (frames)
constexpr uint8_t kFifoConfig1 = 0x3E;  // bits 7:6 mode (0 bypass, 1 fifo, 2 stream), bits 1:0 data select
constexpr uint8_t kFifoData = 0x3F;

constexpr int kFifoDepthFrames = 100;
constexpr int kFrameBytes = 6;

// RANGE codes: full scale and sensitivity (16.4 .. 262.4 LSB/(deg/s)).
enum class Range : uint8_t {
  k2000dps = 0x00,
  k1000dps = 0x01,
  k500dps = 0x02,
  k250dps = 0x03,
  k125dps = 0x04
};
constexpr double range_dps(Range r) {
  return r == Range::k2000dps   ? 2000.0
         : r == Range::k1000dps ? 1000.0
         : r == Range::k500dps  ? 500.0
         : r == Range::k250dps  ? 250.0
                                : 125.0;
}
// 61.0 / 30.5 / 15.3 / 7.6 / 3.8 mdeg/s per LSB: full scale over 2^15 counts.
constexpr double lsb_mdps(Range r) { return range_dps(r) * 1000.0 / 32768.0; }

// BW codes: (output data rate, filter bandwidth).
enum class Bandwidth : uint8_t {
  k2000Hz_523Hz = 0x00,  // unfiltered
  k2000Hz_230Hz = 0x01,
  k1000Hz_116Hz = 0x02,
  k400Hz_47Hz = 0x03,
  k200Hz_23Hz = 0x04,
  k100Hz_12Hz = 0x05,
  k200Hz_64Hz = 0x06,
  k100Hz_32Hz = 0x07
};
constexpr double odr_hz(Bandwidth b) {
  constexpr double kOdrHz[8] = {2000, 2000, 1000, 400, 200, 100, 200, 100};
  return kOdrHz[static_cast<unsigned>(b) & 7u];
}
constexpr double bandwidth_hz(Bandwidth b) {
  constexpr double kBandwidthHz[8] = {523, 230, 116, 47, 23, 12, 64, 32};
  return kBandwidthHz[static_cast<unsigned>(b) & 7u];
}
constexpr uint8_t kBwReadOnlyMask = 0x80;
constexpr uint8_t kFifoModeStream = 0x80;
constexpr uint8_t kBistTrigger = 0x01;
constexpr uint8_t kBistReady = 0x02;
constexpr uint8_t kBistFail = 0x04;
}  // namespace gyro

// ---- magnetometer (BMM150) ----------------------------------------------------------
// Optional: probed and reported; compensated output needs the trim registers
// (0x5D..0x71) and is not produced yet (docs/drivers/bmx055.md, "gaps").
namespace mag {
constexpr uint8_t kChipIdReg = 0x40;  // readable only once power control bit is set
constexpr uint8_t kChipId = 0x32;
constexpr uint8_t kDataXLsb = 0x42;   // x 13 bit, y 13 bit, z 15 bit, rhall 14 bit
constexpr uint8_t kPowerCtrl = 0x4B;  // bit 0 power control; bits 7 and 1 soft reset
constexpr uint8_t kOpMode = 0x4C;     // bits 5:3 data rate (0 = 10 Hz), bits 2:1 mode (0 normal, 3 sleep)
constexpr uint8_t kPowerOn = 0x01;
constexpr uint8_t kSoftReset = 0x83;
}  // namespace mag

}  // namespace kestrel::drivers::bmx055

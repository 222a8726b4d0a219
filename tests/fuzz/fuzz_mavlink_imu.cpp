// The flight controller's IMU driver's receive path on any bytes
// (tests/mavlink/mavlink_imu_fuzz_entry.hpp holds the invariants). Seeds: for
// each message kind, unsigned and signed, the TIMESYNC answers that bring the
// driver's clock estimate to converge, the COMMAND_ACK, then a stream of IMU
// messages, as the simulated autopilot of tests/mavlink sends them.
#include "fuzz_target.hpp"
#include "mavlink_imu_fuzz_entry.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::test::mavlink_imu_fuzz_one(data, size);
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  namespace km = kestrel::mavlink;
  size_t n = 0;
  for (uint8_t mode : {0, 1, 2, 4, 5, 6}) {
    km::MavlinkSigning sign(kestrel::test::fuzz_signing_key(), 3, &kestrel::test::fuzz_signing_clock);
    km::MavlinkSigning* s = (mode & 4) != 0 ? &sign : nullptr;
    std::string bytes(1, static_cast<char>(mode));
    uint8_t f[km::kMaxFrameBytes];
    uint8_t seq = 0;
    auto add = [&](std::size_t len) { bytes.append(reinterpret_cast<const char*>(f), len); };
    for (int i = 0; i < 6; ++i) {
      km::TimesyncMsg t;
      t.tc1 = 5'000'000'000 + i;
      t.ts1 = kestrel::test::kFuzzHostNs;
      t.target_system = 1;
      t.target_component = 191;
      add(km::encode_timesync(t, seq++, 1, 1, f, s));
    }
    km::CommandAckMsg a;
    a.command = km::kMavCmdSetMessageInterval;
    add(km::encode_command_ack(a, seq++, 1, 1, f, s));
    for (int i = 0; i < 20; ++i) {
      const uint64_t t_us = 5'000'000 + 5000 * static_cast<uint64_t>(i) - 100'000;
      if (mode % 4 == 0) {
        km::HighresImuMsg m;
        m.time_usec = t_us;
        m.xacc = 0.1f * i, m.zacc = -9.8f, m.zgyro = 0.01f * i;
        add(km::encode_highres_imu(m, seq++, 1, 1, f, s));
      } else if (mode % 4 == 1) {
        km::ScaledImuMsg m;
        m.time_boot_ms = static_cast<uint32_t>(t_us / 1000);
        m.zacc = -1000, m.xgyro = static_cast<int16_t>(i);
        add(km::encode_scaled_imu(m, seq++, 1, 1, f, s));
      } else {
        km::RawImuMsg m;
        m.time_usec = t_us;
        m.zacc = -4096, m.ygyro = static_cast<int16_t>(3 * i);
        add(km::encode_raw_imu(m, seq++, 1, 1, f, s));
      }
    }
    write_file(dir + "/imu_mode" + std::to_string(mode) + ".bin", bytes);
    ++n;
  }
  return n;
}

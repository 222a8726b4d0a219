// Any byte string through the MAVLink v2 decoder (tests/mavlink/mavlink_fuzz_entry.hpp
// holds the invariants). Seeds: HEARTBEAT and TIMESYNC frames as the link
// sends them, one stream of each and one interleaved.
#include "fuzz_target.hpp"
#include "kestrel/drivers/mavlink/mavlink_v2.hpp"
#include "mavlink_fuzz_entry.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::test::mavlink_fuzz_one(data, size);
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  namespace km = kestrel::mavlink;
  std::string hb, ts, both;
  uint8_t f[km::kMaxFrameBytes];
  for (int i = 0; i < 4; ++i) {
    km::TimesyncMsg t;
    t.tc1 = i;
    t.ts1 = 1000 * i;
    const std::string a(reinterpret_cast<const char*>(f),
                        km::encode_timesync(t, static_cast<uint8_t>(i), 1, 1, f));
    km::HeartbeatMsg h;
    const std::string b(reinterpret_cast<const char*>(f),
                        km::encode_heartbeat(h, static_cast<uint8_t>(i), 1, 1, f));
    ts += a;
    hb += b;
    both += a + b;
  }
  write_file(dir + "/heartbeat.bin", hb);
  write_file(dir + "/timesync.bin", ts);
  write_file(dir + "/interleaved.bin", both);
  return 3;
}

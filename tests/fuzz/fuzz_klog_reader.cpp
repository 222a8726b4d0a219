// Any byte string as a .klog, strict and salvaging (tests/log/klog_fuzz_entry.hpp
// holds the invariants; the unit suite runs the same entry on mutations).
// Seeds: the log fixture every record type is written by, and two cuts of it,
// so the fuzzer starts past the magic and the CRCs; and a log whose images
// are compressed (zstd and lz4, version 2), so it reaches the decoders.
#include "fuzz_target.hpp"
#include "klog_fuzz_entry.hpp"
#include "log_fixtures.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::test::klog_fuzz_one(data, size, false);
  kestrel::test::klog_fuzz_one(data, size, true);
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  std::vector<kestrel::test::RecordSpan> spans;
  kestrel::test::write_small_klog(dir + "/small.klog", &spans);
  const auto bytes = kestrel::test::read_bytes(dir + "/small.klog");
  kestrel::test::write_bytes(dir + "/head3.klog", bytes.data(), spans[3].begin);
  kestrel::test::write_bytes(dir + "/cut.klog", bytes.data(), spans[4].begin + 20);
  kestrel::test::write_compressed_klog(dir + "/compressed.klog", nullptr);
  return 4;
}

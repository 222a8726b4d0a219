// Writes the seed corpus for fuzz_klog_reader: the small fixture log and two
// cut-down variants, so the fuzzer starts past the magic and the CRCs.
#include <cstdio>
#include <string>

#include "log_fixtures.hpp"

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: %s CORPUS_DIR\n", argv[0]);
    return 2;
  }
  const std::string dir = argv[1];
  std::vector<kestrel::test::RecordSpan> spans;
  kestrel::test::write_small_klog(dir + "/small.klog", &spans);
  const auto bytes = kestrel::test::read_bytes(dir + "/small.klog");
  kestrel::test::write_bytes(dir + "/head3.klog", bytes.data(), spans[3].begin);
  kestrel::test::write_bytes(dir + "/cut.klog", bytes.data(), spans[4].begin + 20);
  return 0;
}

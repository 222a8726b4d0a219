// libFuzzer target: any byte string as a .klog, strict and salvaging.
// Built only with -DKESTREL_BUILD_FUZZ=ON and clang.
#include <cstddef>
#include <cstdint>

#include "klog_fuzz_entry.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::test::klog_fuzz_one(data, size, false);
  kestrel::test::klog_fuzz_one(data, size, true);
  return 0;
}

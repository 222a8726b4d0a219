// libFuzzer target: any byte string through the MAVLink v2 decoder.
// Built only with -DKESTREL_BUILD_FUZZ=ON and clang.
#include <cstddef>
#include <cstdint>

#include "mavlink_fuzz_entry.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  kestrel::test::mavlink_fuzz_one(data, size);
  return 0;
}

// The one entry point shared by the libFuzzer target and the unit-suite
// mutation test: read a byte buffer as a klog and touch everything recovered.
#pragma once

#include <cstdint>
#include <cstdlib>
#include <stdexcept>
#include <vector>

#include "kestrel/drivers/klog.hpp"

namespace kestrel::test {

struct KlogFuzzResult {
  bool opened = false;
  std::vector<uint64_t> offsets;  // of every record recovered, in order
  std::vector<drivers::RecordType> types;
  size_t problems = 0;
  uint64_t checksum = 0;
};

inline KlogFuzzResult klog_fuzz_one(const uint8_t* data, size_t size, bool salvage) {
  KlogFuzzResult res;
  std::unique_ptr<drivers::KlogReader> reader;
  try {
    reader = drivers::KlogReader::from_memory(data, size, "fuzz", drivers::KlogReader::Options{salvage});
  } catch (const std::runtime_error&) {
    return res;  // a damaged header is allowed to refuse; anything else escapes and is a finding
  }
  res.opened = true;
  // Each record consumes at least its 16-byte header, so more records than
  // this means the reader is looping.
  const size_t bound = size / 16 + 1;
  drivers::LogRecord r;
  uint64_t checksum = 0;
  for (int pass = 0; pass < 2; ++pass) {
    size_t n = 0;
    while (reader->next(r)) {
      if (++n > bound) std::abort();
      if (pass == 0) {
        res.offsets.push_back(r.offset);
        res.types.push_back(r.type);
      } else if (n > res.offsets.size() || res.offsets[n - 1] != r.offset) {
        std::abort();  // rewind must replay the same records
      }
      if (r.type == drivers::RecordType::kRgb || r.type == drivers::RecordType::kDepth) {
        const auto v = r.image.view();
        if (static_cast<size_t>(v.stride_bytes) * static_cast<size_t>(v.height) != r.image.pixels.size())
          std::abort();
        for (uint8_t b : r.image.pixels) checksum += b;
      }
      checksum += static_cast<uint64_t>(r.imu.t_ns) + r.event.text.size();
    }
    if (n != res.offsets.size()) std::abort();
    reader->rewind();
  }
  res.problems = reader->problems().size();
  res.checksum = checksum;  // keeps the reads of every field observable
  return res;
}

}  // namespace kestrel::test

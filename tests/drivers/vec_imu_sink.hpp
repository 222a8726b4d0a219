// An ImuSink that keeps everything, for driver tests (capacity lets a test
// make the ring look full).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/drivers/bmx055.hpp"

namespace kestrel::test {

struct VecImuSink final : drivers::ImuSink {
  std::vector<ImuSample> samples;
  std::vector<std::string> events;
  size_t capacity = SIZE_MAX;
  bool push(const ImuSample& s) noexcept override {
    if (samples.size() >= capacity) return false;
    samples.push_back(s);
    return true;
  }
  void event(int64_t, EventCode, const char* text) noexcept override { events.emplace_back(text); }
};

}  // namespace kestrel::test

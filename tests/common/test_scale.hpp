// The one knob for sanitizer-sized runs: KESTREL_TEST_SCALE=small (the debug
// test presets set it, docs/testing.md). Under ASan + UBSan a release-sized
// flight outlasts its timeout, so the heavy tests fly a shorter flight or
// smaller images and keep every assertion, with thresholds that depend on the
// length (counts of frames, poses) scaled with it. Unset or "full": the
// release sizes. Anything else is a typo and stops the test run.
#pragma once

#include <cstdio>
#include <cstdlib>
#include <cstring>

namespace kestrel::test {

inline bool small_scale() {
  static const bool small = [] {
    const char* e = std::getenv("KESTREL_TEST_SCALE");
    if (e == nullptr || *e == '\0' || std::strcmp(e, "full") == 0) return false;
    if (std::strcmp(e, "small") == 0) {
      std::fprintf(stderr, "KESTREL_TEST_SCALE=small: sanitizer-sized flights\n");
      return true;
    }
    std::fprintf(stderr, "KESTREL_TEST_SCALE=%s: expected small or full\n", e);
    std::abort();
  }();
  return small;
}

// `full` normally, `small` under KESTREL_TEST_SCALE=small.
template <class T>
T scaled(T full, T small) {
  return small_scale() ? small : full;
}

}  // namespace kestrel::test

// Where tests find ../shared/data, and the loud skip when it is absent.
#pragma once

#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <string>

namespace kestrel::test {

inline std::string shared_data_dir() {
  if (const char* env = std::getenv("KESTREL_SHARED_DATA")) return env;
  return KESTREL_SHARED_DATA;
}

inline std::string shared_path(const std::string& rel) { return shared_data_dir() + "/" + rel; }

// A fresh scratch directory per test, removed by the caller if it wants.
inline std::string temp_dir(const std::string& name) {
  auto dir = std::filesystem::temp_directory_path() / ("kestrel_test_" + name);
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  return dir.string();
}

}  // namespace kestrel::test

// Skips the current test, loudly, when a file or folder of ../shared/data is missing.
#define KESTREL_REQUIRE_SHARED(rel)                                                              \
  do {                                                                                           \
    const std::string kestrel_p_ = ::kestrel::test::shared_path(rel);                            \
    if (!std::filesystem::exists(kestrel_p_)) {                                                  \
      std::fprintf(stderr, "SKIPPED: ../shared/data not found (%s)\n", kestrel_p_.c_str());      \
      GTEST_SKIP() << "SKIPPED: ../shared/data not found (" << kestrel_p_ << ")";               \
    }                                                                                            \
  } while (0)

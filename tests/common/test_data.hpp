// Where tests find ../shared/data, and the loud skip when it is absent.
#pragma once

#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <system_error>
#include <vector>

namespace kestrel::test {

// The process's resident set now [MB] (soak tests).
inline double rss_mb() {
  std::ifstream f("/proc/self/statm");
  long pages_total = 0, pages_rss = 0;
  f >> pages_total >> pages_rss;
  return static_cast<double>(pages_rss) * static_cast<double>(sysconf(_SC_PAGESIZE)) / (1024.0 * 1024.0);
}

inline std::string shared_data_dir() {
  if (const char* env = std::getenv("KESTREL_SHARED_DATA")) return env;
  return KESTREL_SHARED_DATA;
}

inline std::string shared_path(const std::string& rel) { return shared_data_dir() + "/" + rel; }

// A fresh folder for this process: ctest runs every test as its own process,
// two at a time, and two tests asking for the same name must not empty each
// other's folder (a reader once saw 94 of 300 frames of a log another test was
// still writing).
// Removed when the process exits normally, as per-process names would
// otherwise leave gigabytes of logs behind every run.
struct TempDirs {
  std::vector<std::filesystem::path> dirs;
  ~TempDirs() {
    std::error_code ec;
    for (const auto& d : dirs) std::filesystem::remove_all(d, ec);
  }
};
inline TempDirs& temp_dirs() {
  static TempDirs t;
  return t;
}

inline std::string temp_dir(const std::string& name) {
  auto dir = std::filesystem::temp_directory_path() /
             ("kestrel_test_" + name + "_" + std::to_string(static_cast<long>(getpid())));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  temp_dirs().dirs.push_back(dir);
  return dir.string();
}

}  // namespace kestrel::test

// Skips the current test, loudly, when a file or folder of ../shared/data is missing.
#define KESTREL_REQUIRE_SHARED(rel)                                                         \
  do {                                                                                      \
    const std::string kestrel_p_ = ::kestrel::test::shared_path(rel);                       \
    if (!std::filesystem::exists(kestrel_p_)) {                                             \
      std::fprintf(stderr, "SKIPPED: ../shared/data not found (%s)\n", kestrel_p_.c_str()); \
      GTEST_SKIP() << "SKIPPED: ../shared/data not found (" << kestrel_p_ << ")";           \
    }                                                                                       \
  } while (0)

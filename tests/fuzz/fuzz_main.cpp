// main() of fuzz_<name>_corpus: the target without libFuzzer, for the seed
// corpus, the regression replay the unit suite runs, and replaying a crash
// file by hand under a debugger.
#include <algorithm>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <string>
#include <system_error>
#include <vector>

#include "fuzz_target.hpp"

namespace {

namespace fs = std::filesystem;

// Files of `path` (itself, or every regular file under it), sorted: a replay
// is the same run every time.
std::vector<std::string> inputs_of(const std::string& path) {
  std::vector<std::string> v;
  if (fs::is_directory(path)) {
    for (const auto& e : fs::recursive_directory_iterator(path))
      if (e.is_regular_file() && e.path().filename().string()[0] != '.') v.push_back(e.path().string());
    std::sort(v.begin(), v.end());
  } else if (fs::is_regular_file(path)) {
    v.push_back(path);
  } else {
    std::fprintf(stderr, "fuzz: %s: no such file or folder\n", path.c_str());
    std::exit(2);
  }
  return v;
}

size_t replay(const std::vector<std::string>& paths) {
  size_t n = 0;
  for (const auto& p : paths)
    for (const auto& f : inputs_of(p)) {
      const std::string bytes = kestrel::fuzz::read_file(f);
      std::fprintf(stderr, "replay %s (%zu bytes)\n", f.c_str(), bytes.size());
      LLVMFuzzerTestOneInput(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
      ++n;
    }
  return n;
}

int usage(const char* argv0) {
  std::fprintf(
      stderr,
      "usage: %s seeds DIR        write the seed corpus into DIR\n"
      "       %s replay PATH...   run files (or every file under folders) through the target\n"
      "       %s check [--regressions DIR] [PATH...]\n"
      "                            seeds into a scratch folder, then replay them, DIR's files (a\n"
      "                            missing DIR is none yet) and PATH...: the unit test fuzz_replay_<name>\n",
      argv0, argv0, argv0);
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) return usage(argv[0]);
  const std::string cmd = argv[1];
  std::vector<std::string> rest(argv + 2, argv + argc);
  if (cmd == "seeds" && rest.size() == 1) {
    fs::create_directories(rest[0]);
    const size_t n = kestrel::fuzz::write_seeds(rest[0]);
    std::printf("%zu seeds in %s\n", n, rest[0].c_str());
    return n > 0 ? 0 : 1;
  }
  if (cmd == "replay" && !rest.empty()) {
    std::printf("replayed %zu inputs\n", replay(rest));
    return 0;
  }
  if (cmd == "check") {
    if (rest.size() >= 2 && rest[0] == "--regressions") {
      const std::string reg = rest[1];
      rest.erase(rest.begin(), rest.begin() + 2);
      if (fs::is_directory(reg)) {
        rest.insert(rest.begin(), reg);
      } else {
        std::printf("no regressions yet (%s)\n", reg.c_str());
      }
    }
    const std::string dir = kestrel::fuzz::scratch_dir("seeds");
    const size_t seeds = kestrel::fuzz::write_seeds(dir);
    if (seeds == 0) {
      std::fprintf(stderr, "fuzz: the target wrote no seeds\n");
      return 1;
    }
    rest.insert(rest.begin(), dir);
    const size_t n = replay(rest);
    std::error_code ec;
    fs::remove_all(dir, ec);
    std::printf("replayed %zu inputs (%zu seeds)\n", n, seeds);
    return 0;
  }
  return usage(argv[0]);
}

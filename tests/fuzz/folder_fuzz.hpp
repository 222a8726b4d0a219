// What the dataset-folder targets share: an input unpacked into the reader's
// text files in a scratch folder, the reader built and drained twice, and
// seeds made by exporting the log fixture to the format (drivers/datasets
// log_export), so the tests' own fixture is the fuzzer's starting point.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "fuzz_target.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "log_fixtures.hpp"

namespace kestrel::fuzz {

// Replays every record twice (rewind must replay the same stream); returns the count.
inline size_t drain_twice(drivers::LogSource& src, size_t input_bytes) {
  // Every record comes from at least one line of at least two bytes (a
  // digit and its newline), so more than this means the reader loops.
  const size_t bound = input_bytes / 2 + 1;
  drivers::LogRecord r;
  size_t first = 0;
  for (int pass = 0; pass < 2; ++pass) {
    size_t n = 0;
    while (src.next(r)) {
      if (++n > bound) std::abort();
      if (r.type == drivers::RecordType::kRgb || r.type == drivers::RecordType::kDepth ||
          r.type == drivers::RecordType::kRight) {
        const auto v = r.image.view();
        if (static_cast<size_t>(v.stride_bytes) * static_cast<size_t>(v.height) != r.image.pixels.size())
          std::abort();
      }
    }
    if (pass == 0) first = n;
    if (pass == 1 && n != first) std::abort();
    src.rewind();
  }
  src.problems();
  return first;
}

// One input: the files `names` of a folder; `open` builds the reader over it.
// A reader may refuse the folder (std::runtime_error); anything else escapes.
template <class Open>
size_t fuzz_folder(const std::string& target, const std::vector<std::string>& names, const uint8_t* data,
                   size_t size, Open open) {
  const std::string dir = scratch_dir(target);
  write_parts(dir, names, unpack(data, size, names.size()));
  std::unique_ptr<drivers::LogSource> src;
  try {
    src = open(dir);
  } catch (const std::runtime_error&) {
    return 0;
  }
  return drain_twice(*src, size);
}

// The log fixture exported by `export_fn` into a scratch folder; returns the folder.
template <class Export>
std::string exported_fixture(const std::string& target, Export export_fn) {
  const std::string dir = scratch_dir(target + "_seed");
  test::write_small_klog(dir + "/fixture.klog", nullptr);
  drivers::KlogReader reader(dir + "/fixture.klog");
  export_fn(reader, dir + "/out");
  return dir + "/out";
}

// A seed that is not read back into records is no start for the fuzzer.
template <class Open>
void write_folder_seed(const std::string& path, const std::string& target,
                       const std::vector<std::string>& names, const std::string& packed, Open open) {
  write_file(path, packed);
  const size_t n =
      fuzz_folder(target, names, reinterpret_cast<const uint8_t*>(packed.data()), packed.size(), open);
  if (n == 0) {
    std::fprintf(stderr, "fuzz: seed %s gives no records\n", path.c_str());
    std::exit(1);
  }
}

// The seed of a format Kestrel exports: the log fixture through `export_fn`, packed.
template <class Export, class Open>
size_t write_exported_seed(const std::string& dir, const std::string& target,
                           const std::vector<std::string>& names, Export export_fn, Open open) {
  const std::string out = exported_fixture(target, export_fn);
  write_folder_seed(dir + "/exported.bin", target, names, pack_folder(out, names), open);
  return 1;
}

}  // namespace kestrel::fuzz

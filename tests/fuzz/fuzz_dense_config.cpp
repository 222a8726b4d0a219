// Any text as the config's `dense:` and `viewer:` sections (tools/dense, docs/dense.md).
// Refusing is allowed (std::runtime_error naming the file and key); a section
// it accepts must print (dense_options_table) to YAML that loads to the same print.
// Seeds: the defaults printed, and a few edited values.
#include "fuzz_target.hpp"
#include "kestrel/dense/dense_config.hpp"

namespace {
std::string to_yaml(const kestrel::dense::DenseOptions& o) {
  std::string s = "dense:\n";
  for (const auto& [k, v] : kestrel::dense::dense_options_table(o)) s += "  " + k.substr(6) + ": " + v + "\n";
  return s;
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  // The `viewer:` section (viewer.dense_*) from the same text: refused, or valid.
  try {
    const kestrel::dense::DenseViewOptions v =
        kestrel::dense::dense_view_options_from_yaml(text, "fuzz.yaml");
    try {
      v.validate();
    } catch (const std::invalid_argument&) {
      std::abort();
    }
  } catch (const std::runtime_error&) {
  }
  kestrel::dense::DenseOptions o;
  try {
    o = kestrel::dense::dense_options_from_yaml(text, "fuzz.yaml");
  } catch (const std::runtime_error&) {
    return 0;
  }
  const auto printed = kestrel::dense::dense_options_table(o);
  const auto back = kestrel::dense::dense_options_from_yaml(to_yaml(o), "printed.yaml");
  if (kestrel::dense::dense_options_table(back) != printed) std::abort();
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  kestrel::dense::DenseOptions o;
  write_file(dir + "/defaults.yaml", to_yaml(o));
  o.enabled = true;
  o.tsdf.voxel_size_m = 0.1;
  o.tsdf.memory_budget_mb = 8;
  write_file(dir + "/edited.yaml", to_yaml(o));
  write_file(dir + "/bad_key.yaml", "dense:\n  voxel: 1\n");
  write_file(dir + "/viewer.yaml",
             "viewer:\n  dense_max_kbps: 500\n  dense_period_s: 0.2\ndense:\n  live_reanchor: true\n");
  return 4;
}

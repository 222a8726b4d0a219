// Any text as an estimator config (`kestrel ... --config`, `kestrel config`).
// Refusing is allowed (std::runtime_error naming the key); a config it
// accepts must print (--print-config) to YAML that loads to the same print.
// Seeds: the printed defaults, and the printed config of each backend.
#include "fuzz_target.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  kestrel::core::EstimatorConfig c;
  try {
    c = kestrel::tools::estimator_config_from_yaml(text, "fuzz.yaml");
  } catch (const std::runtime_error&) {
    return 0;
  }
  const std::string printed = kestrel::tools::estimator_config_to_yaml(c);
  const auto back = kestrel::tools::estimator_config_from_yaml(printed, "printed.yaml");
  if (kestrel::tools::estimator_config_to_yaml(back) != printed) std::abort();
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  size_t n = 0;
  for (const char* backend : {"auto", "window", "vo", "ekf", "rgbd"}) {
    kestrel::core::EstimatorConfig c;
    c.backend = backend;
    write_file(dir + "/" + backend + ".yaml", kestrel::tools::estimator_config_to_yaml(c));
    ++n;
  }
  return n;
}

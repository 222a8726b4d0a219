#include "kestrel/tools/map_files.hpp"

#include <fstream>
#include <iterator>
#include <memory>
#include <stdexcept>

namespace kestrel::tools {

void set_map_in(core::EstimatorConfig& c, const std::string& path) {
  core::MapSystemOptions& m = c.window.map;
  // "auto" becomes window when the log has an IMU (the caller checks afterwards that a map ran).
  if (!may_have_map(c))
    throw std::invalid_argument("--map-in needs a backend with the map (window, or ekf with --mapping on)");
  if (!m.loop)
    throw std::invalid_argument("--map-in: a loaded map is found by relocalisation, which needs --loop on");
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error(path + ": cannot open map file");
  auto bytes = std::make_shared<std::vector<uint8_t>>((std::istreambuf_iterator<char>(f)),
                                                      std::istreambuf_iterator<char>());
  m.map_in = std::move(bytes);
  m.map_in_path = path;
}

bool may_have_map(const core::EstimatorConfig& c) {
  return (c.backend == "auto" || c.backend.rfind("window", 0) == 0 ||
          (c.backend == "ekf" && c.ekf.mapping)) &&
         c.window.map.mapping;
}

void write_map_file(const std::string& path, const std::vector<uint8_t>& bytes) {
  if (bytes.empty()) throw std::runtime_error(path + ": no map to write (the backend ran without one)");
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  f.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  if (!f) throw std::runtime_error(path + ": cannot write map file");
}

}  // namespace kestrel::tools

// Map files (`--map-in`, `--map-out`, docs/map.md): core turns the map into
// bytes and back (core/map/map_file.hpp), this reads and writes them.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/core/estimator_config.hpp"

namespace kestrel::tools {

// Reads the map file for a window backend with the map (or "auto", which
// becomes one with an IMU; the caller then checks a map ran): its bytes go into
// the config (c.window.map.map_in); they are decoded, and refused with the
// file's name and the reason, when the estimator is made. Throws
// std::invalid_argument when the config has no map to load it into and
// std::runtime_error naming the file when it cannot be read.
void set_map_in(core::EstimatorConfig& c, const std::string& path);
// Writes the bytes of MapSystem::save(); throws std::runtime_error naming
// the file (and when there is no map to save).
void write_map_file(const std::string& path, const std::vector<uint8_t>& bytes);
// The backend name can run with a map ("auto" may).
bool may_have_map(const core::EstimatorConfig& c);

}  // namespace kestrel::tools

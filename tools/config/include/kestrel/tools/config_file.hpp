// One reader for a Kestrel config file (issue 45 item 5).
//
// The file is read and parsed once. Its top-level keys are checked against
// one table of sections, and each section is handed to the one module that
// owns it, which parses it into its struct:
//   rig                          drivers/rig      (inline, or the name of a rig file)
//   drivers, threads, mavlink,
//   record, ros2                 drivers/devices
//   estimator, frontend, ...     tools/config     (core's options table)
//   dense, viewer                tools/dense
// Commands, the Python module and the tests get parsed structs; nothing else
// opens the file. docs/config.md, "One file", lists the sections.
#pragma once

#include <yaml-cpp/yaml.h>

#include <optional>
#include <string>
#include <vector>

#include "kestrel/core/estimator_config.hpp"
#include "kestrel/dense/dense_config.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::tools {

struct ConfigSection {
  std::string name;   // the top-level key
  std::string owner;  // the folder whose parser reads it
  std::string what;
};
// Every top-level section a config file may hold, in the order docs/config.md lists them.
const std::vector<ConfigSection>& config_sections();

struct Config {
  std::string path;          // the file; "" for the built-in defaults
  std::optional<Rig> rig;    // `rig:` inline or `rig: FILE.yaml`; absent where a log brings its own
  bool has_drivers = false;  // the file has a `drivers:` section (live sensors need one)
  drivers::DriverSettings drivers;
  drivers::ThreadTable threads = drivers::default_thread_table();
  drivers::MavlinkSettings mavlink;
  drivers::RecordSettings record;
  drivers::Ros2Settings ros2;
  core::EstimatorConfig estimator;  // the command line's defaults with the file's keys on top
  bool backend_from_file = false;   // the file named estimator.backend and no override replaced it
  dense::DenseOptions dense;
  dense::DenseViewOptions dense_view;
  // Which of drivers.camera's size and rate the file named: a log camera
  // takes the others from the log (live_config).
  bool camera_width_named = false;
  bool camera_height_named = false;
  bool camera_rate_named = false;
};

// Throws std::runtime_error naming the file, the line where known, and the
// key: "x.yaml:4: windw: unknown section (expected one of: rig, drivers, ...)".
// backend_override (a command's --estimator) replaces estimator.backend.
Config config_from_yaml(const std::string& text, const std::string& where,
                        const std::string& backend_override = "");
// The same from a parsed document (yaml_document()), for a caller that
// looked at it first (`kestrel calib --base`: a config or a rig file?).
Config config_from_node(YAML::Node document, const std::string& where,
                        const std::string& backend_override = "");
// The same from a file; path "" gives the built-in defaults.
Config load_config(const std::string& path, const std::string& backend_override = "");

// The live sensors' sections. `drivers:` is required, and the rig unless the sensors are a
// log, whose own rig (and camera size and rate, unless the file names them)
// is used: std::runtime_error "x.yaml: rig: missing (...)".
drivers::LiveConfig live_config(const Config& c);
// config_from_yaml / load_config, then live_config.
drivers::LiveConfig live_config_from_yaml(const std::string& text, const std::string& where);
drivers::LiveConfig load_live_config(const std::string& path);

}  // namespace kestrel::tools

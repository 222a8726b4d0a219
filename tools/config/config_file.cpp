#include "kestrel/tools/config_file.hpp"

#include <yaml-cpp/yaml.h>

#include <fstream>
#include <sstream>
#include <stdexcept>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"
#include "kestrel/tools/vocabulary_files.hpp"

namespace kestrel::tools {

const std::vector<ConfigSection>& config_sections() {
  static const std::vector<ConfigSection> sections = [] {
    std::vector<ConfigSection> s = {
        {"rig", "drivers/rig", "the sensors' calibration, inline or a rig file's name (docs/log-format.md)"},
        {"drivers", "drivers/devices", "the camera, IMU and strobe devices (docs/drivers/README.md)"},
        {"threads", "drivers/devices", "each pipeline thread's scheduling and CPU (docs/threads.md)"},
        {"mavlink", "drivers/devices", "the flight-controller link (docs/px4.md)"},
        {"record", "drivers/devices", "how recordings compress images (docs/log-format.md)"},
        {"ros2", "drivers/devices", "what --mcap-out and --foxglove publish beside the poses (docs/ros2.md)"},
    };
    for (const std::string& e : estimator_config_sections())
      s.push_back({e, "tools/config", "the estimator's tunables, core's options table (docs/config.md)"});
    s.push_back({"dense", "tools/dense", "the dense map (docs/dense.md)"});
    s.push_back({"viewer", "tools/dense", "the dense map's stream to the live viewer (docs/dense.md)"});
    return s;
  }();
  return sections;
}

namespace {

std::string section_names() {
  std::string s;
  for (const ConfigSection& c : config_sections()) s += (s.empty() ? "" : ", ") + c.name;
  return s;
}

// The document's top-level keys against the table: a misspelt section is an
// error, never a section silently ignored.
void check_sections(const YAML::Node& root, const std::string& where) {
  for (const auto& kv : root) {
    const std::string k = kv.first.Scalar();
    bool known = false;
    for (const ConfigSection& c : config_sections()) known = known || c.name == k;
    if (!known) {
      throw std::runtime_error(where + ":" + std::to_string(kv.first.Mark().line + 1) + ": " + k +
                               ": unknown section (expected one of: " + section_names() + ")");
    }
  }
}

Rig rig_section(const YAML::Node& node, const std::string& where) {
  if (!node.IsScalar()) return drivers::rig_from_yaml_node(node, where, "rig.");
  // A rig file of its own (what `kestrel calib import-kalibr` writes), relative to this config.
  std::string file = node.Scalar();
  const auto slash = where.rfind('/');
  if (!file.empty() && file[0] != '/' && slash != std::string::npos) file = where.substr(0, slash + 1) + file;
  return drivers::load_rig_file(file);
}

}  // namespace

Config config_from_yaml(const std::string& text, const std::string& where,
                        const std::string& backend_override) {
  return config_from_node(yaml_document(text, where), where, backend_override);
}

Config config_from_node(YAML::Node parsed, const std::string& where, const std::string& backend_override) {
  if (parsed.IsNull()) parsed = YAML::Node(YAML::NodeType::Map);
  // Looked up through const from here: operator[] on a non-const node may insert the key.
  const YAML::Node& root = parsed;
  if (!root.IsMap()) throw std::runtime_error(where + ": expected a mapping of sections (docs/config.md)");
  check_sections(root, where);
  Config c;
  c.path = where;
  try {
    if (root["rig"]) c.rig = rig_section(root["rig"], where);
    // Optional here (replay has no devices); live_config requires it.
    c.has_drivers = static_cast<bool>(root["drivers"]);
    if (c.has_drivers) c.drivers = drivers::driver_settings_from_yaml_node(root["drivers"], where);
    // A key missing under const access is an invalid node, which throws on
    // anything but IsDefined(): each lookup below checks that first.
    const YAML::Node drv = root["drivers"];
    const YAML::Node cam = drv.IsDefined() && drv.IsMap() ? drv["camera"] : YAML::Node();
    const bool cam_map = cam.IsDefined() && cam.IsMap();
    c.camera_width_named = cam_map && cam["width_px"].IsDefined();
    c.camera_height_named = cam_map && cam["height_px"].IsDefined();
    c.camera_rate_named = cam_map && cam["rate_hz"].IsDefined();
    c.threads = drivers::thread_table_from_yaml_node(root["threads"], where);
    c.mavlink = drivers::mavlink_settings_from_yaml_node(root["mavlink"], where);
    c.record = drivers::record_settings_from_yaml_node(root["record"], where);
    c.ros2 = drivers::ros2_settings_from_yaml_node(root["ros2"], where);
    c.estimator = estimator_config_from_node(root, where, backend_override);
    const YAML::Node est = root["estimator"];
    c.backend_from_file =
        backend_override.empty() && est.IsDefined() && est.IsMap() && est["backend"].IsDefined();
    c.dense = dense::dense_options_from_node(root["dense"], where);
    c.dense_view = dense::dense_view_options_from_node(root["viewer"], where);
  } catch (const YAML::Exception& e) {
    // Structural surprises yaml-cpp finds before a section's parser does.
    throw std::runtime_error(where + ": " + e.what());
  }
  resolve_vocabulary(c.estimator);
  return c;
}

Config load_config(const std::string& path, const std::string& backend_override) {
  if (path.empty()) {
    Config c = config_from_yaml("{}", "(defaults)", backend_override);
    c.path.clear();
    return c;
  }
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error(path + ": cannot open config file");
  std::ostringstream s;
  s << f.rdbuf();
  return config_from_yaml(s.str(), path, backend_override);
}

drivers::LiveConfig live_config(const Config& c) {
  const std::string where = c.path.empty() ? std::string("(defaults)") : c.path;
  if (!c.has_drivers) throw std::runtime_error(where + ": drivers: missing (required for live sensors)");
  drivers::LiveConfig l;
  l.path = c.path;
  l.drivers = c.drivers;
  l.threads = c.threads;
  l.mavlink = c.mavlink;
  l.record = c.record;
  l.ros2 = c.ros2;
  const bool log = c.drivers.camera.type == drivers::CameraType::kLog;
  if (c.rig) {
    l.rig = *c.rig;
  } else if (log) {
    l.rig = drivers::KlogReader(c.drivers.log_path).rig();  // a log plays with its own rig
  } else {
    throw std::runtime_error(where + ": rig: missing (required unless the sensors are a log)");
  }
  if (log) {
    // The log's camera size and rate unless the file names them.
    drivers::CameraSettings& cs = l.drivers.camera;
    if (!c.camera_width_named && l.rig.rgb.width > 0) cs.width_px = l.rig.rgb.width;
    if (!c.camera_height_named && l.rig.rgb.height > 0) cs.height_px = l.rig.rgb.height;
    if (!c.camera_rate_named && l.rig.camera_rate_hz > 0) cs.rate_hz = l.rig.camera_rate_hz;
  }
  return l;
}

drivers::LiveConfig live_config_from_yaml(const std::string& text, const std::string& where) {
  return live_config(config_from_yaml(text, where));
}

drivers::LiveConfig load_live_config(const std::string& path) { return live_config(load_config(path)); }

}  // namespace kestrel::tools

// `kestrel calib import-kalibr CAMCHAIN IMU --out RIG`: Kalibr's camera-IMU
// calibration as a Kestrel rig file (the mapping: drivers/rig kalibr.hpp,
// docs/own-sensors.md). Fields Kalibr has no place for come from --base and
// are listed, so nothing is defaulted silently.
#include <cstdio>
#include <fstream>
#include <memory>
#include <string>

#include <yaml-cpp/yaml.h>

#include "kestrel/commands.hpp"
#include "kestrel/drivers/kalibr.hpp"
#include "kestrel/drivers/rig_yaml.hpp"

namespace kestrel::cli {
namespace {

struct CalibArgs {
  std::string camchain, imu, out, camera = "cam0", base;
};

// A rig file, or a live config's `rig:` section.
Rig load_base_rig(const std::string& path) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const YAML::BadFile&) {
    throw UsageError("--base " + path + ": cannot open");
  } catch (const YAML::ParserException& e) {
    throw std::runtime_error(path + ":" + std::to_string(e.mark.line + 1) + ": YAML syntax error: " + e.msg);
  }
  if (root.IsMap() && root["rig"] && root["rig"].IsMap()) return drivers::rig_from_yaml_node(root["rig"], path, "rig.");
  return drivers::load_rig_file(path);
}

}  // namespace

Subcommand add_calib_command(CLI::App& parent) {
  auto a = std::make_shared<CalibArgs>();
  CLI::App* app = parent.add_subcommand("calib", "calibration: import Kalibr's camera-IMU calibration as a rig file");
  app->require_subcommand(1, 1);
  CLI::App* imp = app->add_subcommand(
      "import-kalibr", "Kalibr's camchain-imucam.yaml + imu.yaml -> a Kestrel rig YAML (T_cam_imu inverted to T_BC)");
  imp->add_option("camchain", a->camchain, "Kalibr camera chain (camchain-imucam-*.yaml)")->required();
  imp->add_option("imu", a->imu, "Kalibr IMU file (imu.yaml, or the imu-*.yaml of its results)")->required();
  imp->add_option("--out", a->out, "rig YAML to write (use it as a live config's `rig: FILE`)")->required();
  imp->add_option("--camera", a->camera, "the colour camera's entry in the chain")->capture_default_str();
  imp->add_option("--base", a->base,
                  "rig file or live config (configs/*.yaml) giving what Kalibr does not: depth model, camera rate, "
                  "IMU ranges, name (default: Kestrel's defaults, 30 Hz)");
  imp->footer(
      "Example:\n  kestrel calib import-kalibr camchain-imucam-run1.yaml imu.yaml --base "
      "configs/realsense_v4l2_bmx055_usb.yaml --out configs/my_rig.yaml\n"
      "Mapping and what to check afterwards: docs/own-sensors.md");
  Subcommand s;
  s.app = app;
  s.run = [a]() -> int {
    Rig base;
    base.camera_rate_hz = 30.0;
    if (!a->base.empty()) base = load_base_rig(a->base);
    const drivers::KalibrImport imp = drivers::import_kalibr(a->camchain, a->imu, a->camera, base);
    std::ofstream f(a->out);
    f << "# Imported by `kestrel calib import-kalibr` from " << a->camchain << " (" << a->camera << ") and " << a->imu
      << ".\n# T_BC is Kalibr's T_cam_imu inverted; time_offset_cam_imu_ns is its timeshift_cam_imu (t_imu = t_cam "
         "+ offset).\n# Not from Kalibr (";
    f << (a->base.empty() ? std::string("Kestrel's defaults") : a->base) << "):\n";
    for (const std::string& n : imp.notes) f << "#   " << n << "\n";
    f << drivers::rig_to_yaml(imp.rig);
    f.close();
    if (!f) throw std::runtime_error(a->out + ": cannot write");
    // The rig must read back as written: the file is what the drivers will load.
    const Rig back = drivers::load_rig_file(a->out);
    if (!drivers::rig_equal(back, imp.rig)) throw std::runtime_error(a->out + ": does not read back to the same rig");
    std::printf("wrote %s: %dx%d, fx %.3f fy %.3f cx %.3f cy %.3f px, %s distortion, time offset %.3f ms, IMU %.1f Hz\n",
                a->out.c_str(), imp.rig.rgb.width, imp.rig.rgb.height, imp.rig.rgb.fx, imp.rig.rgb.fy, imp.rig.rgb.cx,
                imp.rig.rgb.cy, drivers::distortion_name(imp.rig.rgb.distortion),
                1e-6 * static_cast<double>(imp.rig.time_offset_cam_imu_ns), imp.rig.imu_rate_hz);
    std::printf("not in Kalibr's files (from %s):\n", a->base.empty() ? "Kestrel's defaults" : a->base.c_str());
    for (const std::string& n : imp.notes) std::printf("  %s\n", n.c_str());
    return 0;
  };
  return s;
}

}  // namespace kestrel::cli

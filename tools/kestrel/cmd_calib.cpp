// `kestrel calib import-kalibr CAMCHAIN IMU --out RIG`: Kalibr's camera-IMU
// calibration as a Kestrel rig file (the mapping: drivers/rig kalibr.hpp,
// docs/own-sensors.md). Fields Kalibr has no place for come from --base and
// are listed, so nothing is defaulted silently.
#include <yaml-cpp/yaml.h>

#include <cstdio>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>

#include "kestrel/commands.hpp"
#include "kestrel/drivers/kalibr.hpp"
#include "kestrel/drivers/realsense_import.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/tools/config_file.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"

namespace kestrel::cli {
namespace {

struct CalibArgs {
  std::string camchain, imu, out, camera = "cam0", base;
};

struct RealSenseArgs {
  std::string dump, out, base, camera = "color", size, depth_size;
  double accel_rate_hz = 250, gyro_rate_hz = 200;
};

// "640x480" -> 640, 480.
void parse_size(const std::string& s, const std::string& option, int& w, int& h) {
  if (s.empty()) return;
  char x = 0;
  int a = 0, b = 0;
  char rest = 0;
  if (std::sscanf(s.c_str(), "%d%c%d%c", &a, &x, &b, &rest) != 3 || x != 'x' || a < 1 || b < 1)
    throw UsageError(option + " " + s + ": expected WIDTHxHEIGHT, e.g. 640x480");
  w = a;
  h = b;
}

// A rig file, or a config file's `rig:` section: read and parsed once.
Rig load_base_rig(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) throw UsageError("--base " + path + ": cannot open");
  std::ostringstream text;
  text << f.rdbuf();
  const YAML::Node root = tools::yaml_document(text.str(), path);
  // A config goes through the one reader (every section checked, `rig: FILE` followed).
  if (root.IsMap() && root["rig"]) return *tools::config_from_node(root, path).rig;
  try {
    return drivers::rig_from_yaml_node(root, path);
  } catch (const YAML::Exception& e) {
    throw std::runtime_error(path + ": " + e.what());  // as drivers::rig_from_yaml reports it
  }
}

}  // namespace

Subcommand add_calib_command(CLI::App& parent) {
  auto a = std::make_shared<CalibArgs>();
  CLI::App* app = parent.add_subcommand("calib",
                                        "calibration: import Kalibr's camera-IMU calibration or a "
                                        "RealSense's factory calibration as a rig file");
  app->require_subcommand(1, 1);
  CLI::App* imp = app->add_subcommand(
      "import-kalibr",
      "Kalibr's camchain-imucam.yaml + imu.yaml -> a Kestrel rig YAML (T_cam_imu inverted to T_BC)");
  imp->add_option("camchain", a->camchain, "Kalibr camera chain (camchain-imucam-*.yaml)")->required();
  imp->add_option("imu", a->imu, "Kalibr IMU file (imu.yaml, or the imu-*.yaml of its results)")->required();
  imp->add_option("--out", a->out, "rig YAML to write (use it as a live config's `rig: FILE`)")->required();
  imp->add_option("--camera", a->camera, "the colour camera's entry in the chain")->capture_default_str();
  imp->add_option(
      "--base", a->base,
      "rig file or live config (configs/*.yaml) giving what Kalibr does not: depth model, camera rate, "
      "IMU ranges, name (default: Kestrel's defaults, 30 Hz)");
  imp->footer(
      "Example:\n  kestrel calib import-kalibr camchain-imucam-run1.yaml imu.yaml --base "
      "configs/realsense_v4l2_bmx055_usb.yaml --out configs/my_rig.yaml\n"
      "Mapping and what to check afterwards: docs/own-sensors.md");
  // ---- import-realsense ----
  auto r = std::make_shared<RealSenseArgs>();
  CLI::App* rs = app->add_subcommand(
      "import-realsense",
      "a RealSense D4xx's factory calibration (`rs-enumerate-devices -c` output) -> a Kestrel rig YAML");
  rs->add_option("dump", r->dump, "the text `rs-enumerate-devices -c > DUMP` printed")->required();
  rs->add_option("--out", r->out, "rig YAML to write (use it as a live config's `rig: FILE`)")->required();
  rs->add_option(
      "--base", r->base,
      "rig file or live config giving what the dump does not (depth unit and range, IMU random walks and "
      "ranges, camera rate): configs/realsense_d435i.yaml or configs/realsense_d455.yaml");
  rs->add_option("--camera", r->camera, "the rig's camera: color, or infrared1 (depth is in its frame)")
      ->capture_default_str();
  rs->add_option("--size", r->size,
                 "the camera stream's size WIDTHxHEIGHT (default: the base rig's, else 640x480)");
  rs->add_option("--depth-size", r->depth_size, "the depth stream's size (default: the camera's)");
  rs->add_option("--accel-rate-hz", r->accel_rate_hz, "the accelerometer's stream rate (noise density)")
      ->capture_default_str();
  rs->add_option("--gyro-rate-hz", r->gyro_rate_hz,
                 "the gyroscope's stream rate (noise density, imu.rate_hz)")
      ->capture_default_str();
  rs->footer(
      "Example:\n  rs-enumerate-devices -c > d435i.txt\n  kestrel calib import-realsense d435i.txt --base "
      "configs/realsense_d435i.yaml --out configs/my_d435i.yaml\nMapping and what to check afterwards: "
      "docs/realsense.md");

  Subcommand s;
  s.app = app;
  s.run = [a, r, rs]() -> int {
    if (rs->parsed()) {
      Rig base;
      base.camera_rate_hz = 30.0;
      if (!r->base.empty()) base = load_base_rig(r->base);
      drivers::RealSenseImportOptions o;
      if (r->camera == "color") {
        o.camera = "Color";
      } else if (r->camera == "infrared1") {
        o.camera = "Infrared 1";
      } else {
        throw UsageError("--camera " + r->camera + ": expected color or infrared1");
      }
      parse_size(r->size, "--size", o.width, o.height);
      parse_size(r->depth_size, "--depth-size", o.depth_width, o.depth_height);
      o.accel_rate_hz = r->accel_rate_hz;
      o.gyro_rate_hz = r->gyro_rate_hz;
      const drivers::RealSenseImport imp = drivers::import_realsense(r->dump, o, base);
      std::ofstream f(r->out);
      f << "# Imported by `kestrel calib import-realsense` from " << r->dump << " (camera: " << o.camera
        << ").\n# T_BC is the dump's Gyro -> camera extrinsic inverted (body = the IMU as librealsense "
           "reports its axes);\n# the depth camera is the dump's Depth stream with Depth -> camera as "
           "T_CD.\n";
      for (const std::string& m : imp.missing) f << "# MISSING: " << m << "\n";
      f << "# Not from the dump (" << (r->base.empty() ? std::string("Kestrel's defaults") : r->base)
        << "):\n";
      for (const std::string& n : imp.notes) f << "#   " << n << "\n";
      f << drivers::rig_to_yaml(imp.rig);
      f.close();
      if (!f) throw std::runtime_error(r->out + ": cannot write");
      const Rig back = drivers::load_rig_file(r->out);
      if (!drivers::rig_equal(back, imp.rig))
        throw std::runtime_error(r->out + ": does not read back to the same rig");
      std::printf(
          "wrote %s: %s %dx%d, fx %.3f fy %.3f cx %.3f cy %.3f px, %s distortion; depth %s; IMU %.1f Hz\n",
          r->out.c_str(), o.camera.c_str(), imp.rig.rgb.width, imp.rig.rgb.height, imp.rig.rgb.fx,
          imp.rig.rgb.fy, imp.rig.rgb.cx, imp.rig.rgb.cy, drivers::distortion_name(imp.rig.rgb.distortion),
          imp.rig.depth_camera.present ? "registered from the Depth stream" : "in the camera's frame",
          imp.rig.imu_rate_hz);
      for (const std::string& m : imp.missing) std::printf("MISSING in %s: %s\n", r->dump.c_str(), m.c_str());
      std::printf("not in the dump (from %s):\n", r->base.empty() ? "Kestrel's defaults" : r->base.c_str());
      for (const std::string& n : imp.notes) std::printf("  %s\n", n.c_str());
      return 0;
    }
    Rig base;
    base.camera_rate_hz = 30.0;
    if (!a->base.empty()) base = load_base_rig(a->base);
    const drivers::KalibrImport imp = drivers::import_kalibr(a->camchain, a->imu, a->camera, base);
    std::ofstream f(a->out);
    f << "# Imported by `kestrel calib import-kalibr` from " << a->camchain << " (" << a->camera << ") and "
      << a->imu
      << ".\n# T_BC is Kalibr's T_cam_imu inverted; time_offset_cam_imu_ns is its timeshift_cam_imu (t_imu = "
         "t_cam "
         "+ offset).\n# Not from Kalibr (";
    f << (a->base.empty() ? std::string("Kestrel's defaults") : a->base) << "):\n";
    for (const std::string& n : imp.notes) f << "#   " << n << "\n";
    f << drivers::rig_to_yaml(imp.rig);
    f.close();
    if (!f) throw std::runtime_error(a->out + ": cannot write");
    // The rig must read back as written: the file is what the drivers will load.
    const Rig back = drivers::load_rig_file(a->out);
    if (!drivers::rig_equal(back, imp.rig))
      throw std::runtime_error(a->out + ": does not read back to the same rig");
    std::printf(
        "wrote %s: %dx%d, fx %.3f fy %.3f cx %.3f cy %.3f px, %s distortion, time offset %.3f ms, IMU %.1f "
        "Hz\n",
        a->out.c_str(), imp.rig.rgb.width, imp.rig.rgb.height, imp.rig.rgb.fx, imp.rig.rgb.fy, imp.rig.rgb.cx,
        imp.rig.rgb.cy, drivers::distortion_name(imp.rig.rgb.distortion),
        1e-6 * static_cast<double>(imp.rig.time_offset_cam_imu_ns), imp.rig.imu_rate_hz);
    std::printf("not in Kalibr's files (from %s):\n",
                a->base.empty() ? "Kestrel's defaults" : a->base.c_str());
    for (const std::string& n : imp.notes) std::printf("  %s\n", n.c_str());
    return 0;
  };
  return s;
}

}  // namespace kestrel::cli

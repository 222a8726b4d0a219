// open_log(): one entry point for every recorded format.
#include "kestrel/drivers/open_log.hpp"

#include <cstring>
#include <fstream>
#include <optional>
#include <stdexcept>

#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/drivers/rosbag2.hpp"
#include "text_log.hpp"

namespace kestrel::drivers {
namespace {

bool has_klog_magic(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  char m[4] = {};
  return f.read(m, 4) && std::memcmp(m, "KLOG", 4) == 0;
}

RosbagTopics topics_of(const LogOpenOptions& o) {
  RosbagTopics t;
  if (!o.rgb_topic.empty()) t.rgb = o.rgb_topic;
  if (!o.depth_topic.empty()) t.depth = o.depth_topic;
  if (!o.imu_topic.empty()) t.imu = o.imu_topic;
  if (!o.camera_info_topic.empty()) t.camera_info = o.camera_info_topic;
  if (!o.ground_truth_topic.empty()) t.ground_truth = o.ground_truth_topic;
  t.right = o.right_topic;
  return t;
}

Rosbag2ReadOptions rosbag2_of(const LogOpenOptions& o) {
  Rosbag2ReadOptions t;
  t.rgb_topic = o.rgb_topic;
  t.depth_topic = o.depth_topic;
  t.imu_topic = o.imu_topic;
  t.camera_info_topic = o.camera_info_topic;
  t.ground_truth_topic = o.ground_truth_topic;
  t.right_topic = o.right_topic;
  t.topics = o.topics;
  return t;
}

SevenScenesReader::Options seven_scenes(const LogOpenOptions& o) {
  SevenScenesReader::Options s;
  s.fps = o.fps;
  return s;
}

}  // namespace

LogFormat parse_log_format(const std::string& name) {
  if (name == "auto") return LogFormat::kAuto;
  if (name == "klog") return LogFormat::kKlog;
  if (name == "euroc") return LogFormat::kEuroc;
  if (name == "tum") return LogFormat::kTum;
  if (name == "eth3d") return LogFormat::kEth3d;
  if (name == "openloris") return LogFormat::kOpenLoris;
  if (name == "rosbag") return LogFormat::kRosbag;
  if (name == "7scenes") return LogFormat::kSevenScenes;
  if (name == "rosbag2") return LogFormat::kRosbag2;
  if (name == "tumvi") return LogFormat::kTumvi;
  throw std::runtime_error("unknown log format \"" + name + "\" (expected " + log_format_names() + ")");
}

const char* log_format_names() {
  return "auto, klog, euroc, tum, eth3d, openloris, rosbag, 7scenes, rosbag2, tumvi";
}

std::unique_ptr<LogSource> open_log(const std::string& path, LogFormat format) {
  LogOpenOptions o;
  o.format = format;
  return open_log(path, o);
}

std::unique_ptr<LogSource> open_log(const std::string& path, const LogOpenOptions& opt) {
  std::optional<Rig> rig;
  if (!opt.rig_path.empty()) rig = load_rig_file(opt.rig_path);
  const Rig* r = rig ? &*rig : nullptr;
  switch (opt.format) {
    case LogFormat::kKlog:
      return std::make_unique<KlogReader>(path);
    case LogFormat::kEuroc:
      return std::make_unique<EurocReader>(path);
    case LogFormat::kTum:
      return std::make_unique<TumReader>(path);
    case LogFormat::kEth3d:
      return std::make_unique<Eth3dReader>(path, r);
    case LogFormat::kOpenLoris:
      return std::make_unique<OpenLorisReader>(path, r);
    case LogFormat::kRosbag:
      return std::make_unique<RosbagReader>(path, topics_of(opt), r);
    case LogFormat::kSevenScenes:
      return std::make_unique<SevenScenesReader>(path, r, seven_scenes(opt));
    case LogFormat::kRosbag2:
      return std::make_unique<Rosbag2Reader>(path, rosbag2_of(opt), r);
    case LogFormat::kTumvi:
      return std::make_unique<TumviReader>(path);
    case LogFormat::kAuto:
      break;
  }
  if (text::is_file(path)) {
    const bool ext = path.size() >= 5 && path.compare(path.size() - 5, 5, ".klog") == 0;
    if (ext || has_klog_magic(path)) return std::make_unique<KlogReader>(path);
    if (is_rosbag_file(path)) return std::make_unique<RosbagReader>(path, topics_of(opt), r);
    if (is_rosbag2(path)) return std::make_unique<Rosbag2Reader>(path, rosbag2_of(opt), r);
    throw std::runtime_error(path +
                             ": not a .klog file (no KLOG magic), not a ROS bag (no #ROSBAG magic), not an "
                             "MCAP file and not a folder");
  }
  if (text::is_dir(path)) {
    if (is_rosbag2(path)) return std::make_unique<Rosbag2Reader>(path, rosbag2_of(opt), r);
    // TUM-VI before EuRoC: both have mav0/.
    if (is_tumvi_folder(path)) return std::make_unique<TumviReader>(path);
    if (is_euroc_folder(path)) return std::make_unique<EurocReader>(path);
    // ETH3D before TUM: both have rgb.txt.
    if (is_eth3d_folder(path)) return std::make_unique<Eth3dReader>(path, r);
    if (is_openloris_folder(path)) return std::make_unique<OpenLorisReader>(path, r);
    if (is_tum_folder(path)) return std::make_unique<TumReader>(path);
    if (is_sevenscenes_folder(path)) return std::make_unique<SevenScenesReader>(path, r, seven_scenes(opt));
    throw std::runtime_error(
        path +
        ": unknown log folder (no metadata.yaml, mav0/, imu0/, imu0.csv, rgb.txt, color.txt, "
        "calibration.txt or frame-000000.pose.txt)");
  }
  throw std::runtime_error(path + ": no such file or folder");
}

}  // namespace kestrel::drivers

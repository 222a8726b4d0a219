// One entry point that opens any recorded format (open_log.cpp): it knows
// every reader, so it belongs to the datasets module, above the log format.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "kestrel/drivers/log_source.hpp"

namespace kestrel::drivers {

enum class LogFormat {
  kAuto,
  kKlog,
  kEuroc,
  kTum,
  kEth3d,
  kOpenLoris,
  kRosbag,
  kSevenScenes,
  kRosbag2,
  kTumvi
};

// How to open a log beyond its path (docs/datasets.md).
struct LogOpenOptions {
  LogFormat format = LogFormat::kAuto;
  // A rig YAML supplying the calibration a dataset lacks (ETH3D, OpenLORIS,
  // rosbag); the dataset's own calibration wins where it has one. "" = none.
  std::string rig_path;
  // 7-Scenes has no time stamps: frame i is at i / fps.
  double fps = 30.0;
  // ROS bag topics ("" = the RealSense D435i defaults of RosbagTopics; for
  // rosbag2, "" = found by message type).
  std::string rgb_topic, depth_topic, imu_topic, camera_info_topic, ground_truth_topic;
  // rosbag2: a stereo pair's right image topic (Rosbag2ReadOptions::right_topic).
  std::string right_topic;
  // rosbag2: read only these topics (empty = all; Rosbag2ReadOptions::topics).
  std::vector<std::string> topics;
};

// Opens `path` as `format` (kAuto: a .klog file, a ROS 1 bag, a rosbag2
// folder (metadata.yaml) or .mcap file, a TUM-VI folder (mav0/ with
// dso/camchain.yaml or mav0/mocap0/), an EuRoC ASL
// folder with mav0/ or imu0/, an ETH3D folder (rgb.txt + calibration.txt,
// associated.txt or imu.txt), an OpenLORIS folder (color.txt,
// d400_accelerometer.txt, or sensors.yaml + trans_matrix.yaml), a 7-Scenes
// folder (frame-000000.pose.txt + frame-000000.color.*), or a TUM RGB-D
// folder with rgb.txt). Throws std::runtime_error naming the path and
// what is missing when it cannot.
std::unique_ptr<LogSource> open_log(const std::string& path, LogFormat format = LogFormat::kAuto);
std::unique_ptr<LogSource> open_log(const std::string& path, const LogOpenOptions& options);

// "auto", "klog", "euroc", "tum", "eth3d", "openloris", "rosbag", "7scenes", "rosbag2", "tumvi"; throws on
// unknown
// names.
LogFormat parse_log_format(const std::string& name);
const char* log_format_names();  // "auto, klog, ..., rosbag2, tumvi"

}  // namespace kestrel::drivers

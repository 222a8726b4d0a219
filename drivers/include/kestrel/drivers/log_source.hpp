// Recorded sensor data as one stream of records, whatever the file format.
//
// Replay, eval, sim export and convert all read through LogSource, so a new
// format is one new reader and nothing else changes. Readers run outside the
// real-time threads (the replay feeder copies their output into the rings), so
// they may allocate.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/msgs.hpp"

namespace kestrel::drivers {

// An image as stored in a log: pixels packed row after row (stride = width * bpp).
struct LogImage {
  int64_t t_ns = 0;
  int64_t t_recv_ns = 0;
  uint32_t seq = 0;
  int32_t exposure_us = 0;
  int width = 0;
  int height = 0;
  PixelFormat format = PixelFormat::kGray8;
  std::vector<uint8_t> pixels;

  ImageView view() const {
    return ImageView{width, height, width * bytes_per_pixel(format), format, pixels.data()};
  }
};

enum class RecordType : uint16_t {
  kImu = 1,
  kRgb = 2,
  kDepth = 3,
  kGroundTruth = 4,
  kEvent = 5,
};

// One record; only the member named by `type` is meaningful.
struct LogRecord {
  RecordType type = RecordType::kImu;
  uint64_t offset = 0;   // byte offset (klog) or line number (text formats) it came from
  ImuSample imu;
  LogImage image;        // kRgb or kDepth
  GroundTruthPose gt;
  Event event;
};

// Something wrong in the input, reported with where it is. Readers never
// throw on bad data after open(): they record a problem and carry on.
struct LogProblem {
  std::string where;   // "file:line" or "file@byte-offset"
  std::string kind;    // short machine-readable tag: "truncated", "bad-crc", "bad-length", "missing-file", ...
  std::string detail;
};

class LogSource {
 public:
  virtual ~LogSource() = default;
  virtual const Rig& rig() const = 0;
  // Next record in time order as the format stores it; false at the end.
  virtual bool next(LogRecord& out) = 0;
  // Back to the first record (for two-pass tools such as eval and bench).
  virtual void rewind() = 0;
  virtual const std::vector<LogProblem>& problems() const = 0;
  virtual std::string format_name() const = 0;
};

enum class LogFormat { kAuto, kKlog, kEuroc, kTum, kEth3d, kOpenLoris, kRosbag };

// How to open a log beyond its path (docs/datasets.md).
struct LogOpenOptions {
  LogFormat format = LogFormat::kAuto;
  // A rig YAML supplying the calibration a dataset lacks (ETH3D, OpenLORIS,
  // rosbag); the dataset's own calibration wins where it has one. "" = none.
  std::string rig_path;
  // ROS bag topics ("" = the RealSense D435i defaults of RosbagTopics).
  std::string rgb_topic, depth_topic, imu_topic, camera_info_topic, ground_truth_topic;
};

// Opens `path` as `format` (kAuto: a .klog file, a ROS 1 bag, an EuRoC ASL
// folder with mav0/ or imu0/, an ETH3D folder (rgb.txt + calibration.txt,
// associated.txt or imu.txt), an OpenLORIS folder (color.txt,
// d400_accelerometer.txt, or sensors.yaml + trans_matrix.yaml), or a TUM
// RGB-D folder with rgb.txt). Throws std::runtime_error naming the path and
// what is missing when it cannot.
std::unique_ptr<LogSource> open_log(const std::string& path, LogFormat format = LogFormat::kAuto);
std::unique_ptr<LogSource> open_log(const std::string& path, const LogOpenOptions& options);

// "auto", "klog", "euroc", "tum", "eth3d", "openloris", "rosbag"; throws on unknown names.
LogFormat parse_log_format(const std::string& name);
const char* log_format_names();   // "auto, klog, euroc, tum, eth3d, openloris, rosbag"

}  // namespace kestrel::drivers

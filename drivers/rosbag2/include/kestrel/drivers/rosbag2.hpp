// rosbag2 without ROS: a folder with metadata.yaml and MCAP files of CDR
// messages (docs/ros2.md). export_rosbag2 writes any LogSource as standard
// sensor messages; Rosbag2Reader replays such a folder (or one .mcap file).
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/mcap.hpp"

namespace kestrel::drivers {

// Topics written, and read when the reader cannot tell by type (the RealSense
// ROS 2 wrapper's names). "" in the reader's copy = detected by message type.
struct Rosbag2Topics {
  std::string imu = "/camera/imu";
  std::string rgb = "/camera/color/image_raw";
  std::string depth = "/camera/aligned_depth_to_color/image_raw";
  std::string camera_info = "/camera/color/camera_info";
  std::string ground_truth = "/kestrel/ground_truth";
  // A stereo rig's right camera (written only for stereo logs; read as the
  // right image when no --right-topic is given).
  std::string right = "/camera/right/image_raw";
  std::string right_camera_info = "/camera/right/camera_info";
};

struct Rosbag2WriteOptions {
  mcap::WriterOptions mcap;  // compression zstd, 4 MiB chunks
  Rosbag2Topics topics;
};

struct Rosbag2Stats {
  size_t imu = 0, rgb = 0, depth = 0, right = 0, ground_truth = 0, skipped = 0;
  uint64_t bytes = 0;
};

// Rewinds `src` and writes out_dir/metadata.yaml (rosbag2 metadata version 5,
// storage mcap) and out_dir/<name>_0.mcap: sensor_msgs/msg/Imu, Image (colour
// as stored: rgb8 / bgr8 / mono8; depth 16UC1 in millimetres), CameraInfo with
// each colour image, /tf_static (base_link -> imu, base_link -> colour camera),
// a stereo log's right images with their CameraInfo (Rosbag2Topics::right),
// ground truth as geometry_msgs/msg/PoseStamped, and the exact Kestrel rig as
// an MCAP Metadata record "kestrel" (key rig_yaml). Header stamps are the
// records' t_ns (on the IMU clock); log times the same. Throws naming the file.
Rosbag2Stats export_rosbag2(LogSource& src, const std::string& out_dir,
                            const Rosbag2WriteOptions& options = {});

// True if `path` is a folder holding metadata.yaml, a file with MCAP magic, or
// a .db3 file with SQLite's header (rosbag2's sqlite3 storage).
bool is_rosbag2(const std::string& path);

struct Rosbag2ReadOptions {
  // "" = found by type: the Imu topic, the colour Image topic (a colour
  // encoding), the depth Image topic (16UC1 / 32FC1), the CameraInfo beside
  // the colour topic, PoseStamped as ground truth.
  std::string rgb_topic, depth_topic, imu_topic, camera_info_topic, ground_truth_topic;
  // A stereo pair's right image topic (e.g. realsense-ros /camera/infra2/image_rect_raw with
  // rgb_topic /camera/infra1/image_rect_raw); "" = Rosbag2Topics::right when the bag has it.
  // The rig's right camera comes from its CameraInfo (beside it) and /tf_static, or from the
  // CameraInfo's projection P (baseline = -P[3] / P[0]) without one.
  std::string right_topic;
  // Non-empty: only these topics are read (then detected by type among them,
  // or named above); tf_static and CameraInfo are read for the rig regardless.
  // A topic the bag does not have is an error naming the ones it has.
  std::vector<std::string> topics;
  mcap::ReaderOptions mcap;
};

// Reads storage mcap (chunked, zstd / lz4) and sqlite3 (libsqlite3, read-only);
// Image and CompressedImage (jpeg / png, image_transport's compressedDepth).
class Rosbag2Reader : public LogSource {
 public:
  // `rig` (from --rig) wins over the file's; else the "kestrel" rig metadata,
  // else CameraInfo + /tf_static. Throws naming the path when it cannot open.
  Rosbag2Reader(const std::string& path, const Rosbag2ReadOptions& options = {}, const Rig* rig = nullptr);
  ~Rosbag2Reader() override;
  const Rig& rig() const override;
  bool next(LogRecord& out) override;
  void rewind() override;
  const std::vector<LogProblem>& problems() const override;
  std::string format_name() const override { return "rosbag2"; }

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace kestrel::drivers

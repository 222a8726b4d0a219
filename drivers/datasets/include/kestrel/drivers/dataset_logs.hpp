// LogSources over public RGB-D + IMU recordings: ETH3D SLAM folders,
// OpenLORIS-Scene folders and ROS 1 bags (docs/datasets.md says what each
// reader takes from which file and what it assumes).
//
// All three take an optional rig (`kestrel ... --rig FILE.yaml`): the dataset's
// own calibration wins where it has one, the rig supplies the rest. When a
// field the estimator cannot do without (camera intrinsics) is in neither,
// the constructor throws naming the file and the missing field.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/log_source.hpp"

namespace kestrel::drivers {

// ETH3D SLAM (RGB-D, optionally with imu.txt): rgb.txt, depth.txt,
// associated.txt, calibration.txt, groundtruth.txt, imu.txt + rgb/, depth/.
// Without `rig`, a kestrel_rig.yaml in the folder (written by export_eth3d) is used as one.
class Eth3dReader final : public FolderLogSource {
 public:
  explicit Eth3dReader(const std::string& path, const Rig* rig = nullptr);
  std::string format_name() const override { return "eth3d"; }
  size_t associated_pairs() const { return pairs_; }

 private:
  size_t pairs_ = 0;
};

// OpenLORIS-Scene (D435i part): color.txt, aligned_depth.txt,
// d400_accelerometer.txt, d400_gyroscope.txt, groundtruth.txt, sensors.yaml,
// trans_matrix.yaml + color/, aligned_depth/. Accelerometer and gyroscope
// come at different rates; they are merged at the faster stream's stamps by
// linear interpolation of the slower one, never extrapolated.
class OpenLorisReader final : public FolderLogSource {
 public:
  explicit OpenLorisReader(const std::string& path, const Rig* rig = nullptr);
  std::string format_name() const override { return "openloris"; }
  size_t associated_pairs() const { return pairs_; }
  size_t imu_dropped() const { return imu_dropped_; }  // fast-stream samples with no slow partner

 private:
  size_t pairs_ = 0;
  size_t imu_dropped_ = 0;
};

// ROS 1 bag topics. Defaults fit a RealSense D435i recording.
struct RosbagTopics {
  std::string rgb = "/camera/color/image_raw";
  std::string depth = "/camera/aligned_depth_to_color/image_raw";
  std::string imu = "/camera/imu";
  std::string camera_info;                             // "" = the colour topic's sibling ".../camera_info"
  std::string ground_truth = "/kestrel/ground_truth";  // geometry_msgs/PoseStamped (T_WB), optional
};

// True when Kestrel was built with librosbag (KESTREL_WITH_ROSBAG).
bool rosbag_built();

// sensor_msgs/Imu, sensor_msgs/Image (rgb8, bgr8, mono8; depth 16UC1 in mm,
// 32FC1 in m), sensor_msgs/CameraInfo. Indexes the bag at construction
// (IMU and poses in memory, images read when replayed). Throws when the bag
// cannot be opened (also: "not built" without librosbag).
class RosbagReader final : public LogSource {
 public:
  explicit RosbagReader(const std::string& path, const RosbagTopics& topics = {}, const Rig* rig = nullptr);
  ~RosbagReader() override;
  const Rig& rig() const override;
  bool next(LogRecord& out) override;
  void rewind() override;
  const std::vector<LogProblem>& problems() const override;
  std::string format_name() const override { return "rosbag"; }

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

bool is_eth3d_folder(const std::string& path);
bool is_openloris_folder(const std::string& path);
bool is_rosbag_file(const std::string& path);  // "#ROSBAG V2.0" magic

}  // namespace kestrel::drivers

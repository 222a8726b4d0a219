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

#include "kestrel/drivers/depth_registration.hpp"
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
  // A stereo pair's right image (e.g. /cam1/image_raw beside rgb /cam0/image_raw); "" = none. Its
  // CameraInfo (the sibling ".../camera_info") gives the right camera and P[3] = -fx * baseline
  // places it, unless --rig has a stereo: section.
  std::string right;
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

// Microsoft 7-Scenes (Shotton et al., CVPR 2013; also the tsdf-fusion-python
// layout): frame-NNNNNN.color.{png,jpg}, frame-NNNNNN.depth.png (mm; 0 and
// 65535 = no reading), frame-NNNNNN.pose.txt (4x4 T_WC of the depth camera,
// KinectFusion), optional camera-intrinsics.txt (the depth camera's 3x3) and
// gravity-direction.txt. No time stamps: frame i is at i / fps. No IMU.
// The depth is registered to colour through the rig's depth camera (without
// a rig: the assumed Kinect v1 calibration of default_rig()); the world is
// levelled with gravity-direction.txt (gravity along -z) and the ground truth
// is the body's (the colour camera without a rig's T_BC). docs/datasets.md.
class SevenScenesReader final : public FolderLogSource {
 public:
  struct Options {
    double fps = 30.0;  // the recording's frame rate: frame i at i / fps [s]
  };
  explicit SevenScenesReader(const std::string& path, const Rig* rig = nullptr);
  SevenScenesReader(const std::string& path, const Rig* rig, const Options& options);
  ~SevenScenesReader() override;
  bool next(LogRecord& out) override;
  std::string format_name() const override { return "7scenes"; }
  // Frames whose colour / depth repeated the previous frame's byte for byte (withheld).
  size_t repeated_colour() const { return repeated_colour_; }
  size_t repeated_depth() const { return repeated_depth_; }
  // The last depth image's registration (zeros when the rig has no depth camera).
  const RegistrationStats& last_registration() const { return last_registration_; }
  // The rig used without --rig: colour 525 px at the centre, the depth camera
  // from camera-intrinsics.txt, T_CD of a calibrated Kinect v1.
  static Rig default_rig(const CameraIntrinsics& depth_intrinsics);

 private:
  std::unique_ptr<DepthRegistration> registration_;
  std::vector<uint16_t> registered_;
  RegistrationStats last_registration_;
  uint32_t unregistered_reported_until_ = 0;
  size_t repeated_colour_ = 0, repeated_depth_ = 0;
};

bool is_sevenscenes_folder(const std::string& path);
bool is_eth3d_folder(const std::string& path);
bool is_openloris_folder(const std::string& path);
bool is_rosbag_file(const std::string& path);  // "#ROSBAG V2.0" magic

}  // namespace kestrel::drivers

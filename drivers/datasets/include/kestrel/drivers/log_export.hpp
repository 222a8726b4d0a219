// Writing a LogSource out in other tools' formats: an EuRoC ASL folder (for
// OKVIS2, OpenVINS, Basalt, ORB-SLAM3) and a TUM trajectory file (for the TUM
// and evo evaluation scripts).
#pragma once

#include <cstddef>
#include <string>

#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/log_source.hpp"

namespace kestrel::drivers {

struct ExportStats {
  size_t imu = 0;
  size_t rgb = 0;
  size_t depth = 0;
  size_t ground_truth = 0;
  size_t events = 0;
};

// Rewinds `src` and writes `out_dir`/mav0/: imu0/data.csv, cam0/data.csv +
// data/<t_ns>.png, depth0/data.csv + 16-bit data/<t_ns>.png,
// state_groundtruth_estimate0/data.csv, the ASL sensor.yaml files, and two
// Kestrel files EuRoC lacks: kestrel_rig.yaml (the exact rig) and
// kestrel_events.csv. Numbers are written with %.17g, so reading the folder
// back with EurocReader gives the same IMU and ground-truth values. IMU
// t_recv_ns, seq, flags and temperature have no EuRoC column and are lost.
// Throws std::runtime_error naming the file on any write failure.
ExportStats export_euroc(LogSource& src, const std::string& out_dir);

// Rewinds `src` and writes its ground truth as a TUM trajectory:
// "t[s] x y z qx qy qz qw" per line (seconds with 9 decimals). Returns the pose count.
size_t export_tum_groundtruth(LogSource& src, const std::string& path);

// Rewinds `src` and writes an ETH3D SLAM folder: rgb/ + rgb.txt, depth/ +
// depth.txt (16-bit PNG, 5000 units per metre, converted from the rig's
// scale), associated.txt (colour and depth records with one stamp),
// calibration.txt (fx fy cx cy: ETH3D images are undistorted pinhole, so
// images of a rig with distortion are undistorted to the same K, colour
// bilinear, depth nearest-neighbour), groundtruth.txt (the colour camera's pose
// T_WC = T_WB * T_BC, TUM order) and imu.txt ("t gx gy gz ax ay az").
// Timestamps are seconds with 9 decimals, numbers %.17g. What ETH3D cannot
// hold (T_BC, IMU noise, depth range, distortion) goes to kestrel_rig.yaml
// beside it, which Eth3dReader uses when no --rig is given. Lost: events,
// receive times, sequence numbers.
ExportStats export_eth3d(LogSource& src, const std::string& out_dir);

// Rewinds `src` and writes an OpenLORIS-Scene folder: color/ + color.txt,
// aligned_depth/ + aligned_depth.txt (the rig's depth units, written as
// d400_depth_optical_frame.depth_scale in sensors.yaml), d400_gyroscope.txt
// and d400_accelerometer.txt (both at the IMU stamps), groundtruth.txt
// (base_link = the IMU body), sensors.yaml and trans_matrix.yaml
// (base_link -> d400_gyroscope = I, d400_gyroscope -> colour = T_BC).
ExportStats export_openloris(LogSource& src, const std::string& out_dir);

// Rewinds `src` and writes a ROS 1 bag: sensor_msgs/Imu, sensor_msgs/Image
// (rgb8 / bgr8 / mono8, depth 16UC1 in millimetres), a CameraInfo with each
// colour image, ground truth as geometry_msgs/PoseStamped. Throws "not built"
// without librosbag.
ExportStats export_rosbag(LogSource& src, const std::string& path, const RosbagTopics& topics = {});

}  // namespace kestrel::drivers

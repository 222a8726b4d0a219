// Writing a LogSource out in other tools' formats: an EuRoC ASL folder (for
// OKVIS2, OpenVINS, Basalt, ORB-SLAM3) and a TUM trajectory file (for the TUM
// and evo evaluation scripts).
#pragma once

#include <cstddef>
#include <string>

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

}  // namespace kestrel::drivers

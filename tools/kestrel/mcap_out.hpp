// `kestrel replay|run --mcap-out FILE`: the poses as nav_msgs/msg/Odometry
// (frame odom -> base_link, with the backend's covariance), /tf
// (tf2_msgs/msg/TFMessage: map -> odom -> base_link) and /diagnostics
// (diagnostic_msgs/msg/DiagnosticArray: quality, resets, the map's state) in an
// MCAP file a ROS 2 or Foxglove tool opens (docs/ros2.md). Used from
// ReplayOptions::on_pose, i.e. on the output thread, never on a real-time
// thread: it allocates and writes to the file.
#pragma once

#include <memory>
#include <string>

#include "kestrel/drivers/mcap.hpp"
#include "kestrel/replay_runner.hpp"

namespace kestrel::cli {

class McapPoseWriter {
 public:
  // Throws naming the file when it cannot be created.
  explicit McapPoseWriter(const std::string& path);
  void write(const PoseSample& s);
  // Writes the summary and footer; poses after it are ignored.
  void close();
  uint64_t count() const { return count_; }

 private:
  void write_diagnostics(const PoseSample& s);

  drivers::mcap::Writer w_;
  uint16_t odom_ = 0, tf_ = 0, diag_ = 0;
  uint64_t count_ = 0;
  int64_t last_t_ns_ = INT64_MIN;
  // Diagnostics once a second of log time, and at once when the quality, the
  // reset counter or the map's alignment changes.
  int64_t last_diag_t_ns_ = INT64_MIN;
  int last_quality_ = -1;
  uint32_t last_resets_ = 0, last_alignment_ = 0;
  std::vector<uint8_t> buf_;
};

// Wraps opt.on_pose so each pose also goes to a McapPoseWriter at `path`
// (none when empty); the writer is closed by the returned handle's close().
std::shared_ptr<McapPoseWriter> add_mcap_out(ReplayOptions& opt, const std::string& path);

}  // namespace kestrel::cli

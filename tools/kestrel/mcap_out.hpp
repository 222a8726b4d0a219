// `kestrel replay|run --mcap-out FILE`: the poses as nav_msgs/msg/Odometry
// (frame odom -> base_link, with the backend's covariance) in an MCAP file a
// ROS 2 or Foxglove tool opens (docs/ros2.md). Used from ReplayOptions::on_pose,
// i.e. on the output thread, never on a real-time thread: it allocates and
// writes to the file.
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
  drivers::mcap::Writer w_;
  uint16_t odom_ = 0;
  uint64_t count_ = 0;
  int64_t last_t_ns_ = INT64_MIN;
  std::vector<uint8_t> buf_;
};

// Wraps opt.on_pose so each pose also goes to a McapPoseWriter at `path`
// (none when empty); the writer is closed by the returned handle's close().
std::shared_ptr<McapPoseWriter> add_mcap_out(ReplayOptions& opt, const std::string& path);

}  // namespace kestrel::cli

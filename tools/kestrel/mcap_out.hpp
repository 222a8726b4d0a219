// `kestrel replay|run --mcap-out FILE`: the ROS 2 topics of ros2_topics.hpp
// in an MCAP file a ROS 2 or Foxglove tool opens (docs/ros2.md). Written from
// ReplayOptions' callbacks, i.e. on the output thread, never on a real-time
// thread: it allocates and writes to the file.
#pragma once

#include <memory>
#include <string>

#include "kestrel/drivers/mcap.hpp"
#include "kestrel/ros2_topics.hpp"

namespace kestrel::cli {

class McapPoseWriter final : public Ros2Sink {
 public:
  // Throws naming the file when it cannot be created.
  explicit McapPoseWriter(const std::string& path);
  void publish(Ros2Topic topic, int64_t t_ns, const std::vector<uint8_t>& cdr) override;
  // Writes the summary and footer; messages after it are ignored.
  void close();
  uint64_t count() const { return out_ ? out_->odometry_count() : 0; }
  Ros2Output& output() { return *out_; }

 private:
  drivers::mcap::Writer w_;
  uint16_t channel_[kRos2Topics] = {};
  std::unique_ptr<Ros2Output> out_;
};

// Wraps opt's callbacks so the poses and the map also go to a McapPoseWriter
// at `path` (none when empty); the writer is closed by the returned handle's close().
std::shared_ptr<McapPoseWriter> add_mcap_out(ReplayOptions& opt, const std::string& path,
                                             double map_points_rate_hz);

}  // namespace kestrel::cli

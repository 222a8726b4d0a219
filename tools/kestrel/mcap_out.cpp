#include "kestrel/mcap_out.hpp"

#include <string>

#include "kestrel/drivers/ros2_msgs.hpp"

namespace kestrel::cli {

McapPoseWriter::McapPoseWriter(const std::string& path) {
  drivers::mcap::WriterOptions o;
  o.chunk_size_bytes = 256u << 10;  // about 300 poses: a crash loses at most ~10 s at 30 Hz
  w_.open(path, o);
  for (int i = 0; i < kRos2Topics; ++i) {
    const Ros2TopicInfo& t = ros2_topic_info(static_cast<Ros2Topic>(i));
    channel_[i] =
        w_.add_channel(w_.add_schema(t.type, "ros2msg", drivers::ros2::schema_text(t.type)), t.topic, "cdr");
  }
  out_ = std::make_unique<Ros2Output>(*this);
}

void McapPoseWriter::publish(Ros2Topic topic, int64_t t_ns, const std::vector<uint8_t>& cdr) {
  if (!w_.is_open()) return;
  w_.write(channel_[static_cast<int>(topic)], static_cast<uint64_t>(t_ns), static_cast<uint64_t>(t_ns),
           cdr.data(), cdr.size());
}

void McapPoseWriter::close() { w_.close(); }

std::shared_ptr<McapPoseWriter> add_mcap_out(ReplayOptions& opt, const std::string& path,
                                             double map_points_rate_hz) {
  if (path.empty()) return nullptr;
  auto w = std::make_shared<McapPoseWriter>(path);
  // The Ros2Output lives inside the writer: share the writer's lifetime with it.
  connect_ros2_output(opt, std::shared_ptr<Ros2Output>(w, &w->output()), map_points_rate_hz);
  return w;
}

}  // namespace kestrel::cli

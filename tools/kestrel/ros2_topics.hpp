// What `--mcap-out` and `--foxglove` publish (docs/ros2.md): the poses as
// nav_msgs/msg/Odometry (odom -> base_link, with the backend's covariance),
// /tf (map -> odom -> base_link), /diagnostics (quality, resets, the map's
// state), the local map's points as sensor_msgs/msg/PointCloud2 and the
// keyframes and loops as visualization_msgs/msg/MarkerArray, and at the end
// the dense map's surface (when it ran) as a coloured PointCloud2, all in CDR.
// Runs on the output thread only (ReplayOptions' callbacks): it allocates.
// A Ros2Sink takes each encoded message (an MCAP file, a WebSocket server).
#pragma once

#include <climits>
#include <cstdint>
#include <memory>
#include <vector>

#include "kestrel/replay_runner.hpp"

namespace kestrel::cli {

enum class Ros2Topic : int { kOdometry, kTf, kDiagnostics, kMapPoints, kMarkers, kDenseMap, kCount };
inline constexpr int kRos2Topics = static_cast<int>(Ros2Topic::kCount);
struct Ros2TopicInfo {
  const char* topic;
  const char* type;  // "nav_msgs/msg/Odometry"; its schema is ros2::schema_text(type)
};
const Ros2TopicInfo& ros2_topic_info(Ros2Topic t);

class Ros2Sink {
 public:
  virtual ~Ros2Sink() = default;
  // t_ns: the message's header stamp (log time); cdr: the serialized message.
  virtual void publish(Ros2Topic topic, int64_t t_ns, const std::vector<uint8_t>& cdr) = 0;
};

class Ros2Output {
 public:
  explicit Ros2Output(Ros2Sink& sink) : sink_(sink) {}
  void on_pose(const core::PoseSample& s);
  // In W; published in the map frame with the T_map_odom of the last pose.
  void on_cloud(const MapCloud& c);
  void on_keyframe(const KeyframePose& k);
  // Clears the keyframe arrows and draws the map's final keyframe path and loops.
  void on_final(const MapFinal& f);
  // The finished dense map's surface, in W: frame odom, stamped with the last pose.
  void on_dense(const core::TsdfMap& m);
  uint64_t odometry_count() const { return count_[static_cast<int>(Ros2Topic::kOdometry)]; }
  uint64_t count(Ros2Topic t) const { return count_[static_cast<int>(t)]; }

 private:
  void publish(Ros2Topic t, int64_t t_ns);
  void write_diagnostics(const core::PoseSample& s);
  void write_loop_edge(const core::PoseSample& s);

  Ros2Sink& sink_;
  uint64_t count_[kRos2Topics] = {};
  int64_t last_t_ns_ = INT64_MIN;
  int64_t last_topic_t_ns_[kRos2Topics] = {INT64_MIN, INT64_MIN, INT64_MIN, INT64_MIN, INT64_MIN, INT64_MIN};
  Eigen::Isometry3d T_map_odom_ = Eigen::Isometry3d::Identity();
  int32_t next_keyframe_id_ = 0;
  uint64_t loops_drawn_ = 0;  // live loop edges published (MapFrameState::loop_closures)
  // Diagnostics once a second of log time, and at once when the quality, the
  // reset counter or the map's alignment changes.
  int64_t last_diag_t_ns_ = INT64_MIN;
  int last_quality_ = -1;
  uint32_t last_resets_ = 0, last_alignment_ = 0;
  std::vector<uint8_t> buf_;
  std::vector<float> xyz_;
  std::vector<uint8_t> rgb_;
};

// Chains the Ros2Output's handlers onto opt's callbacks (after any already
// set), asking for map points at map_points_rate_hz.
void connect_ros2_output(ReplayOptions& opt, const std::shared_ptr<Ros2Output>& out,
                         double map_points_rate_hz);

}  // namespace kestrel::cli

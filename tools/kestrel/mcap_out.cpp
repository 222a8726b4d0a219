#include "kestrel/mcap_out.hpp"

#include <climits>
#include <string>
#include <utility>
#include <vector>

#include "kestrel/drivers/ros2_msgs.hpp"

namespace kestrel::cli {

McapPoseWriter::McapPoseWriter(const std::string& path) {
  drivers::mcap::WriterOptions o;
  o.chunk_size_bytes = 256u << 10;  // about 300 poses: a crash loses at most ~10 s at 30 Hz
  w_.open(path, o);
  const char* type = "nav_msgs/msg/Odometry";
  odom_ = w_.add_channel(w_.add_schema(type, "ros2msg", drivers::ros2::schema_text(type)),
                         "/kestrel/odometry", "cdr");
  const char* tf = "tf2_msgs/msg/TFMessage";
  tf_ = w_.add_channel(w_.add_schema(tf, "ros2msg", drivers::ros2::schema_text(tf)), "/tf", "cdr");
  const char* diag = "diagnostic_msgs/msg/DiagnosticArray";
  diag_ =
      w_.add_channel(w_.add_schema(diag, "ros2msg", drivers::ros2::schema_text(diag)), "/diagnostics", "cdr");
}

void McapPoseWriter::write_diagnostics(const PoseSample& s) {
  const int q = static_cast<int>(s.quality);
  if (s.t_ns - last_diag_t_ns_ < 1'000'000'000 && q == last_quality_ && s.reset_counter == last_resets_ &&
      s.map.alignment == last_alignment_)
    return;
  last_diag_t_ns_ = s.t_ns, last_quality_ = q, last_resets_ = s.reset_counter,
  last_alignment_ = s.map.alignment;
  drivers::ros2::DiagnosticArray d;
  d.t_ns = s.t_ns;
  drivers::ros2::DiagnosticStatus st;
  // OK while the camera keeps the pose; WARN while the IMU alone carries it or
  // nothing is known yet; ERROR when the backend says it is lost.
  st.level = s.quality == core::TrackingQuality::kTracking || s.quality == core::TrackingQuality::kVisionOnly
                 ? 0
             : s.quality == core::TrackingQuality::kLost ? 2
                                                         : 1;
  st.name = "kestrel: estimator";
  st.hardware_id = "kestrel";
  st.message = core::tracking_quality_name(s.quality);
  st.values = {{"quality", core::tracking_quality_name(s.quality)},
               {"reset_counter", std::to_string(s.reset_counter)}};
  if (s.map.active) {
    st.values.emplace_back("map_localized", s.map.localized ? "true" : "false");
    st.values.emplace_back("map_keyframes", std::to_string(s.map.keyframes));
    st.values.emplace_back("map_points", std::to_string(s.map.points));
    st.values.emplace_back("loop_closures", std::to_string(s.map.loop_closures));
    st.values.emplace_back("relocalisations", std::to_string(s.map.relocalisations));
  }
  d.status.push_back(std::move(st));
  drivers::ros2::encode(d, buf_);
  w_.write(diag_, static_cast<uint64_t>(s.t_ns), static_cast<uint64_t>(s.t_ns), buf_.data(), buf_.size());
}

void McapPoseWriter::write(const PoseSample& s) {
  if (!w_.is_open() || s.t_ns < 0) return;
  // MCAP wants log times in order per channel for indexed reading; repeated stamps are skipped.
  if (s.t_ns <= last_t_ns_) return;
  last_t_ns_ = s.t_ns;
  drivers::ros2::Odometry m;
  m.t_ns = s.t_ns;
  m.frame_id = "odom";
  m.child_frame_id = "base_link";
  m.pose.position = {s.p_WB.x(), s.p_WB.y(), s.p_WB.z()};
  m.pose.orientation_xyzw = {s.q_WB.x(), s.q_WB.y(), s.q_WB.z(), s.q_WB.w()};
  if (s.pose_cov.valid) {
    // Ours is [dp_W; dtheta_B]; ROS's pose covariance is (x y z) then rotation
    // about the fixed axes of the parent frame: dtheta_W = R_WB dtheta_B.
    Eigen::Matrix<double, 6, 6> J = Eigen::Matrix<double, 6, 6>::Identity();
    J.bottomRightCorner<3, 3>() = s.q_WB.toRotationMatrix();
    const Eigen::Matrix<double, 6, 6> C = J * s.pose_cov.cov * J.transpose();
    for (int i = 0; i < 6; ++i)
      for (int j = 0; j < 6; ++j) m.pose_covariance[static_cast<size_t>(i * 6 + j)] = C(i, j);
  } else {
    m.pose_covariance[0] = -1;  // no covariance from this backend (REP 145's "unknown")
  }
  const Eigen::Vector3d v_B = s.q_WB.conjugate() * s.v_WB;  // twist is in the child frame
  m.linear = {v_B.x(), v_B.y(), v_B.z()};
  m.angular = {s.omega_B_rps.x(), s.omega_B_rps.y(), s.omega_B_rps.z()};
  m.twist_covariance[0] = -1;
  drivers::ros2::encode(m, buf_);
  w_.write(odom_, static_cast<uint64_t>(s.t_ns), static_cast<uint64_t>(s.t_ns), buf_.data(), buf_.size());
  ++count_;

  // REP 105: map -> odom is the map's correction (identity without a map),
  // odom -> base_link the continuous odometry.
  std::vector<drivers::ros2::TransformStamped> tf(2);
  const Eigen::Isometry3d T_map_odom = s.map.active ? s.map.T_map_odom() : Eigen::Isometry3d::Identity();
  const Eigen::Quaterniond q_mo(T_map_odom.linear());
  tf[0].t_ns = tf[1].t_ns = s.t_ns;
  tf[0].frame_id = "map";
  tf[0].child_frame_id = "odom";
  tf[0].translation = {T_map_odom.translation().x(), T_map_odom.translation().y(),
                       T_map_odom.translation().z()};
  tf[0].rotation_xyzw = {q_mo.x(), q_mo.y(), q_mo.z(), q_mo.w()};
  tf[1].frame_id = "odom";
  tf[1].child_frame_id = "base_link";
  tf[1].translation = m.pose.position;
  tf[1].rotation_xyzw = m.pose.orientation_xyzw;
  drivers::ros2::encode(tf, buf_);
  w_.write(tf_, static_cast<uint64_t>(s.t_ns), static_cast<uint64_t>(s.t_ns), buf_.data(), buf_.size());
  write_diagnostics(s);
}

void McapPoseWriter::close() { w_.close(); }

std::shared_ptr<McapPoseWriter> add_mcap_out(ReplayOptions& opt, const std::string& path) {
  if (path.empty()) return nullptr;
  auto w = std::make_shared<McapPoseWriter>(path);
  auto prev = opt.on_pose;
  opt.on_pose = [w, prev](const PoseSample& s) {
    if (prev) prev(s);
    w->write(s);
  };
  return w;
}

}  // namespace kestrel::cli

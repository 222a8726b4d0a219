#include "kestrel/mcap_out.hpp"

#include <climits>

#include "kestrel/drivers/ros2_msgs.hpp"

namespace kestrel::cli {

McapPoseWriter::McapPoseWriter(const std::string& path) {
  drivers::mcap::WriterOptions o;
  o.chunk_size_bytes = 256u << 10;  // about 300 poses: a crash loses at most ~10 s at 30 Hz
  w_.open(path, o);
  const char* type = "nav_msgs/msg/Odometry";
  odom_ = w_.add_channel(w_.add_schema(type, "ros2msg", drivers::ros2::schema_text(type)),
                         "/kestrel/odometry", "cdr");
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

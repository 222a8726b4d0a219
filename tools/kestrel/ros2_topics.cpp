#include "kestrel/ros2_topics.hpp"

#include <cmath>
#include <string>
#include <utility>

#include "kestrel/drivers/ros2_msgs.hpp"

namespace kestrel::cli {
namespace {

const Ros2TopicInfo kTopics[kRos2Topics] = {
    {"/kestrel/odometry", "nav_msgs/msg/Odometry"},
    {"/tf", "tf2_msgs/msg/TFMessage"},
    {"/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"},
    {"/kestrel/map_points", "sensor_msgs/msg/PointCloud2"},
    {"/kestrel/map_markers", "visualization_msgs/msg/MarkerArray"},
    {"/kestrel/dense_map", "sensor_msgs/msg/PointCloud2"},
};

drivers::ros2::Pose pose_of(const Eigen::Isometry3d& T) {
  const Eigen::Quaterniond q(T.linear());
  drivers::ros2::Pose p;
  p.position = {T.translation().x(), T.translation().y(), T.translation().z()};
  p.orientation_xyzw = {q.x(), q.y(), q.z(), q.w()};
  return p;
}

}  // namespace

const Ros2TopicInfo& ros2_topic_info(Ros2Topic t) { return kTopics[static_cast<int>(t)]; }

void Ros2Output::publish(Ros2Topic t, int64_t t_ns) {
  const int i = static_cast<int>(t);
  // MCAP wants log times in order per channel for indexed reading, and a
  // Foxglove client plots them in order too.
  if (t_ns < last_topic_t_ns_[i]) t_ns = last_topic_t_ns_[i];
  last_topic_t_ns_[i] = t_ns;
  sink_.publish(t, t_ns, buf_);
  ++count_[i];
}

void Ros2Output::write_diagnostics(const core::PoseSample& s) {
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
  publish(Ros2Topic::kDiagnostics, s.t_ns);
}

// A closed loop as it happens: one segment between its two keyframes, where
// the map put them at the closure (ns loop_edges, id = the loop's index). The
// final markers redraw every loop where the map ends up.
void Ros2Output::write_loop_edge(const core::PoseSample& s) {
  if (!s.map.active || s.map.loop_closures <= loops_drawn_) return;
  loops_drawn_ = s.map.loop_closures;
  std::vector<drivers::ros2::Marker> a(1);
  a[0].t_ns = s.t_ns;
  a[0].frame_id = "map";
  a[0].ns = "loop_edges";
  a[0].id = static_cast<int32_t>(s.map.loop_closures - 1);
  a[0].type = drivers::ros2::Marker::kLineList;
  a[0].scale = {0.02, 0, 0};
  a[0].color_rgba = {1.0f, 0.3f, 0.1f, 1.0f};
  a[0].points.push_back({s.map.loop_p_M_query[0], s.map.loop_p_M_query[1], s.map.loop_p_M_query[2]});
  a[0].points.push_back(
      {s.map.loop_p_M_candidate[0], s.map.loop_p_M_candidate[1], s.map.loop_p_M_candidate[2]});
  drivers::ros2::encode(a, buf_);
  publish(Ros2Topic::kMarkers, s.t_ns);
}

void Ros2Output::on_pose(const core::PoseSample& s) {
  // Repeated stamps are skipped: one odometry message per time.
  if (s.t_ns < 0 || s.t_ns <= last_t_ns_) return;
  last_t_ns_ = s.t_ns;
  T_map_odom_ = s.map.active ? s.map.T_map_odom() : Eigen::Isometry3d::Identity();
  drivers::ros2::Odometry m;
  m.t_ns = s.t_ns;
  m.frame_id = "odom";
  m.child_frame_id = "base_link";
  m.pose.position = {s.p_WB().x(), s.p_WB().y(), s.p_WB().z()};
  m.pose.orientation_xyzw = {s.q_WB().x(), s.q_WB().y(), s.q_WB().z(), s.q_WB().w()};
  if (s.pose_cov_valid) {
    // Ours is [dp_W; dtheta_B]; ROS's pose covariance is (x y z) then rotation
    // about the fixed axes of the parent frame: dtheta_W = R_WB dtheta_B.
    Eigen::Matrix<double, 6, 6> J = Eigen::Matrix<double, 6, 6>::Identity();
    J.bottomRightCorner<3, 3>() = s.q_WB().toRotationMatrix();
    const Eigen::Matrix<double, 6, 6> C = J * s.covariance().cov * J.transpose();
    for (int i = 0; i < 6; ++i)
      for (int j = 0; j < 6; ++j) m.pose_covariance[static_cast<size_t>(i * 6 + j)] = C(i, j);
  } else {
    m.pose_covariance[0] = -1;  // no covariance from this backend (REP 145's "unknown")
  }
  const Eigen::Vector3d v_B = s.q_WB().conjugate() * s.v_WB();  // twist is in the child frame
  m.linear = {v_B.x(), v_B.y(), v_B.z()};
  m.angular = {s.omega_B().x(), s.omega_B().y(), s.omega_B().z()};
  m.twist_covariance[0] = -1;
  drivers::ros2::encode(m, buf_);
  publish(Ros2Topic::kOdometry, s.t_ns);

  // REP 105: map -> odom is the map's correction (identity without a map),
  // odom -> base_link the continuous odometry.
  std::vector<drivers::ros2::TransformStamped> tf(2);
  const drivers::ros2::Pose mo = pose_of(T_map_odom_);
  tf[0].t_ns = tf[1].t_ns = s.t_ns;
  tf[0].frame_id = "map";
  tf[0].child_frame_id = "odom";
  tf[0].translation = mo.position;
  tf[0].rotation_xyzw = mo.orientation_xyzw;
  tf[1].frame_id = "odom";
  tf[1].child_frame_id = "base_link";
  tf[1].translation = m.pose.position;
  tf[1].rotation_xyzw = m.pose.orientation_xyzw;
  drivers::ros2::encode(tf, buf_);
  publish(Ros2Topic::kTf, s.t_ns);
  write_diagnostics(s);
  write_loop_edge(s);
}

void Ros2Output::on_cloud(const MapCloud& c) {
  xyz_.resize(3 * static_cast<size_t>(c.n));
  const Eigen::Matrix3f R = T_map_odom_.linear().cast<float>();
  const Eigen::Vector3f t = T_map_odom_.translation().cast<float>();
  for (int i = 0; i < c.n; ++i) {
    const Eigen::Vector3f p = R * Eigen::Vector3f(c.xyz_W[3 * i], c.xyz_W[3 * i + 1], c.xyz_W[3 * i + 2]) + t;
    for (int k = 0; k < 3; ++k) xyz_[3 * static_cast<size_t>(i) + static_cast<size_t>(k)] = p[k];
  }
  drivers::ros2::PointCloudXyz m;
  m.t_ns = c.t_ns;
  m.frame_id = "map";
  m.xyz = xyz_.data();
  m.n = static_cast<uint32_t>(c.n);
  drivers::ros2::encode(m, buf_);
  publish(Ros2Topic::kMapPoints, c.t_ns);
}

void Ros2Output::on_keyframe(const KeyframePose& k) {
  Eigen::Isometry3d T_WC = Eigen::Isometry3d::Identity();
  T_WC.linear() =
      Eigen::Quaterniond(k.q_WC[0], k.q_WC[1], k.q_WC[2], k.q_WC[3]).normalized().toRotationMatrix();
  T_WC.translation() = Eigen::Vector3d(k.p_WC[0], k.p_WC[1], k.p_WC[2]);
  // An ARROW points along its pose's x; the camera looks along its z, so the
  // marker's frame is the camera's turned -90 degrees about y (x -> z).
  Eigen::Isometry3d T_arrow = T_map_odom_ * T_WC;
  T_arrow.linear() =
      T_arrow.linear() * Eigen::AngleAxisd(-M_PI / 2, Eigen::Vector3d::UnitY()).toRotationMatrix();
  std::vector<drivers::ros2::Marker> a(1);
  a[0].t_ns = k.t_ns;
  a[0].frame_id = "map";
  a[0].ns = "keyframes";
  a[0].id = next_keyframe_id_++;
  a[0].type = drivers::ros2::Marker::kArrow;
  a[0].pose = pose_of(T_arrow);
  a[0].scale = {0.15, 0.02, 0.02};  // length, shaft and head width [m]: a hand-held camera's size
  a[0].color_rgba = {0.2f, 0.6f, 1.0f, 1.0f};
  drivers::ros2::encode(a, buf_);
  publish(Ros2Topic::kMarkers, k.t_ns);
}

void Ros2Output::on_final(const MapFinal& f) {
  const int64_t t_ns = last_t_ns_ == INT64_MIN ? 0 : last_t_ns_;
  std::vector<drivers::ros2::Marker> a(1);
  a[0].t_ns = t_ns;
  a[0].frame_id = "map";
  a[0].action = drivers::ros2::Marker::kDeleteAll;  // the flight's arrows: the map has moved them since
  drivers::ros2::Marker path;
  path.t_ns = t_ns;
  path.frame_id = "map";
  path.ns = "keyframe_path";
  path.type = drivers::ros2::Marker::kLineStrip;
  path.scale = {0.01, 0, 0};  // line width [m]
  path.color_rgba = {0.2f, 0.6f, 1.0f, 1.0f};
  for (const MapFinal::Keyframe& k : f.keyframes)
    path.points.push_back({k.T_MB.translation().x(), k.T_MB.translation().y(), k.T_MB.translation().z()});
  if (path.points.size() >= 2) a.push_back(std::move(path));
  drivers::ros2::Marker loops;
  loops.t_ns = t_ns;
  loops.frame_id = "map";
  loops.ns = "loop_edges";
  loops.type = drivers::ros2::Marker::kLineList;
  loops.scale = {0.02, 0, 0};
  loops.color_rgba = {1.0f, 0.3f, 0.1f, 1.0f};
  for (const MapFinal::Loop& l : f.loops) {
    loops.points.push_back({l.p_M_query.x(), l.p_M_query.y(), l.p_M_query.z()});
    loops.points.push_back({l.p_M_candidate.x(), l.p_M_candidate.y(), l.p_M_candidate.z()});
  }
  if (!loops.points.empty()) a.push_back(std::move(loops));
  drivers::ros2::encode(a, buf_);
  publish(Ros2Topic::kMarkers, t_ns);
}

void Ros2Output::on_dense(const core::TsdfMap& m) {
  std::vector<core::SurfacePoint> pts;
  m.extract_surface(pts);
  xyz_.resize(3 * pts.size());
  rgb_.resize(3 * pts.size());
  for (std::size_t i = 0; i < pts.size(); ++i) {
    for (std::size_t k = 0; k < 3; ++k) {
      xyz_[3 * i + k] = pts[i].p[static_cast<int>(k)];
      rgb_[3 * i + k] = pts[i].rgb[k];
    }
  }
  drivers::ros2::PointCloudXyz c;
  c.t_ns = last_t_ns_ == INT64_MIN ? 0 : last_t_ns_;
  c.frame_id = "odom";  // fused along the odometry (W), as --dense-out
  c.xyz = xyz_.data();
  c.rgb = rgb_.data();
  c.n = static_cast<uint32_t>(pts.size());
  drivers::ros2::encode(c, buf_);
  publish(Ros2Topic::kDenseMap, c.t_ns);
}

void connect_ros2_output(ReplayOptions& opt, const std::shared_ptr<Ros2Output>& out,
                         double map_points_rate_hz) {
  auto pose = opt.on_pose;
  opt.on_pose = [out, pose](const core::PoseSample& s) {
    if (pose) pose(s);
    out->on_pose(s);
  };
  auto cloud = opt.on_map_cloud;
  opt.on_map_cloud = [out, cloud](const MapCloud& c) {
    if (cloud) cloud(c);
    out->on_cloud(c);
  };
  auto kf = opt.on_keyframe;
  opt.on_keyframe = [out, kf](const KeyframePose& k) {
    if (kf) kf(k);
    out->on_keyframe(k);
  };
  auto fin = opt.on_map_final;
  opt.on_map_final = [out, fin](const MapFinal& f) {
    if (fin) fin(f);
    out->on_final(f);
  };
  auto dense = opt.on_dense_finished;
  opt.on_dense_finished = [out, dense](const core::TsdfMap& m) {
    if (dense) dense(m);
    out->on_dense(m);
  };
  opt.map_points_rate_hz = std::max(opt.map_points_rate_hz, map_points_rate_hz);
}

}  // namespace kestrel::cli

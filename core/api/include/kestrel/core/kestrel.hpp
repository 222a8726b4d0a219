// Kestrel embedded: the estimator behind a plain C++ API, without our threads,
// rings, drivers or ROS. The caller feeds IMU samples and RGB-D frames from
// its own loop or threads (one at a time: the object is not thread-safe) and
// receives the state through a callback, synchronously, from inside the feed
// call that changed it. docs/api.md has a complete example.
//
// Contract, enforced and counted rather than trusted:
// - time order: feed IMU and frames merged by time; an IMU sample not after the
//   previous one is rejected by the propagator, a frame not after the previous
//   frame is rejected here (counters().frames_rejected);
// - a frame is used with the IMU fed so far: feed the IMU up to a frame's time
//   before the frame for the best prediction;
// - the image views need to stay valid only during the call.
// No allocation in steady state (after the first frames), no locks, no I/O.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel {

// The estimate, in the frames of docs/frames.md: W has gravity along -z and
// its origin and yaw at the first state; B is the IMU body.
struct State {
  int64_t t_ns = 0;  // time of the newest sample used
  Eigen::Vector3d p_WB = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_WB = Eigen::Quaterniond::Identity();
  Eigen::Vector3d v_WB = Eigen::Vector3d::Zero();
  Eigen::Vector3d gyro_bias_rps = Eigen::Vector3d::Zero();
  Eigen::Vector3d acc_bias_mps2 = Eigen::Vector3d::Zero();
  core::TrackingQuality quality = core::TrackingQuality::kUninitialized;
  uint32_t reset_counter = 0;  // increments when the estimate jumps (re-initialisation)
  bool from_frame = false;     // updated by a camera frame (else by an IMU sample)
};

struct EmbeddedCounters {
  core::EstimatorCounters estimator;  // IMU in/used/rejected, frames in/used, resets
  uint64_t frames_rejected = 0;       // out of order / duplicate time / no colour image
  uint64_t callbacks = 0;
};

class Estimator {
 public:
  using StateCallback = std::function<void(const State&)>;

  // backend: a core::make_estimator name ("vo", "imu", ...); throws
  // std::invalid_argument naming the known backends for an unknown one.
  explicit Estimator(const Rig& rig, const std::string& backend = "vo");
  ~Estimator();
  Estimator(const Estimator&) = delete;
  Estimator& operator=(const Estimator&) = delete;

  // Called from inside feed_imu / feed_rgbd whenever the state changed; with
  // imu_rate false only on frames. Set it before feeding.
  void on_state(StateCallback cb, bool imu_rate = true);

  // Both return true when the state changed (and the callback ran).
  bool feed_imu(const ImuSample& s);
  bool feed_rgbd(int64_t t_ns, const ImageView& rgb, const ImageView& depth);

  const State& state() const { return state_; }
  const EmbeddedCounters& counters() const;
  const char* backend_name() const;

 private:
  void publish(bool from_frame);
  std::unique_ptr<core::Estimator> impl_;
  StateCallback cb_;
  bool imu_rate_ = true;
  State state_;
  mutable EmbeddedCounters counters_;
  int64_t last_frame_t_ns_ = -1;
  uint32_t frame_seq_ = 0;
};

}  // namespace kestrel

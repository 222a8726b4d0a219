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
// No allocation in steady state (after the first frames), no locks, no I/O, in
// the tracking and IMU paths. The map (local mapping, loop closing) is the
// command line's: on for the backends that have one, its work run where
// MapWork says; it allocates, as the map threads of `kestrel run` do.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "kestrel/core/estimator.hpp"
#include "kestrel/core/estimator_config.hpp"
#include "kestrel/core/estimator_factory.hpp"
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
  // The map's word (backends with a map): T_map_odom moves W onto the map frame M after a loop
  // closure or a relocalisation; the pose in the map is T_map_odom * T_WB. Identity without a map.
  bool map_active = false;
  Eigen::Isometry3d T_map_odom = Eigen::Isometry3d::Identity();
  uint64_t loop_closures = 0;
};

// Where a backend's map work (local mapping, loop closing) runs.
enum class MapWork : uint8_t {
  // Inside feed_rgbd, after the frame, until the map has taken it: the results
  // of `kestrel replay --pace lockstep`. The simplest; the feed call then
  // takes the map's time too.
  kInline,
  // The caller runs map_step() on a thread of its own (not real time), so the
  // feed calls never wait for the map, as in `kestrel run`.
  kCaller,
};

struct EmbeddedCounters {
  core::EstimatorCounters estimator;  // IMU in/used/rejected, frames in/used, resets
  uint64_t frames_rejected = 0;       // out of order / duplicate time / no colour image
  uint64_t callbacks = 0;
};

class Estimator {
 public:
  using StateCallback = std::function<void(const State&)>;

  // backend: a core::make_estimator name ("auto", "window", "vo", ...) with
  // the command line's defaults (docs/config.md), map and loop closing
  // included; throws std::invalid_argument naming the known backends for an
  // unknown one.
  explicit Estimator(const Rig& rig, const std::string& backend = "auto",
                     MapWork map_work = MapWork::kInline);
  // Every option (core::EstimatorConfig: EstimatorConfig::defaults(backend)
  // changed in code, or a config file through tools::load_config(path).estimator);
  // throws std::invalid_argument listing every bad option.
  Estimator(const Rig& rig, const core::EstimatorConfig& config, MapWork map_work = MapWork::kInline);
  ~Estimator();
  Estimator(const Estimator&) = delete;
  Estimator& operator=(const Estimator&) = delete;

  // Called from inside feed_imu / feed_rgbd whenever the state changed; with
  // imu_rate false only on frames. Set it before feeding.
  void on_state(StateCallback cb, bool imu_rate = true);

  // Both return true when the state changed (and the callback ran).
  bool feed_imu(const ImuSample& s);
  bool feed_rgbd(int64_t t_ns, const ImageView& rgb, const ImageView& depth);

  // MapWork::kCaller: runs the map work handed over so far (from one thread
  // at a time, never the feeding one's hot path); true when there was some.
  // With kInline, or without a map, it does nothing and returns false.
  bool map_step();
  bool has_map() const;

  const State& state() const { return state_; }
  const EmbeddedCounters& counters() const;
  const char* backend_name() const;

 private:
  void publish(bool from_frame);
  void run_map();
  bool step_map_workers(bool* busy);
  std::unique_ptr<core::Estimator> impl_;
  MapWork map_work_ = MapWork::kInline;
  StateCallback cb_;
  bool imu_rate_ = true;
  State state_;
  mutable EmbeddedCounters counters_;
  int64_t last_frame_t_ns_ = -1;
  uint32_t frame_seq_ = 0;
};

}  // namespace kestrel

// The estimator as the pipeline sees it: fed IMU samples and RGB-D frames in
// time order, it keeps a newest state. Backends (IMU dead reckoning now; the
// keyframe window and the EKF later) implement this, and the pipeline's
// threads, the replay harness and embedders call nothing else.
#pragma once

#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/core/imu_propagator.hpp"
#include "kestrel/msgs.hpp"
#include "kestrel/rt/latency_histogram.hpp"

namespace kestrel::core {

// A frame as handed to the estimator: views onto pixels the caller owns for
// the duration of the call.
struct RgbdFrame {
  int64_t t_ns = 0;
  uint32_t seq = 0;
  ImageView rgb;    // data == nullptr when absent
  ImageView depth;  // registered to rgb; data == nullptr when absent
  // A stereo rig: rgb and right are the rectified pair (drivers/stereo), the
  // features' depth comes from matching them; data == nullptr when absent.
  ImageView right;
};

enum class TrackingQuality : uint8_t {
  kUninitialized = 0,
  kImuOnly = 1,  // coasting on the IMU: the covariance grows without bound
  kTracking = 2,
  kLost = 3,
  // Tracking on the camera alone: a backend without an IMU (rgbd), or the
  // window backend while its IMU is silent (docs/real-imagery.md). The pose
  // is as good as tracking; attitude is not tied to gravity meanwhile.
  kVisionOnly = 4,
};
// "uninitialized", "imu_only", "tracking", "lost", "vision_only": the names
// outputs print (ROS diagnostics, Python).
const char* tracking_quality_name(TrackingQuality q);

// Covariance of a pose estimate, 6x6 in the order [dp_W; dtheta_B]:
//   dp_W     position error in W [m] (x, y, z of W): p_WB = p_hat + dp_W
//   dtheta_B rotation error in B [rad] (x, y, z of the body), a right
//            perturbation: R_WB = R_hat Exp(dtheta_B)
// (the window optimizer's tangent, window_problem.hpp). Frames of a flight
// controller are converted in its adapter only (tools/mavlink).
struct PoseCovariance {
  Eigen::Matrix<double, 6, 6> cov = Eigen::Matrix<double, 6, 6>::Zero();
  int64_t t_ns = 0;    // the state time it was computed for
  bool valid = false;  // false: the backend has none (vo, imu) or lost it (reset)
};

// Where the odometry frame W sits in the map frame M (backends with a map;
// docs/map.md). The odometry stays continuous; corrections of the map (loop
// closures, relocalisations, a loaded map) move T_map_odom instead.
// Trivially copyable: it crosses threads in mailboxes and rings.
struct MapFrameState {
  bool active = false;         // a map is built (or used)
  bool localized = false;      // T_map_odom is known (false: lost, or a loaded map not found yet)
  uint32_t alignment = 0;      // steps on every change of T_map_odom
  double p[3] = {0, 0, 0};     // T_map_odom: translation [m]
  double q[4] = {1, 0, 0, 0};  // and rotation (w x y z)
  uint64_t loop_closures = 0;
  // The newest closed loop's two keyframes (camera positions in M at its
  // closure), for drawing it live; zero before the first.
  double loop_p_M_query[3] = {0, 0, 0};
  double loop_p_M_candidate[3] = {0, 0, 0};
  uint64_t relocalisations = 0;
  uint32_t keyframes = 0;  // in the map
  uint32_t points = 0;
  Eigen::Isometry3d T_map_odom() const {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = Eigen::Quaterniond(q[0], q[1], q[2], q[3]).normalized().toRotationMatrix();
    T.translation() = Eigen::Vector3d(p[0], p[1], p[2]);
    return T;
  }
  void set_T_map_odom(const Eigen::Isometry3d& T) {
    const Eigen::Quaterniond r(T.linear());
    for (int i = 0; i < 3; ++i) p[i] = T.translation()[i];
    q[0] = r.w();
    q[1] = r.x();
    q[2] = r.y();
    q[3] = r.z();
  }
};

struct EstimatorOutput {
  NavState state;
  TrackingQuality quality = TrackingQuality::kUninitialized;
  uint32_t reset_counter = 0;
  // Between its updates a backend may keep the last one (the window backend:
  // the last applied solve's, so pose_cov.t_ns < state.t_ns; the EKF: its
  // propagated covariance, at the state's time).
  PoseCovariance pose_cov;
  MapFrameState map;
};

// Why a backend decided it had lost the truth (divergence.hpp).
enum class DivergenceCause : uint8_t {
  kNone = 0,
  kCoastTimeout,
  kSpeed,
  kAccBias,
  kGyroBias,
  kCovariance,
  kVisualImuDisagreement,
  kNonFinite,
};
constexpr int kDivergenceCauseCount = 8;
const char* to_string(DivergenceCause c);

struct DivergenceCounts {
  uint64_t divergences = 0;  // detections that made the backend re-initialise
  std::array<uint64_t, kDivergenceCauseCount> by_cause{};
  // Restarts while already lost (no fix came back within another coast span):
  // they bound the drift of the placeholder pose, they are not new divergences.
  uint64_t restarts_while_lost = 0;
  uint64_t coast_timeouts = 0;  // coasts that reached max_coast_s: reported lost, state kept
  int64_t coast_ns = 0;         // IMU-only time after a fix, up to max_coast_s each time
  int64_t lost_ns = 0;          // time reported lost
};

struct EstimatorCounters {
  uint64_t imu_in = 0;
  uint64_t imu_used = 0;
  uint64_t frames_in = 0;
  uint64_t frames_used = 0;
  uint64_t resets = 0;
  ImuRejectCounts imu_rejects;
  DivergenceCounts divergence;  // zero for backends without divergence detection (imu)
};

class MapSystem;  // core/mapping

// One keyframe of the map at the end of a flight (MapSystem::keyframe_poses).
struct MapKeyframePose {
  int64_t t_ns = 0;
  Eigen::Isometry3d T_MB = Eigen::Isometry3d::Identity();  // refined, in the map frame
  Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();  // odometry frame, when it was taken
};

class Tracker;

// A backend's optimizer, for status lines and the viewer (EstimatorView).
struct OptimizerStatus {
  uint64_t jobs = 0;     // solves asked for
  uint64_t applied = 0;  // solves whose result was taken
  uint64_t failures = 0;
  uint64_t skipped_busy = 0;  // frames that found the optimizer still busy
  uint64_t resets = 0;        // window restarts
  int64_t last_solve_ns = 0;
};

// Work a backend runs off the thread that feeds it, on a thread the pipeline
// gives it from its thread table (docs/threads.md): the window's optimizer,
// the map's local mapping and loop closing. The pipeline schedules workers by
// kind, without knowing the backend.
class EstimatorWorker {
 public:
  enum class Kind : uint8_t { kOptimizer, kMapping, kLoop };
  virtual ~EstimatorWorker() = default;
  virtual Kind kind() const = 0;
  // Before the first sample, by a caller that will run step() on a thread of
  // its own. Without it the optimizer runs inline in add_frame, which is
  // deterministic (lockstep replay, tests), and bounded by its iteration
  // limit only; on a thread its time budget applies. The map's workers do
  // nothing unless someone steps them.
  virtual void set_threaded(bool /*on*/) {}
  // One unit of queued work; false when there was none. The worker's thread only.
  virtual bool step() = 0;
  // Workers that return the same non-null group share state: their callers
  // never run step() of two of them at once (one mutex per group; core takes
  // no locks). The map's two workers share the map.
  virtual const void* group() const { return nullptr; }
  // Work that follows step() outside the group's exclusion, on the same
  // thread (the global bundle adjustment solves its own copy of the map);
  // false when there was none.
  virtual bool step_ungrouped() { return false; }
  // Work was handed over and is not finished (deterministic paces wait for it).
  virtual bool busy() const { return false; }
  // Per step [ns]; read it after the worker's thread stopped. nullptr: not measured.
  virtual const rt::LatencyHistogram* latency() const { return nullptr; }
};

// A backend's workers, at most one of each kind, fixed for its life.
struct EstimatorWorkers {
  std::array<EstimatorWorker*, 3> list{};
  int count = 0;
  void add(EstimatorWorker* w) { list[static_cast<size_t>(count++)] = w; }
  EstimatorWorker* find(EstimatorWorker::Kind k) const {
    for (int i = 0; i < count; ++i)
      if (list[static_cast<size_t>(i)]->kind() == k) return list[static_cast<size_t>(i)];
    return nullptr;
  }
  EstimatorWorker* const* begin() const { return list.data(); }
  EstimatorWorker* const* end() const { return list.data() + count; }
};

// What a display reads of a backend, from the thread that feeds it.
struct EstimatorView {
  const Tracker* tracker = nullptr;  // the tracking front end; nullptr for imu
  bool has_optimizer = false;        // optimizer is valid
  OptimizerStatus optimizer;
};

class Estimator {
 public:
  virtual ~Estimator() = default;
  virtual const char* name() const = 0;
  // Both return true when the newest output changed.
  virtual bool add_imu(const ImuSample& s) = 0;
  virtual bool add_frame(const RgbdFrame& f) = 0;
  virtual const EstimatorOutput& output() const = 0;
  virtual const EstimatorCounters& counters() const = 0;

  // The work this backend runs beside the feeding thread (none for most).
  virtual EstimatorWorkers workers() { return {}; }
  // The map (nullptr without one: window and ekf with mapping on, docs/map.md).
  // Keyframes reach it through a lock-free ring the tracking side may
  // overrun; its own work is the kMapping and kLoop workers. The harness
  // turns on its loop log before the flight; save(), keyframe_poses() and
  // the rest are read after the workers' threads stopped.
  virtual MapSystem* map_system() const { return nullptr; }
  bool has_map() const { return map_system() != nullptr; }
  // For displays, from the thread that feeds.
  virtual EstimatorView view() const { return {}; }

  // One line of backend-specific counters for reports ("" when none).
  virtual std::string backend_summary() const { return {}; }
  // The camera-IMU time offset the backend estimated online on top of the
  // rig's time_offset_cam_imu_ns [s] (a frame stamped t was taken at t + it);
  // false when it does not estimate one. Read it from the thread that feeds.
  virtual bool estimated_time_offset_s(double* /*td_s*/) const { return false; }
  // W's z axis is up (gravity along -z): true for every backend with an IMU.
  // A backend without one (rgbd) starts W at its first body pose, tilted as
  // that pose was, so only a full SE(3) alignment compares it with the truth.
  virtual bool world_levelled() const { return true; }
};

// IMU-only dead reckoning after a static initialisation. Named as what it is:
// it ignores the camera, and its error grows quadratically with time.
class DeadReckoningEstimator final : public Estimator {
 public:
  // moving_start_after_ns: with no still window by then, start anyway with
  // gravity from the mean specific force (a moving start). No default: each
  // backend passes its own config value (vo, ekf, window: 0.25 s).
  explicit DeadReckoningEstimator(const Rig& rig, int64_t moving_start_after_ns);
  const char* name() const override { return "imu-dead-reckoning"; }
  bool add_imu(const ImuSample& s) override;
  bool add_frame(const RgbdFrame& f) override;
  const EstimatorOutput& output() const override { return out_; }
  const EstimatorCounters& counters() const override;
  // The state came from a moving window, not a still one (tilt and velocity are guesses).
  bool started_moving() const { return started_moving_; }

 private:
  StaticInitializer init_;
  ImuPropagator prop_;
  EstimatorOutput out_;
  mutable EstimatorCounters counters_;
  int64_t first_t_ns_ = -1;
  int64_t moving_start_after_ns_;
  bool started_moving_ = false;
};

}  // namespace kestrel::core

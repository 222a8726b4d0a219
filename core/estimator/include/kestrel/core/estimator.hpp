// The estimator as the pipeline sees it: fed IMU samples and RGB-D frames in
// time order, it keeps a newest state. Backends (IMU dead reckoning now; the
// keyframe window and the EKF later) implement this, and the pipeline's
// threads, the replay harness and embedders call nothing else.
#pragma once

#include <cstdint>
#include <string>

#include "kestrel/core/imu_propagator.hpp"
#include "kestrel/msgs.hpp"
#include "kestrel/rt/latency_histogram.hpp"

namespace kestrel::core {

// A frame as handed to the estimator: views onto pixels the caller owns for
// the duration of the call.
struct RgbdFrame {
  int64_t t_ns = 0;
  uint32_t seq = 0;
  ImageView rgb;     // data == nullptr when absent
  ImageView depth;   // registered to rgb; data == nullptr when absent
};

enum class TrackingQuality : uint8_t {
  kUninitialized = 0,
  kImuOnly = 1,     // coasting on the IMU: the covariance grows without bound
  kTracking = 2,
  kLost = 3,
  // Tracking on the camera alone: a backend without an IMU (rgbd), or the
  // window backend while its IMU is silent (docs/real-imagery.md). The pose
  // is as good as tracking; attitude is not tied to gravity meanwhile.
  kVisionOnly = 4,
};

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

struct EstimatorOutput {
  NavState state;
  TrackingQuality quality = TrackingQuality::kUninitialized;
  uint32_t reset_counter = 0;
  // Between its updates a backend may keep the last one (the window backend:
  // the last applied solve's, so pose_cov.t_ns < state.t_ns; the EKF: its
  // propagated covariance, at the state's time).
  PoseCovariance pose_cov;
};

struct EstimatorCounters {
  uint64_t imu_in = 0;
  uint64_t imu_used = 0;
  uint64_t frames_in = 0;
  uint64_t frames_used = 0;
  uint64_t resets = 0;
  ImuRejectCounts imu_rejects;
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

  // Backends with an optimizer. By default add_frame runs it inline, which is
  // deterministic (lockstep replay, tests). After set_threaded_optimizer(true)
  // (before the first sample) add_frame only queues the work and the caller
  // runs optimizer_step() on a thread of its own: a lock-free hand-off both
  // ways, so a slow solve delays refinement, never the pose output.
  virtual bool has_optimizer() const { return false; }
  virtual void set_threaded_optimizer(bool /*on*/) {}
  // One queued solve; false when there was nothing to do. Optimizer thread only.
  virtual bool optimizer_step() { return false; }
  // Per solve [ns]; read it after the optimizer thread stopped.
  virtual const rt::LatencyHistogram* optimizer_latency() const { return nullptr; }
  // One line of backend-specific counters for reports ("" when none).
  virtual std::string backend_summary() const { return {}; }
};

// IMU-only dead reckoning after a static initialisation. Named as what it is:
// it ignores the camera, and its error grows quadratically with time.
class DeadReckoningEstimator final : public Estimator {
 public:
  // moving_start_after_ns: with no still window by then, start anyway with
  // gravity from the mean specific force (a moving start).
  explicit DeadReckoningEstimator(const Rig& rig, int64_t moving_start_after_ns = 2'000'000'000);
  const char* name() const override { return "imu-dead-reckoning"; }
  bool add_imu(const ImuSample& s) override;
  bool add_frame(const RgbdFrame& f) override;
  const EstimatorOutput& output() const override { return out_; }
  const EstimatorCounters& counters() const override;

 private:
  StaticInitializer init_;
  ImuPropagator prop_;
  EstimatorOutput out_;
  mutable EstimatorCounters counters_;
  int64_t first_t_ns_ = -1;
  int64_t moving_start_after_ns_;
};

}  // namespace kestrel::core

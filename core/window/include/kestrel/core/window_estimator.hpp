// The full estimator of paper 000: the front end (IMU propagation + tracking,
// frontend_odometry.hpp) on the tracking side and the sliding-window
// optimizer (window_optimizer.hpp: reprojection + depth + IMU preintegration
// over S recent frames and N keyframes) behind it.
//
// Data flow, per tracked frame: the tracker's inlier observations (persistent
// landmark ids) and the IMU preintegrated since the previous window frame
// become one job; the optimizer adds it to the window and solves; the newest
// optimized state, propagated through the preintegrations of every frame
// queued since, replaces the front end's propagated state, and the tracker's
// keyframe takes its refined pose. The pose output is always the front end's
// IMU-rate propagation: it never waits for a solve.
//
// Threading: single-threaded by default (the optimizer runs inside add_frame /
// add_imu: bit-exact replays). set_threaded_optimizer(true) splits the work:
// the tracking thread queues jobs into a lock-free ring, another thread runs
// optimizer_step(), and results come back through a seqlock mailbox. Job
// buffers are a fixed pool; when the optimizer is behind, frames are left out
// of the window (counted) and the IMU chain bridges them.
//
// Failure handling: a solve that fails, returns non-finite numbers, an absurd
// speed, or a state far from the front end's is not applied (counted); a few
// in a row re-initialise the window from the front end's state (counted in
// the reset counter). An IMU gap too long to preintegrate does the same.
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>

#include "kestrel/core/estimator.hpp"
#include "kestrel/core/frontend_odometry.hpp"
#include "kestrel/core/map_system.hpp"
#include "kestrel/core/time_offset_calibrator.hpp"
#include "kestrel/core/window_optimizer.hpp"
#include "kestrel/rt/mailbox.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::core {

struct WindowEstimatorOptions {
  FrontendOdometryOptions frontend = [] {
    FrontendOdometryOptions f;
    f.moving_start_after_ns = 250'000'000;  // the dynamic start: the window sorts out attitude and velocity
    return f;
  }();
  WindowOptions window;
  // false: every tracked frame enters the window (the S recent frames are
  // consecutive frames); true: keyframes only (cheaper, less accurate).
  bool keyframes_only = false;
  // The rig's IMU noise densities are a datasheet's, for a still sensor; on a
  // flying vehicle vibration and unmodelled effects make the real errors
  // larger. Every density is multiplied by this. 30 is what the real EuRoC
  // IMU needed (V1_01 hybrid: 6.4 cm at 1, 4.2 cm at 10, 2.1 cm at 30); on
  // the simulator's ideal-model IMU it costs a little (figure8: 1.0 -> 2.1 cm).
  // docs/optimizer.md, "Window estimator".
  double imu_noise_inflation = 30.0;
  int min_observations = 8;              // a frame with fewer stays out of the window
  double max_correction_m = 0.5;         // optimized vs propagated position beyond this: a failure
  double max_speed_mps = 25.0;           // an optimized speed beyond this: a failure
  int max_consecutive_failures = 3;      // then the window restarts
  int64_t max_imu_gap_ns = 200'000'000;  // a longer gap cannot be preintegrated (see continue_without_imu)
  // IMU failure in flight: frames go on into the window as vision-only states
  // (no IMU factor; velocity and biases held) while the front end tracks on
  // the camera alone, and when samples return the preintegration chain
  // restarts at the next frame: no window restart, no reset of the world
  // frame, the biases re-estimated by the new IMU factors from where they
  // were. false: a gap longer than max_imu_gap_ns restarts the window.
  bool continue_without_imu = true;
  bool zero_velocity_when_still = true;  // window.zero_velocity_sigma_mps on frames the IMU says are still
  // The IMU test alone also passes smooth flight at near-constant
  // acceleration; a frame counts as still only if the estimated speed agrees.
  double still_max_speed_mps = 0.05;
  // A keyframe the tracker re-located against its local map carries that
  // pose into the window as a factor, with the PnP's own sigma but at least
  // these (the map points carry the error of the keyframes that made them):
  // loose enough that the window's IMU and landmark terms still shape it,
  // tight enough to undo the chain's drift (docs/optimizer.md, "Local map").
  bool use_map_pose = true;
  double map_pose_sigma_m = 0.02;
  double map_pose_sigma_rad = 0.01;
  // The map (local mapping, loop closing, relocalisation; docs/map.md). Its
  // work runs on threads the caller provides (Estimator::mapping_step /
  // loop_step); without them nothing is mapped.
  MapSystemOptions map;
  // window.estimate_time_offset: the measurement of t_d that the window's
  // state follows (rotation correlation of vision against the gyro).
  TimeOffsetCalibratorOptions time_offset;
  // A frame pair's vision-only rotation needs this many depth-backed matches.
  int time_offset_min_matches = 20;

  std::string validate() const;
};

struct WindowEstimatorCounters {
  uint64_t jobs = 0;  // frames sent to the optimizer
  uint64_t solves_ok = 0;
  uint64_t applied = 0;   // results that corrected the front end
  uint64_t failures = 0;  // solves not applied (failed, non-finite, absurd, far off)
  uint64_t window_resets = 0;
  uint64_t skipped_busy = 0;  // tracked frames left out: the optimizer was behind
  uint64_t skipped_few_obs = 0;
  uint64_t skipped_no_imu = 0;  // a frame not followed by IMU before the next one
  uint64_t stale_results = 0;   // too old to propagate to now
  uint64_t imu_gaps = 0;
  uint64_t stationary_frames = 0;   // window frames given the zero-velocity factor
  uint64_t map_poses = 0;           // window frames given the local map's pose
  uint64_t vision_only_frames = 0;  // window frames without an IMU factor (IMU silent)
  // The tracker's far tracks (frontend.far_tracks): observations without depth.
  uint64_t far_observations = 0;
};

// Optimizer -> tracking side. Trivially copyable: crosses threads through the mailbox.
struct WindowSolveResult {
  uint64_t seq = 0;
  bool ok = false;
  bool reset_done = false;
  bool has_kf = false;
  PackedNavState x{};  // the newest window state (at the job's frame time)
  double td_s = 0.0;   // the window's time offset estimate (estimate_time_offset)
  int64_t kf_t_ns = 0;
  double kf_p[3] = {0, 0, 0}, kf_q[4] = {1, 0, 0, 0};  // T_WC of the tracker's keyframe
  int64_t solve_ns = 0;                                // wall time of this solve on the optimizer thread
};

class WindowEstimator final : public Estimator {
 public:
  explicit WindowEstimator(const Rig& rig, const WindowEstimatorOptions& opt = {});
  ~WindowEstimator() override;

  const char* name() const override { return "window"; }
  bool add_imu(const ImuSample& s) override;
  bool add_frame(const RgbdFrame& f) override;
  const EstimatorOutput& output() const override { return front_.output(); }
  const EstimatorCounters& counters() const override { return front_.counters(); }

  // The optimizer, and with the map its two workers.
  EstimatorWorkers workers() override;
  // Inline solves are bounded by the iteration limit only: a wall-clock budget
  // would make the result depend on the machine's load, and inline is the
  // bit-exact replay mode. On its own thread the time budget applies. The
  // optimizer worker's set_threaded / step / latency.
  void set_threaded_optimizer(bool on);
  bool optimizer_step();
  const rt::LatencyHistogram* optimizer_latency() const { return &opt_latency_; }
  std::string backend_summary() const override;
  bool estimated_time_offset_s(double* td_s) const override;

  MapSystem* map_system() const override { return map_.get(); }

  const WindowEstimatorCounters& window_counters() const { return wc_; }
  // Wall time of the newest solve whose result reached the tracking side
  // (0 before the first): a live figure for displays, read on the tracking thread.
  int64_t last_solve_ns() const { return last_solve_ns_; }
  EstimatorView view() const override;
  const FrontendOdometry& front() const { return front_; }

 private:
  class OptimizerWorker final : public EstimatorWorker {
   public:
    explicit OptimizerWorker(WindowEstimator& e) : e_(e) {}
    Kind kind() const override { return Kind::kOptimizer; }
    void set_threaded(bool on) override { e_.set_threaded_optimizer(on); }
    bool step() override { return e_.optimizer_step(); }
    const rt::LatencyHistogram* latency() const override { return e_.optimizer_latency(); }

   private:
    WindowEstimator& e_;
  };

  static constexpr int kPool = 6;    // jobs in flight (front -> optimizer)
  static constexpr int kChain = 16;  // preintegrations kept to propagate results to now

  struct Job {
    uint64_t seq = 0;
    bool reset = false;  // restart the window with this frame
    bool stationary = false;
    bool has_pim = false;
    bool keyframe = false;
    bool vision_only = false;  // no IMU factor from the previous window frame
    bool has_map_pose = false;
    Eigen::Isometry3d T_WB_map = Eigen::Isometry3d::Identity();
    double map_sigma_p_m = 0, map_sigma_rad = 0;
    int64_t t_ns = 0;
    int64_t tracker_kf_t_ns = -1;
    NavState guess;
    Preintegrated pim;
    int n_obs = 0;
    double td_meas_s = 0.0, td_meas_sigma_s = 0.0;  // the calibrator's t_d when this frame was queued
  };

  void queue_job(const RgbdFrame& f, const TrackResult& r);
  void process(int slot);  // optimizer side
  void poll_results();     // tracking side
  void apply(const WindowSolveResult& r);
  void submit_pending();
  void fail_and_maybe_reset();
  void map_before_tracking();
  void map_after_tracking(const RgbdFrame& f);
  WindowObservation* obs_of(int slot) { return obs_pool_.get() + static_cast<size_t>(slot) * max_obs_; }
  Eigen::Vector2d* vel_of(int slot) { return vel_pool_.get() + static_cast<size_t>(slot) * max_obs_; }
  double* dvel_of(int slot) { return dvel_pool_.get() + static_cast<size_t>(slot) * max_obs_; }
  // Image velocities of a frame's observations from the previous tracked frame (time offset).
  void image_velocities(int64_t t_ns, const WindowObservation* obs, int n, Eigen::Vector2d* vel);
  // Pixel and depth rates of the depth-backed observations, from the front
  // end's velocity and the gyro (time offset).
  void depth_velocities(const NavState& x, const WindowObservation* obs, int n, Eigen::Vector2d* vel,
                        double* dvel) const;
  // The camera's rotation since the tracker's keyframe from vision alone
  // (PnP on the keyframe's depth), handed to the time offset calibrator; a
  // new keyframe's observations are kept for the frames after it.
  void measure_camera_rotation(int64_t t_ns, const TrackResult& r);
  void remember_observations(int64_t t_ns);

  WindowEstimatorOptions opt_;
  Eigen::Isometry3d T_BC_;
  PreintegrationParams pim_params_;
  FrontendOdometry front_;
  std::unique_ptr<WindowOptimizer> window_;
  bool threaded_ = false;
  OptimizerWorker optimizer_worker_{*this};
  int max_obs_ = 0;

  // Job pool and the two rings of slot indices.
  std::unique_ptr<Job[]> jobs_;
  std::unique_ptr<WindowObservation[]> obs_pool_;
  std::unique_ptr<Eigen::Vector2d[]> vel_pool_;  // per observation of a job [px/s]
  // The previous tracked frame's observations by landmark id (sorted), for
  // the image velocities; fixed capacity (the tracker's feature budget).
  struct PrevObs {
    uint32_t id = 0;
    Eigen::Vector2d uv;
    double depth_m = 0;  // 0: none
  };

 public:
  using PrevObsView = PrevObs*;

 private:
  std::unique_ptr<PrevObs[]> prev_obs_;
  int prev_cap_ = 0, n_prev_ = 0;
  int64_t prev_t_ns_ = -1;
  std::unique_ptr<PrevObs[]> kf_obs_;  // the tracker's keyframe's observations by id [prev_cap_]
  int n_kf_obs_ = 0;
  int64_t kf_t_ns_ = -1;
  Eigen::Isometry3d kf_T_WC_ = Eigen::Isometry3d::Identity();
  PinholeK K_;
  std::unique_ptr<double[]> dvel_pool_;  // per observation of a job [m/s]
  std::unique_ptr<TimeOffsetCalibrator> calib_;
  std::unique_ptr<Correspondence2D3D[]> corr_;  // scratch of measure_camera_rotation [prev_cap_]
  Eigen::Vector3d last_gyro_rps_ = Eigen::Vector3d::Zero();
  double td_s_ = 0.0;              // the last applied solve's time offset
  rt::SpscRing<uint8_t, 8> todo_;  // front -> optimizer
  rt::SpscRing<uint8_t, 8> done_;  // optimizer -> front (slots to reuse)
  int free_slots_[kPool] = {};
  int n_free_ = 0;
  rt::Mailbox<WindowSolveResult> results_;
  WindowSolveResult inline_result_;
  bool inline_result_new_ = false;
  uint64_t last_result_version_ = 0;

  // Tracking side: preintegration since the last window frame.
  Preintegrated pim_;
  bool pim_active_ = false;
  int64_t t_last_frame_ns_ = 0;
  ImuSample last_sample_{};
  bool have_last_sample_ = false;
  int pending_slot_ = -1;  // a frame waiting for the IMU sample after it
  uint64_t next_seq_ = 1;
  Preintegrated chain_[kChain];  // pim of job seq k at k % kChain
  uint64_t chain_seq_[kChain] = {};
  uint64_t last_applied_seq_ = 0;
  int64_t last_solve_ns_ = 0;
  int consecutive_failures_ = 0;
  // Stationarity: the static initialiser's test (0.1 s block means agree),
  // run continuously; still while its last verdict is at most a block old.
  StaticInitializer still_;
  int64_t still_t_ns_ = -1;
  bool reset_requested_ = false;
  // The front end's divergence epoch this window was built in; results of
  // jobs sent before the newest re-initialisation describe the diverged
  // state and are never applied.
  uint64_t epoch_ = 0;
  uint64_t first_seq_of_epoch_ = 0;
  void follow_front_end_restart();

  // The map: the keyframe being held until the window has refined it, and
  // the newest state of the map's frame.
  std::unique_ptr<MapSystem> map_;
  KeyframePacket* map_pending_ = nullptr;
  // The held keyframe's motion when it was taken (time offset: its pose is
  // handed to the map at t + t_d, where its pixels and depths were taken).
  Eigen::Vector3d map_pending_v_W_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d map_pending_w_B_ = Eigen::Vector3d::Zero();
  Eigen::Isometry3d at_capture_time(const Eigen::Isometry3d& T_WC) const;
  // The odometry's chain for the map (KeyframePacket::chain): steps when the
  // output turns lost or the front end re-initialises.
  uint32_t map_chain_ = 0;
  bool map_chain_lost_ = false;
  uint64_t map_chain_epoch_ = 0;
  bool window_started_ = false;  // a frame went in since the last (re)start

  // Optimizer side.
  rt::LatencyHistogram opt_latency_;
  WindowEstimatorCounters wc_;
  std::atomic<uint64_t> solves_ok_{0};
};

}  // namespace kestrel::core

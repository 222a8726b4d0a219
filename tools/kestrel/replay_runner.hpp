// `kestrel replay` as a library call, so `kestrel bench` and the tests run the
// very same harness: log → ReplaySource → sensor rings → estimator thread →
// output ring → trajectory.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "kestrel/core/estimator.hpp"
#include "kestrel/core/estimator_config.hpp"
#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/core/global_bundle_adjustment.hpp"
#include "kestrel/core/pose_sample.hpp"
#include "kestrel/dense/dense_mapper.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/replay_source.hpp"
#include "kestrel/loop_truth.hpp"
#include "kestrel/map_topics.hpp"
#include "kestrel/mavlink/odometry_adapter.hpp"
#include "kestrel/mavlink/odometry_stream.hpp"
#include "kestrel/rt/latency_histogram.hpp"
#include "kestrel/rt/perf.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "kestrel/viewer/server.hpp"

namespace kestrel::cli {

// Threads with nothing to do sleep on a doorbell that their producer rings;
// this bound only lets them see a stop flag nobody rang for (a few wake-ups a
// second per thread, against thousands for the sleep loops it replaced).
constexpr int64_t kIdleWaitNs = 50'000'000;

// The flight-controller link from a config's `mavlink:` section and the
// command line, whose --mavlink-udp HOST:PORT or --mavlink-serial
// DEVICE[:BAUD] chooses the transport over the section's; sysid, compid,
// R_FB, rates and TIMESYNC come from the section. nullopt when no transport
// is named. Throws std::invalid_argument naming the bad value.
std::optional<mavlink::OdometryStreamOptions> mavlink_options(const drivers::MavlinkSettings& cfg,
                                                              const std::string& udp,
                                                              const std::string& serial);
// Why a backend whose world is not levelled (Estimator::world_levelled()
// false: rgbd) may not feed a flight controller: ODOMETRY's LOCAL_FRD frame
// has its z along gravity, and this backend's W is its first camera pose.
std::string mavlink_needs_levelled_world(const std::string& backend);

// The map's last word, for the ROS outputs' final markers.
struct MapFinal {
  struct Keyframe {
    int64_t t_ns = 0;
    Eigen::Isometry3d T_MB = Eigen::Isometry3d::Identity();
  };
  struct Loop {
    int64_t query_t_ns = 0, candidate_t_ns = 0;
    Eigen::Vector3d p_M_query = Eigen::Vector3d::Zero(), p_M_candidate = Eigen::Vector3d::Zero();
  };
  std::vector<Keyframe> keyframes;  // oldest first
  std::vector<Loop> loops;          // closed loops, in order
};

// The 1 Hz status the estimator thread publishes (one per second of log time,
// which in realtime pace is one per wall second), read lock-free by the
// output thread. Its levels and maxima; the counts are in the run's perf
// registry (pipeline_counters.hpp), which format_status reads.
struct PipelineStatus {
  int64_t t_ns = 0;
  double t_s = 0;  // since the first record
  core::TrackingQuality quality = core::TrackingQuality::kUninitialized;
  uint32_t reset_counter = 0;
  int features = -1;  // -1: the backend does not say
  int inliers = -1;
  uint64_t frames_in_window = 0;  // frames fed in the last second
  uint64_t frames_total = 0;
  int64_t tracking_max_ns = 0;  // over the last second
  int64_t imu_to_output_max_ns =
      0;                    // the estimator thread's view (in realtime pace the IMU-rate pose is faster)
  core::MapFrameState map;  // active: the backend has a map (then: localized, relocalisations, loop closures)
};

// counters: the run's registry (or a copy of it): drops, rejects and faults by path.
std::string format_status(const PipelineStatus& s, const rt::PerfValues& counters);

// One row of the thread table as it was applied: what was asked for, and
// whether the system granted it (a refused SCHED_FIFO or CPU pin leaves the
// thread running SCHED_OTHER / unpinned; `error` says why).
struct AppliedThread {
  std::string name;
  int cpu = -1;
  std::string policy;  // "fifo" | "other" (as requested)
  int priority = 0;
  bool applied = false;
  std::string error;
};
AppliedThread applied_thread(const rt::ThreadSpec& spec, const rt::ThreadSetupReport& r);
// "threads: kst-replay other/any ok; kst-propagate fifo 60/cpu 0 NOT applied (...)", one line per thread.
std::string threads_summary(const std::vector<AppliedThread>& t);
// Features and inliers of the newest frame where the backend exposes them
// (the front end and backends built on it), else -1: for status lines only.
void frame_stats(const core::Estimator& est, int& features, int& inliers);

// Live sensors in place of a log (`kestrel run`): the pipeline starts them
// with sinks into its rings and runs in realtime pace until should_stop() says
// so; everything after the rings is the same code a replay runs.
struct LiveInput {
  Rig rig;
  std::string description;          // what runs, for the report
  std::size_t max_image_bytes = 0;  // the largest image the drivers deliver (0: the rig's size)
  // Why the camera settings cannot deliver a stereo rig's right image ("" when they can;
  // drivers::stereo_capability): a stereo rig is refused before start with it.
  std::string stereo_problem;
  // Starts the sensor threads delivering into the sinks (which outlive stop());
  // appends the threads it started, as granted.
  std::function<void(drivers::ImuSink&, drivers::FrameSink&, std::vector<AppliedThread>&)> start;
  // Stops and joins them: no push after it returns.
  std::function<void()> stop;
  // Asked by the output thread between drains (Ctrl-C, --duration).
  std::function<bool()> should_stop;
};

struct ReplayOptions {
  std::string path;
  // Live sensors instead of `path` (pace must be realtime).
  std::shared_ptr<LiveInput> live;
  std::string map_out;  // the map file written at the end ("": none; tools/config/map_files.hpp)
  // Keep the loop closer's log of every query and candidate (ReplayReport::loop_log).
  bool loop_log = false;
  drivers::LogFormat format = drivers::LogFormat::kAuto;
  drivers::LogOpenOptions open;  // rig for datasets, bag topics (open.format is ignored: `format` rules)
  drivers::ReplayPace pace = drivers::ReplayPace::kLockstep;
  std::string estimator = "auto";  // core::make_estimator name, when `config` is empty
  // Every option of the backend (config.backend names it); empty: the
  // defaults of `estimator`.
  std::optional<core::EstimatorConfig> config;
  // Scheduling and CPUs of the harness threads in realtime pace (a config's
  // `threads:` section); fast pace runs the default table, lockstep one thread.
  drivers::ThreadTable threads = drivers::default_thread_table();
  // Allocation counting and latency statistics start after this much log time,
  // so start-up (buffers reserved, first frames) is not counted as steady state.
  int64_t warmup_ns = 2'000'000'000;
  // Logs without camera records still get a trajectory, at this period.
  int64_t imu_only_output_period_ns = 50'000'000;
  // ... once the camera has been silent this long: 1 s in replay (a log without
  // a camera); `kestrel run` sets 150 ms, so a flight controller keeps getting
  // ODOMETRY through a short camera dropout.
  int64_t camera_silent_after_ns = 1'000'000'000;
  // Live input only: a frame waits at most this long (wall clock) for the IMU
  // up to its time, so an IMU that stopped cannot hold the camera back.
  int64_t max_frame_wait_for_imu_ns = 50'000'000;
  // Called on the output thread for every pose (not the estimator thread: it
  // may block or allocate).
  std::function<void(const core::PoseSample&)> on_pose;
  // Realtime pace: the IMU-rate pose kst-propagate publishes (latest-value
  // mailbox), handed over on the output thread as it drains (every ~1 ms; a
  // pose newer than the last one seen, skipped ones are not replayed).
  std::function<void(const core::PoseSample&)> on_imu_pose;
  // The flight-controller link: ODOMETRY per pose, HEARTBEAT, TIMESYNC
  // (mavlink_options() below; nullopt = off).
  std::optional<mavlink::OdometryStreamOptions> mavlink;
  // Called on the output thread when T_map_odom changes (a loop closure, a
  // relocalisation, a loaded map found): the correction, published apart
  // from the continuous odometry (docs/map.md).
  std::function<void(const core::PoseSample&)> on_map_correction;
  // The map for the ROS outputs (docs/ros2.md), on the output thread: the
  // local map's points at most map_points_rate_hz of log time (0: none) and
  // every new keyframe's camera pose, in W; handed over by MapTopicsFeed
  // when either callback is set and the backend has a tracker.
  double map_points_rate_hz = 0;
  std::function<void(const MapCloud&)> on_map_cloud;
  std::function<void(const KeyframePose&)> on_keyframe;
  // After the map threads stopped (backends with a map): the keyframes as the
  // map holds them at the end and the loops closed between them.
  std::function<void(const MapFinal&)> on_map_final;
  // Called with the backend once it is built, before any record is read or
  // thread started: the command checks the options that depend on it (a map
  // output for a backend without a map) and throws, so nothing runs in vain.
  std::function<void(const core::Estimator&)> check_before_start;
  // Instead of opening `path`: a source made by the caller (a generator that
  // streams a simulation, tests that build logs in memory).
  std::function<std::unique_ptr<drivers::LogSource>()> open_source;
  // The 1 Hz status line: to on_status, else to stdout.
  bool status_line = false;
  std::function<void(const PipelineStatus&, const std::string&)> on_status;
  // The live viewer (tools/viewer, docs/viewer.md), served while the replay
  // runs; its thread is the table's kst-viewer. Lockstep pace gets pause and
  // step from the page.
  bool view = false;
  viewer::ServerOptions view_options;
  // Wait up to this long for a browser before the first record (0: start at once).
  double view_wait_s = 0;
  // Called once the viewer listens (the CLI prints where to point a browser).
  std::function<void(const viewer::Server&)> on_view_ready;
  // The dense map (tools/dense, docs/dense.md): its thread runs when
  // dense.enabled, or when one of its outputs below is asked for.
  dense::DenseOptions dense;
  std::string dense_out;          // the surface as PLY, in W (the frame of the trajectory)
  std::string dense_octomap_out;  // occupancy as an OctoMap .bt
  // The surface again, re-integrated from the keyframe archive along the map's
  // final trajectory (the frame M of --map-final-traj-out, after loops and
  // bundle adjustments); without a map, along the trajectory itself (M = W).
  std::string dense_map_out;
  // The dense map's stream to the live viewer (--view with the map on): the
  // config's viewer: section (docs/dense.md).
  dense::DenseViewOptions dense_view;
  // Called with the re-integrated map (tests, measurements); enables the map and the re-integration.
  std::function<void(const core::TsdfMap&)> on_dense_map_rebuilt;
  // Called at the end with the finished map (tests, measurements); enables the map.
  std::function<void(const core::TsdfMap&)> on_dense_map;
  // The map as it was at the end of the flight, before any re-integration:
  // in W, or in the map frame with dense.live_reanchor (benches score it).
  std::function<void(const core::TsdfMap&)> on_dense_map_live;
  // A planner in flight (docs/dense.md "Live queries"): called with the running
  // mapper before the first record, and with nullptr once its thread has
  // stopped (also when the replay throws); in between any non-real-time thread
  // may call its occupancy / segment / distance / read. The mapper is destroyed
  // soon after the nullptr call returns, so that call must not return while
  // another thread is still inside a query (e.g. take the mutex the planner
  // holds around its queries). Does not enable the map.
  std::function<void(const dense::DenseMapper*)> on_dense_live;
  // Called at the end with the finished map in W when the map ran for another
  // reason (the ROS outputs' dense cloud); unlike on_dense_map it does not enable it.
  std::function<void(const core::TsdfMap&)> on_dense_finished;
};

struct ReplayReport {
  std::string estimator;
  bool world_levelled = true;  // Estimator::world_levelled(): posyaw alignment is meaningful
  bool stereo = false;         // a stereo rig, rectified at start-up (docs/stereo.md)
  double stereo_baseline_m = 0;
  // The effective settings ("section.key", YAML value), for the metrics JSON.
  std::vector<std::pair<std::string, std::string>> config;
  std::string log_path;
  std::string log_format;
  drivers::ReplayPace pace = drivers::ReplayPace::kLockstep;
  tools::Trajectory trajectory;  // body pose in W at each camera frame the backend did not call lost
  // Every counter of the run's perf registry at the end, by path
  // (pipeline_counters.hpp: input.*, rings.*, output.*, mavlink.*, viewer.*,
  // ros2.*, estimator.*, window.*); the metrics JSON's `counters`.
  rt::PerfValues counters;
  tools::Trajectory map_trajectory;  // the same poses in the map frame, T_map_odom(t) * T_WB(t)
  // The same poses through the map's keyframes as they ended the flight
  // (tools::anchor_to_keyframes): the map's final word, not available in flight.
  tools::Trajectory map_final_trajectory;
  std::vector<tools::KeyframeAnchor> map_final_keyframes;  // what it was anchored to
  // The map (backends with one): its frame at the end, per keyframe cost of
  // the mapping and loop threads, and their CPU time.
  bool has_map = false;
  core::LoopLog loop_log;  // ReplayOptions::loop_log
  // The loop log against the log's ground truth (loop_truth.hpp), when the
  // caller computed it: the metrics JSON's `loop_truth`, a summary line.
  std::optional<LoopTruth> loop_truth;
  core::MapFrameState map;
  rt::LatencyHistogram mapping;
  rt::LatencyHistogram loop;
  // The global bundle adjustment after loops (map.global_ba; none when off):
  // its counters and the time of each solve on the loop thread.
  std::optional<core::GlobalBaStats> global_ba;
  rt::LatencyHistogram global_ba_solve;
  double mapping_cpu_s = 0, loop_cpu_s = 0;
  double log_duration_s = 0;
  double wall_s = 0;
  double realtime_factor = 0;  // log seconds per wall second
  double cpu_s = 0;            // whole process
  // The backend's own work: its add_imu / add_frame calls, and the optimizer's
  // thread when the solve runs apart (realtime pace). The harness's waiting is
  // not in it; it is in estimator_thread_cpu_s, the estimator thread's total.
  double estimator_cpu_s = 0;
  double estimator_thread_cpu_s = 0;
  // The estimator thread's CPU outside the backend's calls: draining the
  // rings, waking, waiting (a busy-yield showed here as most of the wall time).
  double estimator_thread_overhead_cpu_s = 0;
  double peak_rss_mb = 0;
  // Realtime pace: ring push of a sample -> its IMU-rate pose available on the
  // propagation thread (end to end, what a flight controller would wait).
  // Fast/lockstep pace: estimator takes the sample -> its pose available.
  rt::LatencyHistogram imu_to_output;
  // In realtime pace the IMU-rate pose comes from the propagation thread
  // (docs/threads.md); this is the estimator thread's own view of the same
  // samples (push -> its add_imu returned), which waits behind tracking.
  rt::LatencyHistogram estimator_imu_latency;
  std::string propagator_thread;       // scheduling the propagation thread got (realtime pace)
  std::vector<AppliedThread> threads;  // every thread the harness started, as applied
  rt::LatencyHistogram tracking;       // per frame, inside the estimator
  drivers::ReplayStats replay;
  core::EstimatorCounters estimator_counters;
  std::string backend_summary;  // Estimator::backend_summary()
  // Camera-IMU time offset: the rig's time_offset_cam_imu_ns (applied to the
  // stamps by the reader) plus what the backend estimated online on top.
  double time_offset_ms = 0.0;
  bool time_offset_estimated = false;
  rt::LatencyHistogram optimizer;   // per solve (backends with an optimizer)
  bool optimizer_threaded = false;  // on its own thread (realtime pace) or inline
  bool mavlink_timesync_converged = false;
  double mavlink_timesync_offset_ms = 0.0;
  bool mavlink_signing = false;
  // Heap allocations made by the estimator thread after warm-up, and how many
  // frames it processed in that span.
  int64_t steady_allocs = 0;
  uint64_t steady_frames = 0;
  bool alloc_counting = false;
  std::vector<drivers::LogProblem> problems;
  bool view = false;  // the viewer ran: its cost figures follow
  viewer::ServerStats viewer;
  // The dense map (docs/dense.md); dense false: it did not run.
  bool dense = false;
  dense::DenseStats dense_stats;
  core::TsdfCounters dense_counters;
  int dense_blocks = 0, dense_block_capacity = 0;
  double dense_memory_mb = 0;
  uint64_t dense_points = 0;  // written to dense_out
  uint64_t dense_octomap_leaves = 0;
  uint64_t dense_map_points = 0;           // written to dense_map_out
  uint64_t dense_archive_overwritten = 0;  // keyframes the archive no longer had for the re-integration
  int dense_archive_capacity = 0;
  bool dense_live_reanchor = false;           // in flight the map was in the map frame (dense.live_reanchor)
  int dense_live_blocks = 0;                  // blocks at the end of the flight, before any re-integration
  core::ReintegrationReport dense_w_rebuild;  // live_reanchor: --dense-out fused again along W
};

ReplayReport run_replay(const ReplayOptions& opt);

std::string replay_metrics_json(const ReplayReport& r);
// A few human-readable lines for the terminal.
std::string replay_summary(const ReplayReport& r);

}  // namespace kestrel::cli

// The pipeline's counters, registered once by path in the run's perf
// registry (rt/perf.hpp). The stages update them through these pointers; the
// metrics JSON, the status line and the live viewer read the registry, so a
// new counter is one line here and shows up everywhere (docs/threads.md,
// "Counters").
//
// Each counter has one updating thread:
//  - input.*, rings.output_drops, estimator.*, window.*: the estimator thread;
//  - output.*, mavlink.*: the output thread;
//  - map.*: the output thread, from the poses;
//  - the other rings.*, viewer.*, ros2.* and dense.*: the calling thread,
//    after every other thread stopped.
// Counts kept elsewhere (a ring's, a backend's, the MAVLink stream's) are
// mirrored with set(); the harness's own are counted here with inc().
#pragma once

#include "kestrel/core/estimator.hpp"
#include "kestrel/dense/dense_mapper.hpp"
#include "kestrel/rt/perf.hpp"

namespace kestrel::cli {

struct PipelineCounters {
  // has_optimizer: register the window.* counters (EstimatorView::has_optimizer).
  PipelineCounters(rt::PerfRegistry& registry, bool has_optimizer);

  rt::PerfRegistry& registry;

  // Input faults the harness sees before the estimator does (the estimator
  // counts its own: estimator.imu_rejects.*). Out-of-order and repeated
  // (frozen) frames are withheld: the estimator's contract is time-ordered,
  // fresh input.
  rt::PerfCounter* frames_missing;       // input.frames_missing: time gaps of more than 1.5 periods
  rt::PerfCounter* frames_out_of_order;  // input.frames_out_of_order: time not after the previous frame
  rt::PerfCounter* frames_repeated;      // input.frames_repeated: pixels identical to the previous frame
  rt::PerfCounter* frames_no_depth;      // input.frames_no_depth: depth absent or almost all invalid;
                                         // stereo: the right image absent
  rt::PerfCounter* imu_gaps;             // input.imu_gaps: steps longer than five sample periods

  // What the rings lost: in fast pace the feeder's lost records, not the
  // refused pushes it retried; live, every refused push.
  rt::PerfCounter* imu_ring_drops;            // rings.imu_drops
  rt::PerfCounter* frame_ring_drops;          // rings.frame_drops
  rt::PerfCounter* output_ring_drops;         // rings.output_drops
  rt::PerfCounter* image_pool_exhausted;      // rings.image_pool_exhausted
  rt::PerfCounter* propagator_forward_drops;  // rings.propagator_forward_drops

  rt::PerfCounter* lost_poses_withheld;  // output.lost_poses_withheld: kLost, not in the trajectory
  rt::PerfCounter* map_corrections;      // output.map_corrections: changes of T_map_odom
  rt::PerfCounter* status_lines;         // output.status_lines
  rt::PerfCounter* imu_rate_poses;       // output.imu_rate_poses: taken from kst-propagate

  rt::PerfCounter* mavlink_odometry;         // mavlink.odometry_sent
  rt::PerfCounter* mavlink_heartbeats;       // mavlink.heartbeats_sent
  rt::PerfCounter* mavlink_frames;           // mavlink.frames_sent: every frame
  rt::PerfCounter* mavlink_failed;           // mavlink.send_failed: counted, never retried
  rt::PerfCounter* mavlink_unauthenticated;  // mavlink.unauthenticated: refused by signing
  rt::PerfCounter* mavlink_timesync;         // mavlink.timesync_answered

  rt::PerfCounter* viewer_snapshots;          // viewer.snapshots_published
  rt::PerfCounter* viewer_snapshots_skipped;  // viewer.snapshots_skipped: no free slot

  rt::PerfCounter* map_clouds;             // ros2.map_clouds
  rt::PerfCounter* map_clouds_dropped;     // ros2.map_clouds_dropped
  rt::PerfCounter* map_keyframes_dropped;  // ros2.map_keyframes_dropped

  rt::PerfCounter* add_frame;  // estimator.add_frame: elapsed, every frame the backend took

  // The backend's own counts (Estimator::counters(), its optimizer's status),
  // mirrored by the estimator thread.
  void mirror_estimator(const core::EstimatorCounters& c, const core::EstimatorView& v) noexcept;

  // Before any thread starts: the map's counters (backends with a map) and
  // the dense map's (when its thread runs). Without them the mirrors below
  // do nothing.
  void register_map();
  void register_dense();
  // map.loop_closures, map.relocalisations, from a pose's map state.
  void mirror_map(const core::MapFrameState& m) noexcept;
  // dense.offered, .keyframes, .integrated, .dropped, .wrong_size, .corrections_dropped.
  void mirror_dense(const dense::DenseStats& d) noexcept;

 private:
  rt::PerfCounter* imu_in_;
  rt::PerfCounter* imu_used_;
  rt::PerfCounter* frames_in_;
  rt::PerfCounter* frames_used_;
  rt::PerfCounter* resets_;
  rt::PerfCounter* imu_non_finite_;
  rt::PerfCounter* imu_saturated_;
  rt::PerfCounter* imu_out_of_order_;
  rt::PerfCounter* imu_rejected_gaps_;
  rt::PerfCounter* divergences_;
  rt::PerfCounter* restarts_while_lost_;
  rt::PerfCounter* coast_timeouts_;
  // Registered only for the parts that run (nullptr otherwise).
  struct Window {
    rt::PerfCounter *jobs = nullptr, *solves_ok = nullptr, *failures = nullptr, *skipped_busy = nullptr,
                    *resets = nullptr;
  } window_;
  struct Map {
    rt::PerfCounter *loop_closures = nullptr, *relocalisations = nullptr;
  } map_;
  struct Dense {
    rt::PerfCounter *offered = nullptr, *keyframes = nullptr, *integrated = nullptr, *dropped = nullptr,
                    *wrong_size = nullptr, *corrections_dropped = nullptr;
  } dense_;
};

}  // namespace kestrel::cli

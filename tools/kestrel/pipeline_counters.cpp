#include "kestrel/pipeline_counters.hpp"

namespace kestrel::cli {

namespace {
rt::PerfCounter* count(rt::PerfRegistry& r, const char* path) {
  return r.register_counter(path, rt::PerfKind::kCount);
}
}  // namespace

PipelineCounters::PipelineCounters(rt::PerfRegistry& r, bool has_optimizer)
    : registry(r),
      frames_missing(count(r, "input.frames_missing")),
      frames_out_of_order(count(r, "input.frames_out_of_order")),
      frames_repeated(count(r, "input.frames_repeated")),
      frames_no_depth(count(r, "input.frames_no_depth")),
      imu_gaps(count(r, "input.imu_gaps")),
      imu_ring_drops(count(r, "rings.imu_drops")),
      frame_ring_drops(count(r, "rings.frame_drops")),
      output_ring_drops(count(r, "rings.output_drops")),
      image_pool_exhausted(count(r, "rings.image_pool_exhausted")),
      propagator_forward_drops(count(r, "rings.propagator_forward_drops")),
      lost_poses_withheld(count(r, "output.lost_poses_withheld")),
      map_corrections(count(r, "output.map_corrections")),
      status_lines(count(r, "output.status_lines")),
      imu_rate_poses(count(r, "output.imu_rate_poses")),
      mavlink_odometry(count(r, "mavlink.odometry_sent")),
      mavlink_heartbeats(count(r, "mavlink.heartbeats_sent")),
      mavlink_frames(count(r, "mavlink.frames_sent")),
      mavlink_failed(count(r, "mavlink.send_failed")),
      mavlink_unauthenticated(count(r, "mavlink.unauthenticated")),
      mavlink_timesync(count(r, "mavlink.timesync_answered")),
      viewer_snapshots(count(r, "viewer.snapshots_published")),
      viewer_snapshots_skipped(count(r, "viewer.snapshots_skipped")),
      map_clouds(count(r, "ros2.map_clouds")),
      map_clouds_dropped(count(r, "ros2.map_clouds_dropped")),
      map_keyframes_dropped(count(r, "ros2.map_keyframes_dropped")),
      add_frame(r.register_counter("estimator.add_frame", rt::PerfKind::kElapsed)),
      imu_in_(count(r, "estimator.imu_in")),
      imu_used_(count(r, "estimator.imu_used")),
      frames_in_(count(r, "estimator.frames_in")),
      frames_used_(count(r, "estimator.frames_used")),
      resets_(count(r, "estimator.resets")),
      imu_non_finite_(count(r, "estimator.imu_rejects.non_finite")),
      imu_saturated_(count(r, "estimator.imu_rejects.saturated")),
      imu_out_of_order_(count(r, "estimator.imu_rejects.out_of_order")),
      imu_rejected_gaps_(count(r, "estimator.imu_rejects.gaps")),
      divergences_(count(r, "estimator.divergences")),
      restarts_while_lost_(count(r, "estimator.restarts_while_lost")),
      coast_timeouts_(count(r, "estimator.coast_timeouts")) {
  if (!has_optimizer) return;
  window_jobs_ = count(r, "window.jobs");
  window_solves_ok_ = count(r, "window.solves_ok");
  window_failures_ = count(r, "window.failures");
  window_skipped_busy_ = count(r, "window.skipped_busy");
  window_resets_ = count(r, "window.resets");
}

void PipelineCounters::mirror_estimator(const core::EstimatorCounters& c,
                                        const core::EstimatorView& v) noexcept {
  imu_in_->set(c.imu_in);
  imu_used_->set(c.imu_used);
  frames_in_->set(c.frames_in);
  frames_used_->set(c.frames_used);
  resets_->set(c.resets);
  imu_non_finite_->set(c.imu_rejects.non_finite);
  imu_saturated_->set(c.imu_rejects.saturated);
  imu_out_of_order_->set(c.imu_rejects.out_of_order);
  imu_rejected_gaps_->set(c.imu_rejects.gaps);
  divergences_->set(c.divergence.divergences);
  restarts_while_lost_->set(c.divergence.restarts_while_lost);
  coast_timeouts_->set(c.divergence.coast_timeouts);
  if (window_jobs_ == nullptr || !v.has_optimizer) return;
  window_jobs_->set(v.optimizer.jobs);
  window_solves_ok_->set(v.optimizer.applied);
  window_failures_->set(v.optimizer.failures);
  window_skipped_busy_->set(v.optimizer.skipped_busy);
  window_resets_->set(v.optimizer.resets);
}

void PipelineCounters::register_map() {
  map_loop_closures_ = count(registry, "map.loop_closures");
  map_relocalisations_ = count(registry, "map.relocalisations");
}

void PipelineCounters::register_dense() {
  dense_offered_ = count(registry, "dense.offered");
  dense_keyframes_ = count(registry, "dense.keyframes");
  dense_integrated_ = count(registry, "dense.integrated");
  dense_dropped_ = count(registry, "dense.dropped");
  dense_wrong_size_ = count(registry, "dense.wrong_size");
  dense_corrections_dropped_ = count(registry, "dense.corrections_dropped");
}

void PipelineCounters::mirror_map(const core::MapFrameState& m) noexcept {
  if (map_loop_closures_ == nullptr) return;
  map_loop_closures_->set(m.loop_closures);
  map_relocalisations_->set(m.relocalisations);
}

void PipelineCounters::mirror_dense(const dense::DenseStats& d) noexcept {
  if (dense_offered_ == nullptr) return;
  dense_offered_->set(d.offered);
  dense_keyframes_->set(d.keyframes);
  dense_integrated_->set(d.integrated);
  dense_dropped_->set(d.dropped);
  dense_wrong_size_->set(d.wrong_size);
  dense_corrections_dropped_->set(d.corrections_dropped);
}

}  // namespace kestrel::cli

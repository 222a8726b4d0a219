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
  window_.jobs = count(r, "window.jobs");
  window_.solves_ok = count(r, "window.solves_ok");
  window_.failures = count(r, "window.failures");
  window_.skipped_busy = count(r, "window.skipped_busy");
  window_.resets = count(r, "window.resets");
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
  if (window_.jobs == nullptr || !v.has_optimizer) return;
  window_.jobs->set(v.optimizer.jobs);
  window_.solves_ok->set(v.optimizer.applied);
  window_.failures->set(v.optimizer.failures);
  window_.skipped_busy->set(v.optimizer.skipped_busy);
  window_.resets->set(v.optimizer.resets);
}

void PipelineCounters::register_map() {
  map_.loop_closures = count(registry, "map.loop_closures");
  map_.relocalisations = count(registry, "map.relocalisations");
}

void PipelineCounters::register_dense() {
  dense_.offered = count(registry, "dense.offered");
  dense_.keyframes = count(registry, "dense.keyframes");
  dense_.integrated = count(registry, "dense.integrated");
  dense_.dropped = count(registry, "dense.dropped");
  dense_.wrong_size = count(registry, "dense.wrong_size");
  dense_.corrections_dropped = count(registry, "dense.corrections_dropped");
}

void PipelineCounters::mirror_map(const core::MapFrameState& m) noexcept {
  if (map_.loop_closures == nullptr) return;
  map_.loop_closures->set(m.loop_closures);
  map_.relocalisations->set(m.relocalisations);
}

void PipelineCounters::mirror_dense(const dense::DenseStats& d) noexcept {
  if (dense_.offered == nullptr) return;
  dense_.offered->set(d.offered);
  dense_.keyframes->set(d.keyframes);
  dense_.integrated->set(d.integrated);
  dense_.dropped->set(d.dropped);
  dense_.wrong_size->set(d.wrong_size);
  dense_.corrections_dropped->set(d.corrections_dropped);
}

}  // namespace kestrel::cli

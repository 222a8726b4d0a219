#include "kestrel/core/kestrel.hpp"

#include <utility>

#include "kestrel/core/estimator_config.hpp"
#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/core/map_system.hpp"

namespace kestrel {

Estimator::Estimator(const Rig& rig, const std::string& backend, MapWork map_work)
    : Estimator(rig, core::EstimatorConfig::defaults(backend), map_work) {}

Estimator::Estimator(const Rig& rig, const core::EstimatorConfig& config, MapWork map_work)
    : impl_(core::make_estimator(config, rig)), map_work_(map_work) {}

Estimator::~Estimator() = default;

void Estimator::on_state(StateCallback cb, bool imu_rate) {
  cb_ = std::move(cb);
  imu_rate_ = imu_rate;
}

bool Estimator::feed_imu(const ImuSample& s) {
  if (!impl_->add_imu(s)) return false;
  publish(false);
  return true;
}

bool Estimator::feed_rgbd(int64_t t_ns, const ImageView& rgb, const ImageView& depth) {
  // The backends assume fresh frames in time order; a repeated or older
  // stamp (a driver hiccup, a replayed buffer) is refused and counted.
  if (rgb.data == nullptr || (last_frame_t_ns_ >= 0 && t_ns <= last_frame_t_ns_)) {
    ++counters_.frames_rejected;
    return false;
  }
  last_frame_t_ns_ = t_ns;
  core::RgbdFrame f;
  f.t_ns = t_ns;
  f.seq = frame_seq_++;
  f.rgb = rgb;
  f.depth = depth;
  const bool used = impl_->add_frame(f);
  // Inline map work: until the map has taken what this frame handed over, as
  // the deterministic replay paces wait for the map threads after each frame.
  if (map_work_ == MapWork::kInline && impl_->has_map()) run_map();
  if (!used) return false;
  publish(true);
  return true;
}

// One round of the map's workers on the caller's thread (one thread: the
// workers' group needs no lock): true when any of them did something.
bool Estimator::step_map_workers(bool* busy) {
  bool worked = false;
  *busy = false;
  for (core::EstimatorWorker* w : impl_->workers()) {
    if (w->kind() == core::EstimatorWorker::Kind::kOptimizer) continue;
    if (w->step()) worked = true;
    if (w->step_ungrouped()) worked = true;
    if (w->busy()) *busy = true;
  }
  return worked;
}

void Estimator::run_map() {
  for (int guard = 0; guard < 1000; ++guard) {
    bool busy = false;
    if (!step_map_workers(&busy) && !busy) return;
  }
}

bool Estimator::map_step() {
  if (map_work_ != MapWork::kCaller || !impl_->has_map()) return false;
  bool busy = false;
  return step_map_workers(&busy);
}

bool Estimator::has_map() const { return impl_->has_map(); }

void Estimator::publish(bool from_frame) {
  const core::EstimatorOutput& o = impl_->output();
  state_.t_ns = o.state.t_ns;
  state_.p_WB = o.state.p_WB;
  state_.q_WB = o.state.q_WB;
  state_.v_WB = o.state.v_WB;
  state_.gyro_bias_rps = o.state.bg_rps;
  state_.acc_bias_mps2 = o.state.ba_mps2;
  state_.quality = o.quality;
  state_.reset_counter = o.reset_counter;
  state_.from_frame = from_frame;
  state_.map_active = o.map.active;
  state_.T_map_odom = o.map.T_map_odom();
  state_.loop_closures = o.map.loop_closures;
  if (cb_ && (from_frame || imu_rate_)) {
    ++counters_.callbacks;
    cb_(state_);
  }
}

const EmbeddedCounters& Estimator::counters() const {
  counters_.estimator = impl_->counters();
  return counters_;
}

const char* Estimator::backend_name() const { return impl_->name(); }

}  // namespace kestrel

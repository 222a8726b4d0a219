#include "kestrel/imu_rate_stage.hpp"

#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/rt/clock.hpp"

namespace kestrel::cli {

Anchor to_anchor(const core::EstimatorOutput& o) {
  return Anchor{core::pack(o.state), o.quality, o.reset_counter};
}

ImuRateStage::ImuRateStage(ImuRing& in, ImuRing& to_estimator, const rt::Mailbox<Anchor>& anchor,
                           const Rig& rig, int64_t warmup_ns, rt::Mailbox<core::PoseSample>& imu_pose)
    : in_(in),
      to_est_(to_estimator),
      anchor_(anchor),
      prop_(core::imu_propagator_options(rig)),
      warmup_ns_(warmup_ns),
      imu_pose_(imu_pose) {}

bool ImuRateStage::step() {
  bool any = false;
  while (ImuSample* p = in_.front()) {
    const ImuSample s = *p;
    in_.pop();
    any = true;
    if (!to_est_.try_push(s)) ++stats_.forward_drops;
    if (first_t_ns_ < 0) first_t_ns_ = s.t_ns;
    if (!counting_ && s.t_ns - first_t_ns_ >= warmup_ns_) {
      counting_ = true;
      allocs_at_warmup_ = rt::alloc_count_this_thread();
    }
    refresh_anchor();
    history_.push(s);
    if (have_anchor_ && prop_.propagate(s)) {
      core::PoseSample o = core::pose_sample_of(prop_.state(), s.gyro_rps);
      o.quality = anchor_quality_;
      o.reset_counter = anchor_reset_counter_;
      imu_pose_.publish(o);
      ++stats_.poses;
      const int64_t latency = rt::now_ns() - s.t_recv_ns;
      if (counting_) stats_.imu_to_output.record(latency);
      // A reader may reset it between the load and the store: it then sees
      // this one sample's max late, which a display can afford.
      if (latency > recent_max_ns_.load(std::memory_order_relaxed))
        recent_max_ns_.store(latency, std::memory_order_relaxed);
    }
  }
  return any;
}

void ImuRateStage::finish() {
  if (counting_)
    stats_.steady_allocs = static_cast<int64_t>(rt::alloc_count_this_thread() - allocs_at_warmup_);
}

void ImuRateStage::refresh_anchor() {
  Anchor a{};
  uint64_t version = 0;
  if (!anchor_.read(a, &version) || version == anchor_version_) return;
  anchor_version_ = version;
  anchor_quality_ = a.quality;
  anchor_reset_counter_ = a.reset_counter;
  prop_.reset(core::unpack(a.x));
  have_anchor_ = true;
  // The sample at the anchor's time re-anchors the integration, later ones
  // carry the state to the newest sample.
  size_t k = 0;
  while (k < history_.size() && history_[k].t_ns < a.x.t_ns) ++k;
  history_.pop_front(k);
  for (size_t i = 0; i < history_.size(); ++i) prop_.propagate(history_[i]);
}

}  // namespace kestrel::cli

#include "kestrel/map_topics.hpp"

#include <Eigen/Geometry>

#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/core/tracker.hpp"

namespace kestrel::cli {

MapTopicsFeed::MapTopicsFeed(const core::Estimator& est, double map_points_rate_hz)
    : tracker_(core::tracker_of(est)),
      period_ns_(map_points_rate_hz > 0 ? static_cast<int64_t>(1e9 / map_points_rate_hz) : -1) {}

void MapTopicsFeed::on_frame(int64_t t_ns) noexcept {
  if (tracker_ == nullptr) return;
  if (tracker_->last().keyframe && tracker_->keyframe_t_ns() != last_keyframe_t_ns_) {
    last_keyframe_t_ns_ = tracker_->keyframe_t_ns();
    keyframe_since_cloud_ = true;
    const Eigen::Isometry3d& T = tracker_->last().T_WC;
    const Eigen::Quaterniond q(T.linear());
    KeyframePose k;
    k.t_ns = t_ns;
    for (int i = 0; i < 3; ++i) k.p_WC[i] = T.translation()[i];
    k.q_WC[0] = q.w(), k.q_WC[1] = q.x(), k.q_WC[2] = q.y(), k.q_WC[3] = q.z();
    (void)keyframes_.try_push(k);  // full: the output thread is behind; counted in drops()
  }
  // The local map changes only with a keyframe: between keyframes a copy
  // would repeat the last one.
  if (period_ns_ < 0 || !keyframe_since_cloud_ ||
      (last_cloud_t_ns_ != INT64_MIN && t_ns - last_cloud_t_ns_ < period_ns_))
    return;
  const rt::PoolHandle h = pool_.acquire();
  MapCloud* c = pool_.get(h);
  if (c == nullptr) {
    clouds_dropped_.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  c->t_ns = t_ns;
  c->n = tracker_->copy_map_points(c->xyz_W, kMapCloudMaxPoints);
  if (!ring_.try_push(h)) {
    pool_.release(h);
    clouds_dropped_.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  last_cloud_t_ns_ = t_ns;
  keyframe_since_cloud_ = false;
  clouds_.fetch_add(1, std::memory_order_relaxed);
}

const MapCloud* MapTopicsFeed::take_cloud(rt::PoolHandle* handle) noexcept {
  rt::PoolHandle h = rt::kInvalidHandle;
  if (!ring_.try_pop(h)) return nullptr;
  *handle = h;
  return pool_.get(h);
}

}  // namespace kestrel::cli

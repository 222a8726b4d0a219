#include "kestrel/viewer/feed.hpp"

#include <algorithm>
#include <cstring>

#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/core/tracker.hpp"
#include "kestrel/rt/clock.hpp"

namespace kestrel::viewer {
namespace {

// Smallest integer step that fits w x h into max_w x max_h.
int step_for(int w, int h, int max_w, int max_h) {
  const int sx = (w + max_w - 1) / max_w, sy = (h + max_h - 1) / max_h;
  return std::max({1, sx, sy});
}

// Nearest-pixel subsampling: on the estimator thread every microsecond
// counts, and a preview does not need a filtered image. VGA -> 320 x 240 is
// 77 k pixel copies.
void preview_rgb(const ImageView& v, ViewSnapshot& s) {
  s.rgb_width = s.rgb_height = 0;
  if (v.data == nullptr || v.width <= 0 || v.height <= 0) return;
  const int step = step_for(v.width, v.height, kPreviewMaxWidth, kPreviewMaxHeight);
  const int w = v.width / step, h = v.height / step;
  for (int y = 0; y < h; ++y) {
    const uint8_t* row = v.data + static_cast<int64_t>(y) * step * v.stride_bytes;
    uint8_t* out = s.rgb + static_cast<int64_t>(y) * w * 3;
    switch (v.format) {
      case PixelFormat::kRgb8:
        for (int x = 0; x < w; ++x) std::memcpy(out + 3 * x, row + 3 * x * step, 3);
        break;
      case PixelFormat::kBgr8:
        for (int x = 0; x < w; ++x) {
          const uint8_t* p = row + 3 * x * step;
          out[3 * x] = p[2];
          out[3 * x + 1] = p[1];
          out[3 * x + 2] = p[0];
        }
        break;
      case PixelFormat::kGray8:
        for (int x = 0; x < w; ++x) std::memset(out + 3 * x, row[x * step], 3);
        break;
      case PixelFormat::kYuyv:  // luma only: Y sits in every even byte
        for (int x = 0; x < w; ++x) std::memset(out + 3 * x, row[2 * x * step], 3);
        break;
      case PixelFormat::kDepthU16:
        return;  // not a colour image
    }
  }
  s.rgb_width = w;
  s.rgb_height = h;
  s.rgb_step = step;
}

void preview_depth(const ImageView& v, ViewSnapshot& s) {
  s.depth_width = s.depth_height = 0;
  if (v.data == nullptr || v.format != PixelFormat::kDepthU16 || v.width <= 0 || v.height <= 0) return;
  const int step = step_for(v.width, v.height, kDepthMaxWidth, kDepthMaxHeight);
  const int w = v.width / step, h = v.height / step;
  for (int y = 0; y < h; ++y) {
    const auto* row =
        reinterpret_cast<const uint16_t*>(v.data + static_cast<int64_t>(y) * step * v.stride_bytes);
    uint16_t* out = s.depth + static_cast<int64_t>(y) * w;
    for (int x = 0; x < w; ++x) out[x] = row[x * step];
  }
  s.depth_width = w;
  s.depth_height = h;
  s.depth_step = step;
}

}  // namespace

ViewerFeed::ViewerFeed(const core::Estimator& est, const Rig& rig, const FeedOptions& opt)
    : est_(est),
      tracker_(core::tracker_of(est)),
      rig_(rig),
      min_period_ns_(opt.max_rate_hz > 0 ? static_cast<int64_t>(1e9 / opt.max_rate_hz) : 0),
      map_period_ns_(static_cast<int64_t>(opt.map_period_s * 1e9)) {}

void ViewerFeed::on_frame(const core::RgbdFrame& f, const FrameInfo& info) noexcept {
  tracking_max_ns_ = std::max(tracking_max_ns_, info.tracking_ns);
  imu_max_ns_ = std::max(imu_max_ns_, info.imu_to_pose_max_ns);
  // Keyframes go whether or not a browser is connected: the viewer thread
  // keeps them all, so one that connects later still sees every keyframe.
  if (tracker_ != nullptr && tracker_->last().keyframe && tracker_->keyframe_t_ns() != last_keyframe_t_ns_) {
    last_keyframe_t_ns_ = tracker_->keyframe_t_ns();
    keyframe_since_map_ = true;
    const Eigen::Isometry3d& T = tracker_->last().T_WC;
    const Eigen::Quaterniond q(T.linear());
    KeyframeMark k;
    k.t_ns = f.t_ns;
    for (int i = 0; i < 3; ++i) k.p_WC[i] = static_cast<float>(T.translation()[i]);
    k.q_WC[0] = static_cast<float>(q.w());
    k.q_WC[1] = static_cast<float>(q.x());
    k.q_WC[2] = static_cast<float>(q.y());
    k.q_WC[3] = static_cast<float>(q.z());
    (void)keyframes_.try_push(k);  // full: the viewer is behind; counted in the ring's drops()
  }
  if (!wanted_.load(std::memory_order_relaxed)) return;
  const int64_t now = rt::now_ns();
  const bool forced = publish_next_.load(std::memory_order_relaxed);
  if (!forced && last_publish_wall_ns_ != 0 && now - last_publish_wall_ns_ < min_period_ns_) return;
  // A regular snapshot leaves the reserved slot free (the producer's view of
  // the ring's size is an upper bound: the viewer only takes from it).
  if (!forced && ring_.size() + 2 >= kPoolSize) {
    skipped_busy_.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  const rt::PoolHandle h = pool_.acquire();
  ViewSnapshot* s = pool_.get(h);
  if (s == nullptr) {
    skipped_busy_.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  const bool with_map =
      tracker_ != nullptr && (map_requested_.load(std::memory_order_relaxed) ||
                              (keyframe_since_map_ && now - last_map_wall_ns_ >= map_period_ns_));
  fill(*s, f, info, with_map);
  if (!ring_.try_push(h)) {
    pool_.release(h);
    skipped_busy_.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  if (with_map) {
    // A browser that asked keeps asking until the map has points.
    if (s->n_map > 0) map_requested_.store(false, std::memory_order_relaxed);
    keyframe_since_map_ = false;
    last_map_wall_ns_ = now;
  }
  last_publish_wall_ns_ = now;
  if (forced) publish_next_.store(false, std::memory_order_relaxed);
  tracking_max_ns_ = imu_max_ns_ = 0;
  published_.fetch_add(1, std::memory_order_relaxed);
}

void ViewerFeed::fill(ViewSnapshot& s, const core::RgbdFrame& f, const FrameInfo& info,
                      bool with_map) noexcept {
  StateSnapshot& st = s.state;
  const core::EstimatorOutput& o = est_.output();
  st.t_ns = f.t_ns;
  st.seq = f.seq;
  st.frames_fed = info.frames_fed;
  st.quality = o.quality;
  st.reset_counter = o.reset_counter;
  for (int i = 0; i < 3; ++i) {
    st.p_WB[i] = o.state.p_WB[i];
    st.v_WB[i] = o.state.v_WB[i];
  }
  st.q_WB[0] = o.state.q_WB.w();
  st.q_WB[1] = o.state.q_WB.x();
  st.q_WB[2] = o.state.q_WB.y();
  st.q_WB[3] = o.state.q_WB.z();
  st.has_tracker = tracker_ != nullptr;
  s.n_features = 0;
  if (tracker_ != nullptr) {
    const core::TrackResult& r = tracker_->last();
    st.track_status = r.status;
    st.keyframe = r.keyframe;
    st.detected = r.detected;
    st.with_depth = r.with_depth;
    st.matched = r.matched;
    st.inliers = r.inliers;
    st.map_inliers = r.map_inliers;
    st.inlier_rms_px = r.inlier_rms_px;
    st.area_ratio = r.area_ratio;
    s.n_features = tracker_->copy_last_features(s.features, kMaxFeatures);
  }
  st.tracking_ns = info.tracking_ns;
  st.tracking_max_ns = tracking_max_ns_;
  st.imu_to_pose_max_ns = imu_max_ns_;
  const core::EstimatorView view = est_.view();
  const core::OptimizerStatus& w = view.optimizer;
  st.has_window = view.has_optimizer;
  if (st.has_window) {
    st.optimizer_solve_ns = w.last_solve_ns;
    st.window_jobs = w.jobs;
    st.window_applied = w.applied;
    st.window_failures = w.failures;
    st.window_skipped_busy = w.skipped_busy;
    st.window_resets = w.resets;
  }
  const core::EstimatorCounters& c = est_.counters();
  st.imu_in = c.imu_in;
  st.frames_in = c.frames_in;
  st.frames_used = c.frames_used;
  st.resets = c.resets;
  st.imu_rejected = c.imu_rejects.non_finite + c.imu_rejects.saturated + c.imu_rejects.out_of_order;
  st.pipeline = info;
  st.snapshots_skipped = skipped_busy_.load(std::memory_order_relaxed);
  preview_rgb(f.rgb, s);
  preview_depth(f.depth, s);
  s.has_map = with_map;
  s.n_map = with_map ? tracker_->copy_map_points(s.map_xyz, kMaxMapPoints) : 0;
}

const ViewSnapshot* ViewerFeed::take_newest(rt::PoolHandle* handle) noexcept {
  rt::PoolHandle newest = rt::kInvalidHandle;
  rt::PoolHandle h = rt::kInvalidHandle;
  while (ring_.try_pop(h)) {
    if (newest != rt::kInvalidHandle) pool_.release(newest);
    newest = h;
  }
  *handle = newest;
  return newest != rt::kInvalidHandle ? pool_.get(newest) : nullptr;
}

void PlaybackControl::pause() noexcept {
  if (!available_ || paused()) return;
  step();
}

void PlaybackControl::resume() noexcept { paused_.store(false, std::memory_order_release); }

void PlaybackControl::step() noexcept {
  if (!available_) return;
  if (feed_ != nullptr) feed_->publish_next();
  step_until_.store(frames_seen_.load(std::memory_order_relaxed) + 1, std::memory_order_relaxed);
  paused_.store(true, std::memory_order_release);
}

bool PlaybackControl::may_proceed(uint64_t frames_fed) noexcept {
  frames_seen_.store(frames_fed, std::memory_order_relaxed);
  if (!paused_.load(std::memory_order_acquire)) return true;
  return frames_fed < step_until_.load(std::memory_order_relaxed);
}

}  // namespace kestrel::viewer

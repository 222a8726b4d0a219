#include "kestrel/dense/dense_mapper.hpp"

#include <time.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <string>

#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/thread_setup.hpp"

namespace kestrel::dense {

namespace {
// A sleep nobody rang for ends after this (stop races, a missed bell).
constexpr int64_t kIdleWaitNs = 50'000'000;

void copy_image(const ImageView& in, std::vector<uint8_t>& bytes, ImageView& out) {
  const int row = in.width * bytes_per_pixel(in.format);
  for (int v = 0; v < in.height; ++v) {
    std::memcpy(bytes.data() + static_cast<std::size_t>(v) * row,
                in.data + static_cast<std::ptrdiff_t>(v) * in.stride_bytes, static_cast<std::size_t>(row));
  }
  out = in;
  out.stride_bytes = row;
  out.data = bytes.data();
}
}  // namespace

void DenseOptions::validate() const {
  tsdf.validate();
  auto require = [](bool ok, const char* what) {
    if (!ok) throw std::invalid_argument(std::string("dense.") + what);
  };
  require(std::isfinite(keyframe_distance_m) && keyframe_distance_m >= 0,
          "keyframe_distance_m must be >= 0 m");
  require(std::isfinite(keyframe_angle_deg) && keyframe_angle_deg >= 0,
          "keyframe_angle_deg must be >= 0 deg");
  require(std::isfinite(keyframe_interval_s) && keyframe_interval_s > 0, "keyframe_interval_s must be > 0 s");
  archive.validate();
  require(std::isfinite(reanchor_min_shift_m) && reanchor_min_shift_m >= 0,
          "reanchor_min_shift_m must be >= 0 m");
  require(std::isfinite(reanchor_min_angle_deg) && reanchor_min_angle_deg >= 0,
          "reanchor_min_angle_deg must be >= 0 deg");
  require(std::isfinite(reanchor_cpu_s_per_s) && reanchor_cpu_s_per_s > 0 && reanchor_cpu_s_per_s <= 1,
          "reanchor_cpu_s_per_s must be in (0, 1] CPU-s per s");
  require(std::isfinite(reanchor_burst_cpu_s) && reanchor_burst_cpu_s > 0 && reanchor_burst_cpu_s <= 60,
          "reanchor_burst_cpu_s must be in (0, 60] CPU-s");
  require(!live_reanchor || archive.budget_mb > 0, "live_reanchor needs archive_budget_mb > 0");
  require(handoff_slots >= 1 && handoff_slots <= static_cast<int>(64), "handoff_slots must be in [1, 64]");
}

DenseMapper::DenseMapper(const DenseOptions& opt, const Rig& rig, bool wait_when_full)
    : opt_(opt), rig_(rig), wait_when_full_(wait_when_full) {
  if (!opt_.enabled) return;
  opt_.validate();
  if (rig.rgb.width <= 0 || rig.rgb.height <= 0)
    throw std::invalid_argument("dense map: the rig has no camera size (rgb.width/height)");
  T_BC_.matrix() = Eigen::Map<const Eigen::Matrix<double, 4, 4, Eigen::RowMajor>>(rig.T_BC.data());
  map_ = std::make_unique<core::TsdfMap>(opt_.tsdf);
  if (opt_.archive.budget_mb > 0) archive_ = std::make_unique<core::KeyframeArchive>(opt_.archive, rig.rgb);
  if (opt_.live_reanchor) {
    fused_C_.assign(static_cast<std::size_t>(archive_->capacity()), Eigen::Isometry3d::Identity());
    target_C_ = fused_C_;
  }
  const auto pixels = static_cast<std::size_t>(rig.rgb.width) * static_cast<std::size_t>(rig.rgb.height);
  slots_.resize(static_cast<std::size_t>(opt_.handoff_slots));
  for (std::size_t i = 0; i < slots_.size(); ++i) {
    slots_[i].rgb_bytes.assign(3 * pixels, 0);
    slots_[i].depth_bytes.assign(2 * pixels, 0);
    (void)free_.try_push(static_cast<uint32_t>(i));
  }
  started_ = true;
  thread_ = rt::start_thread(
      thread_spec(), [this] { run(); }, &thread_report_);
}

DenseMapper::~DenseMapper() { stop(); }

const rt::ThreadSpec& DenseMapper::thread_spec() {
  // Not real time: SCHED_OTHER on any CPU, below everything that flies.
  static const rt::ThreadSpec spec{"kst-dense", 0, -1, 0};
  return spec;
}

bool DenseMapper::is_keyframe(int64_t t_ns, const Eigen::Isometry3d& T_WB) const {
  if (!have_last_) return true;
  if (static_cast<double>(t_ns - last_t_ns_) * 1e-9 >= opt_.keyframe_interval_s) return true;
  if ((T_WB.translation() - last_T_WB_.translation()).norm() >= opt_.keyframe_distance_m) return true;
  const double angle_rad = Eigen::AngleAxisd(last_T_WB_.linear().transpose() * T_WB.linear()).angle();
  return angle_rad * 180.0 / M_PI >= opt_.keyframe_angle_deg;
}

void DenseMapper::offer(int64_t t_ns, const ImageView& rgb, const ImageView& depth,
                        const Eigen::Isometry3d& T_WB) {
  if (!started_) return;
  ++stats_.offered;
  if (depth.data == nullptr || !T_WB.matrix().allFinite() || !is_keyframe(t_ns, T_WB)) return;
  if (depth.width != rig_.rgb.width || depth.height != rig_.rgb.height ||
      depth.format != PixelFormat::kDepthU16 ||
      (rgb.data != nullptr &&
       (rgb.width != depth.width || rgb.height != depth.height || bytes_per_pixel(rgb.format) != 3))) {
    ++stats_.wrong_size;
    return;
  }
  ++stats_.keyframes;
  have_last_ = true;
  last_t_ns_ = t_ns;
  last_T_WB_ = T_WB;
  uint32_t* idx = free_.front();
  while (idx == nullptr && wait_when_full_) {
    free_bell_.wait_for_ns(kIdleWaitNs);
    idx = free_.front();
  }
  if (idx == nullptr) {
    ++stats_.dropped;
    return;
  }
  const uint32_t i = *idx;
  free_.pop();
  Slot& s = slots_[i];
  s.t_ns = t_ns;
  s.T_WC = T_WB * T_BC_;
  copy_image(depth, s.depth_bytes, s.depth);
  if (rgb.data != nullptr) {
    copy_image(rgb, s.rgb_bytes, s.rgb);
  } else {
    s.rgb = ImageView{};
  }
  s.C_MW = C_now_;
  s.handed_ns = rt::now_ns();
  handed_.fetch_add(1, std::memory_order_relaxed);
  (void)filled_.try_push(i);  // never full: it holds at most handoff_slots <= its capacity
  work_bell_.ring();
}

void DenseMapper::note_correction(int64_t t_ns, uint32_t alignment, const Eigen::Isometry3d& C_MW) {
  if (!started_ || !opt_.live_reanchor || !C_MW.matrix().allFinite()) return;
  if (have_alignment_ && alignment == alignment_) return;
  have_alignment_ = true;
  alignment_ = alignment;
  C_now_ = C_MW;
  Correction c;
  c.t_ns = t_ns;
  c.received_ns = rt::now_ns();
  c.C_MW = C_MW;
  (void)corrections_.try_push(c);  // full: counted by the ring, read at stop()
  work_bell_.ring();
}

void DenseMapper::attach_view(DenseViewSink* sink, const DenseViewOptions& view) {
  if (!started_ || sink == nullptr) return;
  view_encoder_ = std::make_unique<DenseViewEncoder>(*map_);
  // A second of the rate as the burst: a browser that connects gets the first
  // second's worth at once, then the steady rate.
  view.validate();
  view_budget_ = std::make_unique<ByteBudget>(view.max_kbps, 1.0);
  view_period_ns_ = static_cast<int64_t>(view.period_s * 1e9);
  view_sink_.store(sink, std::memory_order_release);
}

namespace {
// Delta^s * A with Delta = B * A^-1: a fraction s of the way from A to B
// (rotation by slerp of the relative rotation, translation linearly with it).
Eigen::Isometry3d interpolate(const Eigen::Isometry3d& A, const Eigen::Isometry3d& B, double s) {
  const Eigen::Isometry3d D = B * A.inverse();
  const Eigen::AngleAxisd aa(D.linear());
  Eigen::Isometry3d Ds = Eigen::Isometry3d::Identity();
  Ds.linear() = Eigen::AngleAxisd(s * aa.angle(), aa.axis()).toRotationMatrix();
  Ds.translation() = s * D.translation();
  return Ds * A;
}
}  // namespace

void DenseMapper::fuse_slot(Slot& s) {
  const int64_t t0 = rt::now_ns();
  if (opt_.live_reanchor) {
    // Fused from the archived copy, so that taking it out again later
    // (deintegrate) subtracts exactly what was added.
    if (archive_->store(s.t_ns, s.T_WC, s.depth, s.rgb)) {
      const int last = archive_->size() - 1;
      const auto k = static_cast<std::size_t>((archive_->counters().stored - 1) %
                                              static_cast<uint64_t>(archive_->capacity()));
      fused_C_[k] = target_C_[k] = s.C_MW;
      Eigen::Isometry3d C_map;
      if (map_correction_at(s.t_ns, C_map)) {
        // Within the span the map has moved already: its word.
        target_C_[k] = C_map;
        if (catch_up_since_ns_ < 0) catch_up_since_ns_ = rt::now_ns();
      } else if (have_correction_ && s.t_ns < last_correction_.t_ns && s.t_ns > interval_t_a_) {
        // Taken before the newest correction but fused after it arrived: its share of that correction.
        target_C_[k] = interpolate(interval_C_a_, last_correction_.C_MW,
                                   static_cast<double>(s.t_ns - interval_t_a_) /
                                       static_cast<double>(last_correction_.t_ns - interval_t_a_));
        if (catch_up_since_ns_ < 0) catch_up_since_ns_ = rt::now_ns();
      }
      const std::unique_lock<std::shared_mutex> lock(map_mutex_);
      map_->integrate(archive_->depth(last), archive_->rgb(last), archive_->camera(), rig_.depth,
                      s.C_MW * s.T_WC);
    }
  } else {
    {
      const std::unique_lock<std::shared_mutex> lock(map_mutex_);
      map_->integrate(s.depth, s.rgb, rig_.rgb, rig_.depth, s.T_WC);
    }
    if (archive_ != nullptr) (void)archive_->store(s.t_ns, s.T_WC, s.depth, s.rgb);
  }
  const int64_t t1 = rt::now_ns();
  stats_.integrate.record(t1 - t0);
  stats_.latency.record(t1 - s.handed_ns);
  ++stats_.integrated;
}

void DenseMapper::apply_correction(const Correction& c) {
  ++stats_.corrections;
  // The drift that the new correction removes built up since the previous
  // one (when the map last agreed with the odometry): keyframes in between
  // get the share of it their time says; later ones all of it (they were
  // fused with it already); earlier ones keep theirs. T_map_odom is all the
  // pipeline sees in flight: a bundle adjustment that moves older keyframes
  // individually is followed at the end (--dense-map-out), not here.
  const int64_t t_a =
      have_correction_ ? last_correction_.t_ns : (archive_->size() > 0 ? archive_->t_ns(0) : c.t_ns);
  const Eigen::Isometry3d C_a = have_correction_ ? last_correction_.C_MW : Eigen::Isometry3d::Identity();
  const uint64_t first = archive_->counters().stored - static_cast<uint64_t>(archive_->size());
  // Keyframes the map's own list covers keep its word; after that list's end
  // the change is the map's realignment to its newest keyframe: all of it.
  const int64_t map_until = map_C_.empty() ? INT64_MIN : map_C_.back().t_ns;
  const bool after_map = map_until > t_a;
  for (int i = 0; i < archive_->size(); ++i) {
    const int64_t t = archive_->t_ns(i);
    if (t <= t_a || t <= map_until) continue;
    const auto k = static_cast<std::size_t>((first + static_cast<uint64_t>(i)) %
                                            static_cast<uint64_t>(archive_->capacity()));
    const double s = t >= c.t_ns || after_map ? 1.0
                                              : static_cast<double>(t - t_a) /
                                                    static_cast<double>(std::max<int64_t>(1, c.t_ns - t_a));
    target_C_[k] = interpolate(C_a, c.C_MW, s);
  }
  interval_t_a_ = t_a;
  interval_C_a_ = C_a;
  last_correction_ = c;
  have_correction_ = true;
  const int pending = reanchor_pending(nullptr);
  reanchor_backlog_.store(pending, std::memory_order_release);
  corrections_applied_.fetch_add(1, std::memory_order_release);
  stats_.reanchor_pending_max = std::max(stats_.reanchor_pending_max, pending);
  if (pending > 0 && catch_up_since_ns_ < 0) catch_up_since_ns_ = c.received_ns;
}

void DenseMapper::note_map_keyframes(const std::vector<MapCorrection>& sorted) {
  if (!started_ || !opt_.live_reanchor || sorted.empty()) return;
  {
    const std::lock_guard<std::mutex> lock(map_moves_mutex_);
    map_moves_in_ = sorted;
  }
  map_moves_ready_.store(true, std::memory_order_release);
  work_bell_.ring();
}

bool DenseMapper::map_correction_at(int64_t t_ns, Eigen::Isometry3d& C_MW) const {
  if (map_C_.empty() || t_ns < map_C_.front().t_ns || t_ns > map_C_.back().t_ns) return false;
  const auto it = std::lower_bound(map_C_.begin(), map_C_.end(), t_ns,
                                   [](const MapCorrection& m, int64_t t) { return m.t_ns < t; });
  if (it->t_ns == t_ns) {  // also the first entry: t_ns >= its time
    C_MW = it->C_MW;
    return true;
  }
  const MapCorrection& a = *std::prev(it);
  C_MW = interpolate(
      a.C_MW, it->C_MW,
      static_cast<double>(t_ns - a.t_ns) / static_cast<double>(std::max<int64_t>(1, it->t_ns - a.t_ns)));
  return true;
}

void DenseMapper::apply_map_keyframes() {
  {
    const std::lock_guard<std::mutex> lock(map_moves_mutex_);
    map_C_.swap(map_moves_in_);
    map_moves_ready_.store(false, std::memory_order_relaxed);
  }
  ++stats_.map_moves;
  const uint64_t first = archive_->counters().stored - static_cast<uint64_t>(archive_->size());
  for (int i = 0; i < archive_->size(); ++i) {
    Eigen::Isometry3d C;
    if (!map_correction_at(archive_->t_ns(i), C)) continue;
    target_C_[static_cast<std::size_t>((first + static_cast<uint64_t>(i)) %
                                       static_cast<uint64_t>(archive_->capacity()))] = C;
  }
  const int pending = reanchor_pending(nullptr);
  reanchor_backlog_.store(pending, std::memory_order_release);
  stats_.reanchor_pending_max = std::max(stats_.reanchor_pending_max, pending);
  if (pending > 0 && catch_up_since_ns_ < 0) catch_up_since_ns_ = rt::now_ns();
  map_moves_applied_.fetch_add(1, std::memory_order_release);
}

int DenseMapper::reanchor_pending(int* worst) const {
  int n = 0;
  double worst_score = 0;
  const uint64_t first = archive_->counters().stored - static_cast<uint64_t>(archive_->size());
  const double min_angle_rad = opt_.reanchor_min_angle_deg * M_PI / 180.0;
  for (int i = 0; i < archive_->size(); ++i) {
    const auto k = static_cast<std::size_t>((first + static_cast<uint64_t>(i)) %
                                            static_cast<uint64_t>(archive_->capacity()));
    const Eigen::Vector3d p_WC = archive_->T_WC(i).translation();
    const double shift_m = (target_C_[k] * p_WC - fused_C_[k] * p_WC).norm();
    const double angle_rad =
        Eigen::AngleAxisd(fused_C_[k].linear().transpose() * target_C_[k].linear()).angle();
    if (shift_m <= opt_.reanchor_min_shift_m && angle_rad <= min_angle_rad) continue;
    ++n;
    // The farthest moved first: at 1 m a turn of one radian moves a surface by a metre.
    const double score = shift_m + angle_rad;
    if (worst != nullptr && score > worst_score) {
      worst_score = score;
      *worst = i;
    }
  }
  return n;
}

bool DenseMapper::reanchor_one() {
  if (!opt_.live_reanchor || catch_up_since_ns_ < 0) return false;
  const int64_t now = rt::now_ns();
  if (reanchor_refill_ns_ < 0) {
    reanchor_refill_ns_ = now;
    reanchor_tokens_cpu_s_ = opt_.reanchor_burst_cpu_s;
  }
  reanchor_tokens_cpu_s_ = std::min(
      opt_.reanchor_burst_cpu_s, reanchor_tokens_cpu_s_ + opt_.reanchor_cpu_s_per_s * 1e-9 *
                                                              static_cast<double>(now - reanchor_refill_ns_));
  reanchor_refill_ns_ = now;
  if (reanchor_tokens_cpu_s_ <= 0) return false;
  int i = -1;
  const int pending = reanchor_pending(&i);
  reanchor_backlog_.store(pending, std::memory_order_release);
  if (pending == 0 || i < 0) {
    stats_.reanchor_catch_up.record(now - catch_up_since_ns_);
    catch_up_since_ns_ = -1;
    return false;
  }
  const uint64_t first = archive_->counters().stored - static_cast<uint64_t>(archive_->size());
  const auto k = static_cast<std::size_t>((first + static_cast<uint64_t>(i)) %
                                          static_cast<uint64_t>(archive_->capacity()));
  timespec a{}, b{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &a);
  const Eigen::Isometry3d& T_WC = archive_->T_WC(i);
  // Out and in again under one lock: a query never sees the keyframe missing.
  const std::unique_lock<std::shared_mutex> lock(map_mutex_);
  map_->deintegrate(archive_->depth(i), archive_->rgb(i), archive_->camera(), rig_.depth, fused_C_[k] * T_WC);
  map_->integrate(archive_->depth(i), archive_->rgb(i), archive_->camera(), rig_.depth, target_C_[k] * T_WC);
  fused_C_[k] = target_C_[k];
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &b);
  const double cpu_s =
      static_cast<double>(b.tv_sec - a.tv_sec) + 1e-9 * static_cast<double>(b.tv_nsec - a.tv_nsec);
  reanchor_tokens_cpu_s_ -= cpu_s;
  stats_.reanchor_cpu_s += cpu_s;
  ++stats_.reanchored;
  return true;
}

void DenseMapper::pump_view() {
  DenseViewSink* sink = view_sink_.load(std::memory_order_acquire);
  if (sink == nullptr || !sink->wanted()) return;
  const int64_t now = rt::now_ns();
  const bool resend = sink->take_resend_request();
  if (resend) view_encoder_->request_all();
  // A round at most every period (a browser that just connected does not wait):
  // a block several keyframes touched meanwhile is extracted and sent once.
  if (!resend && now < view_next_round_ns_) return;
  view_next_round_ns_ = now + view_period_ns_;
  // As many messages as the budget and the free slots allow; what is left waits for the next round.
  for (;;) {
    const std::size_t allowed = view_budget_->available(now);
    if (allowed < kDenseViewMinMessageBytes) return;
    std::size_t capacity = 0;
    uint8_t* buf = sink->acquire(&capacity);
    if (buf == nullptr) {
      ++stats_.view_no_slot;
      return;
    }
    const std::size_t n = view_encoder_->encode(buf, std::min(capacity, allowed));
    if (n == 0) return;
    view_budget_->spend(n);
    sink->publish(n);
    ++stats_.view_messages;
    stats_.view_bytes += n;
  }
}

void DenseMapper::run() {
  for (;;) {
    Correction c;
    // The map's keyframe list first: a correction that comes with it (the
    // realignment after a bundle adjustment) then leaves the keyframes it covers alone.
    if (map_moves_ready_.load(std::memory_order_acquire)) apply_map_keyframes();
    while (corrections_.try_pop(c)) apply_correction(c);
    uint32_t* idx = filled_.front();
    if (idx == nullptr) {
      if (stop_.load(std::memory_order_acquire) && filled_.front() == nullptr) break;
      // Idle: old keyframes a correction moved, then the viewer; new keyframes come first.
      if (reanchor_one()) {
        pump_view();
        continue;
      }
      pump_view();
      work_bell_.wait_for_ns(kIdleWaitNs);
      continue;
    }
    const uint32_t i = *idx;
    filled_.pop();
    fuse_slot(slots_[i]);
    (void)free_.try_push(i);
    done_.fetch_add(1, std::memory_order_release);
    free_bell_.ring();
    pump_view();
  }
  stats_.corrections_dropped = corrections_.drops();
  if (opt_.live_reanchor) stats_.reanchor_left = reanchor_pending(nullptr);
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  stats_.cpu_s = static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

void DenseMapper::rebuild_along(const std::function<bool(int64_t t_ns, Eigen::Isometry3d& C_MW)>& C_MW_of) {
  if (map_ == nullptr || archive_ == nullptr) return;
  stop();
  const std::unique_lock<std::shared_mutex> lock(map_mutex_);
  stats_.rebuild =
      core::reintegrate(*archive_, rig_.depth, *map_,
                        [&](int64_t t_ns, const Eigen::Isometry3d& T_WC, Eigen::Isometry3d& T_MC) {
                          Eigen::Isometry3d C_MW;
                          if (!C_MW_of(t_ns, C_MW)) return false;
                          T_MC = C_MW * T_WC;
                          return true;
                        });
  stats_.rebuilt = true;
}

core::Occupancy DenseMapper::occupancy(const Eigen::Vector3d& p) const {
  if (map_ == nullptr) return core::Occupancy::kUnknown;
  queries_.fetch_add(1, std::memory_order_relaxed);
  const std::shared_lock<std::shared_mutex> lock(map_mutex_);
  return map_->occupancy(p);
}

core::Occupancy DenseMapper::segment(const Eigen::Vector3d& a, const Eigen::Vector3d& b) const {
  if (map_ == nullptr) return core::Occupancy::kUnknown;
  queries_.fetch_add(1, std::memory_order_relaxed);
  const std::shared_lock<std::shared_mutex> lock(map_mutex_);
  return map_->segment(a, b);
}

bool DenseMapper::distance(const Eigen::Vector3d& p, float& sdf_m) const {
  if (map_ == nullptr) return false;
  queries_.fetch_add(1, std::memory_order_relaxed);
  const std::shared_lock<std::shared_mutex> lock(map_mutex_);
  return map_->distance(p, sdf_m);
}

void DenseMapper::read(const std::function<void(const core::TsdfMap&)>& fn) const {
  if (map_ == nullptr) return;
  queries_.fetch_add(1, std::memory_order_relaxed);
  const std::shared_lock<std::shared_mutex> lock(map_mutex_);
  fn(*map_);
}

void DenseMapper::wait_idle() {
  if (!started_) return;
  while (done_.load(std::memory_order_acquire) < handed_.load(std::memory_order_relaxed))
    free_bell_.wait_for_ns(kIdleWaitNs);
}

void DenseMapper::stop() {
  if (!started_) return;
  stop_.store(true, std::memory_order_release);
  work_bell_.ring();
  if (thread_.joinable()) thread_.join();
  started_ = false;
}

}  // namespace kestrel::dense

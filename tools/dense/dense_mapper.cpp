#include "kestrel/dense/dense_mapper.hpp"

#include <time.h>

#include <cmath>
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
  for (int v = 0; v < in.height; ++v)
    std::memcpy(bytes.data() + static_cast<std::size_t>(v) * row,
                in.data + static_cast<std::ptrdiff_t>(v) * in.stride_bytes, static_cast<std::size_t>(row));
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
  s.handed_ns = rt::now_ns();
  handed_.fetch_add(1, std::memory_order_relaxed);
  (void)filled_.try_push(i);  // never full: it holds at most handoff_slots <= its capacity
  work_bell_.ring();
}

void DenseMapper::run() {
  for (;;) {
    uint32_t* idx = filled_.front();
    if (idx == nullptr) {
      if (stop_.load(std::memory_order_acquire) && filled_.front() == nullptr) break;
      work_bell_.wait_for_ns(kIdleWaitNs);
      continue;
    }
    const uint32_t i = *idx;
    filled_.pop();
    Slot& s = slots_[i];
    const int64_t t0 = rt::now_ns();
    map_->integrate(s.depth, s.rgb, rig_.rgb, rig_.depth, s.T_WC);
    if (archive_ != nullptr) (void)archive_->store(s.t_ns, s.T_WC, s.depth, s.rgb);
    const int64_t t1 = rt::now_ns();
    stats_.integrate.record(t1 - t0);
    stats_.latency.record(t1 - s.handed_ns);
    ++stats_.integrated;
    (void)free_.try_push(i);
    done_.fetch_add(1, std::memory_order_release);
    free_bell_.ring();
  }
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  stats_.cpu_s = static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

void DenseMapper::rebuild_along(const std::function<bool(int64_t t_ns, Eigen::Isometry3d& C_MW)>& C_MW_of) {
  if (map_ == nullptr || archive_ == nullptr) return;
  stop();
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

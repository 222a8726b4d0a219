#include "kestrel/core/keyframe_archive.hpp"

#include <time.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <stdexcept>
#include <string>

namespace kestrel::core {

namespace {
int64_t now_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}
}  // namespace

void KeyframeArchiveOptions::validate() const {
  if (!std::isfinite(budget_mb) || budget_mb < 0 || budget_mb > 65536)
    throw std::invalid_argument("dense.archive_budget_mb must be in [0, 65536] MiB");
  if (stride_px < 1 || stride_px > 16)
    throw std::invalid_argument("dense.archive_stride_px must be in [1, 16]");
}

KeyframeArchive::KeyframeArchive(const KeyframeArchiveOptions& opt, const CameraIntrinsics& cam)
    : opt_(opt), cam_full_(cam) {
  opt_.validate();
  if (cam.width <= 0 || cam.height <= 0) throw std::invalid_argument("keyframe archive: camera has no size");
  const int s = opt_.stride_px;
  cam_small_ = cam;
  cam_small_.width = (cam.width + s - 1) / s;
  cam_small_.height = (cam.height + s - 1) / s;
  // Pixel (u', v') of the small image is pixel (s u', s v') of the full one, so
  // a projection u = fx x + cx becomes u' = u / s: every term divides by s.
  cam_small_.fx = cam.fx / s;
  cam_small_.fy = cam.fy / s;
  cam_small_.cx = cam.cx / s;
  cam_small_.cy = cam.cy / s;
  const auto pixels =
      static_cast<std::size_t>(cam_small_.width) * static_cast<std::size_t>(cam_small_.height);
  capacity_ = static_cast<int>(opt_.budget_mb * 1048576.0 / static_cast<double>(pixels * 5));
  if (capacity_ <= 0) return;
  entries_.resize(static_cast<std::size_t>(capacity_));
  depth_.assign(pixels * static_cast<std::size_t>(capacity_), 0);
  rgb_.assign(3 * pixels * static_cast<std::size_t>(capacity_), 0);
}

bool KeyframeArchive::store(int64_t t_ns, const Eigen::Isometry3d& T_WC, const ImageView& depth,
                            const ImageView& rgb) {
  if (capacity_ <= 0 || depth.data == nullptr || depth.format != PixelFormat::kDepthU16 ||
      depth.width != cam_full_.width || depth.height != cam_full_.height)
    return false;
  const bool has_rgb = rgb.data != nullptr && rgb.width == depth.width && rgb.height == depth.height &&
                       bytes_per_pixel(rgb.format) == 3;
  int slot;
  if (size_ < capacity_) {
    slot = index(size_);
    ++size_;
  } else {
    slot = head_;
    head_ = (head_ + 1) % capacity_;
    ++counters_.overwritten;
  }
  Entry& e = entries_[static_cast<std::size_t>(slot)];
  e.t_ns = t_ns;
  e.T_WC = T_WC;
  e.has_rgb = has_rgb;
  e.rgb_format = has_rgb ? rgb.format : PixelFormat::kRgb8;
  const int s = opt_.stride_px, w = cam_small_.width, h = cam_small_.height;
  const std::size_t pixels = static_cast<std::size_t>(w) * static_cast<std::size_t>(h);
  uint16_t* d = depth_.data() + static_cast<std::size_t>(slot) * pixels;
  uint8_t* c = rgb_.data() + static_cast<std::size_t>(slot) * pixels * 3;
  for (int v = 0; v < h; ++v) {
    const uint8_t* drow = depth.data + static_cast<std::ptrdiff_t>(v * s) * depth.stride_bytes;
    const uint8_t* crow =
        has_rgb ? rgb.data + static_cast<std::ptrdiff_t>(v * s) * rgb.stride_bytes : nullptr;
    for (int u = 0; u < w; ++u) {
      uint16_t z;
      std::memcpy(&z, drow + 2 * u * s, 2);
      d[v * w + u] = z;
      if (crow != nullptr) std::memcpy(c + 3 * (v * w + u), crow + 3 * u * s, 3);
    }
  }
  ++counters_.stored;
  return true;
}

ImageView KeyframeArchive::depth(int i) const {
  const int slot = index(i);
  const std::size_t pixels =
      static_cast<std::size_t>(cam_small_.width) * static_cast<std::size_t>(cam_small_.height);
  ImageView v;
  v.width = cam_small_.width;
  v.height = cam_small_.height;
  v.stride_bytes = 2 * cam_small_.width;
  v.format = PixelFormat::kDepthU16;
  v.data = reinterpret_cast<const uint8_t*>(depth_.data() + static_cast<std::size_t>(slot) * pixels);
  return v;
}

ImageView KeyframeArchive::rgb(int i) const {
  const int slot = index(i);
  if (!entries_[static_cast<std::size_t>(slot)].has_rgb) return ImageView{};
  const std::size_t pixels =
      static_cast<std::size_t>(cam_small_.width) * static_cast<std::size_t>(cam_small_.height);
  ImageView v;
  v.width = cam_small_.width;
  v.height = cam_small_.height;
  v.stride_bytes = 3 * cam_small_.width;
  v.format = entries_[static_cast<std::size_t>(slot)].rgb_format;
  v.data = rgb_.data() + static_cast<std::size_t>(slot) * pixels * 3;
  return v;
}

void KeyframeArchive::clear() {
  head_ = 0;
  size_ = 0;
  counters_ = KeyframeArchiveCounters{};
}

ReintegrationReport reintegrate(const KeyframeArchive& archive, const DepthModel& depth_model, TsdfMap& map,
                                const std::function<bool(int64_t t_ns, const Eigen::Isometry3d& T_WC,
                                                         Eigen::Isometry3d& T_MC)>& T_MC_of) {
  ReintegrationReport r;
  const int64_t t0 = now_ns();
  map.clear();
  for (int i = 0; i < archive.size(); ++i) {
    Eigen::Isometry3d T_MC = Eigen::Isometry3d::Identity();
    if (!T_MC_of(archive.t_ns(i), archive.T_WC(i), T_MC) || !T_MC.matrix().allFinite()) {
      ++r.no_pose;
      continue;
    }
    map.integrate(archive.depth(i), archive.rgb(i), archive.camera(), depth_model, T_MC);
    ++r.fused;
  }
  r.cpu_ns = now_ns() - t0;
  return r;
}

}  // namespace kestrel::core

#include "kestrel/core/depth_grid.hpp"

#include <algorithm>
#include <cmath>

#include "kestrel/core/camera.hpp"

namespace kestrel::core {

DepthGridShape DepthGridShape::make(int cols, const PinholeK& K, int width, int height) {
  DepthGridShape s;
  if (cols <= 0 || width <= 0 || height <= 0) return s;
  s.cols = cols;
  s.rows = std::max(1, static_cast<int>(std::lround(static_cast<double>(cols) * height / width)));
  s.K = K;
  s.width = width;
  s.height = height;
  return s;
}

DepthGridSampler::DepthGridSampler(const DepthGridShape& shape, const CameraIntrinsics& cam,
                                   const DepthModel& depth, double edge_rel)
    : shape_(shape), depth_(depth), edge_rel_(edge_rel), width_(cam.width), height_(cam.height) {
  if (shape_.cells() <= 0) return;
  const PinholeCamera pc(cam);
  pixel_.reset(new int32_t[static_cast<size_t>(shape_.cells())]);
  for (int c = 0; c < shape_.cells(); ++c) {
    const Eigen::Vector2d uv = pc.distort_normalized_to_pixel(shape_.ray(c));
    const int x = static_cast<int>(std::lround(uv.x())), y = static_cast<int>(std::lround(uv.y()));
    pixel_[c] = (x >= 1 && y >= 1 && x < width_ - 1 && y < height_ - 1) ? y * width_ + x : -1;
  }
}

int DepthGridSampler::sample(const ImageView& d, uint16_t* z_mm) const {
  const int n = shape_.cells();
  if (n <= 0) return 0;
  std::fill(z_mm, z_mm + n, uint16_t{0});
  if (d.data == nullptr || d.format != PixelFormat::kDepthU16 || d.width != width_ || d.height != height_)
    return 0;
  const int window = std::max(1, width_ / shape_.cols / 4);  // half-width [px]: a quarter of a cell
  int valid = 0;
  for (int c = 0; c < n; ++c) {
    if (pixel_[c] < 0) continue;
    const int x = pixel_[c] % width_, y = pixel_[c] / width_;
    double zmin = 1e300, zmax = 0, zc = 0;
    bool hole = false;
    for (int dy = -1; dy <= 1 && !hole; ++dy) {
      const auto* row =
          reinterpret_cast<const uint16_t*>(d.data + static_cast<size_t>(y + dy) * d.stride_bytes);
      for (int dx = -1; dx <= 1; ++dx) {
        const uint16_t raw = row[x + dx];
        if (raw == 0) {
          hole = true;
          break;
        }
        const double z = raw * depth_.scale_m_per_unit;
        zmin = std::min(zmin, z);
        zmax = std::max(zmax, z);
        if (dx == 0 && dy == 0) zc = z;
      }
    }
    if (hole || zc < depth_.min_range_m || zc > depth_.max_range_m || zmax - zmin > edge_rel_ * zc) continue;
    // The cell's depth is the mean over the middle of the cell (half its
    // width), not one pixel: a structured-light pixel's noise (k z^2, 2 cm at
    // 3 m) would otherwise tilt the normals the alignment pairs along.
    double sum = 0;
    int used = 0;
    for (int dy = -window; dy <= window; ++dy) {
      const int yy = y + dy;
      if (yy < 0 || yy >= height_) continue;
      const auto* row = reinterpret_cast<const uint16_t*>(d.data + static_cast<size_t>(yy) * d.stride_bytes);
      for (int dx = -window; dx <= window; ++dx) {
        const int xx = x + dx;
        if (xx < 0 || xx >= width_ || row[xx] == 0) continue;
        const double z = row[xx] * depth_.scale_m_per_unit;
        if (std::abs(z - zc) > 2.0 * edge_rel_ * zc) continue;
        sum += z;
        ++used;
      }
    }
    zc = sum / used;  // the centre itself is always used
    const long mm = std::lround(zc * 1e3);
    if (mm <= 0 || mm > 65535) continue;
    z_mm[c] = static_cast<uint16_t>(mm);
    ++valid;
  }
  return valid;
}

}  // namespace kestrel::core

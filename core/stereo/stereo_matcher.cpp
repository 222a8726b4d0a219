#include "kestrel/core/stereo_matcher.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <opencv2/core/hal/intrin.hpp>
#include <sstream>

namespace kestrel::core {
namespace {

constexpr int kPatchCols = 16;      // one 128-bit vector of pixels
constexpr int kPatchLeft = 8;       // columns left of the keypoint's column
constexpr int kMaxDisparity = 256;  // the cost array lives on the stack
std::atomic<bool> g_vector{true};

inline uint32_t sad_scalar(const uint8_t* a, const uint8_t* b, int stride_a, int stride_b, int rows) {
  uint32_t s = 0;
  for (int r = 0; r < rows; ++r, a += stride_a, b += stride_b)
    for (int c = 0; c < kPatchCols; ++c) s += static_cast<uint32_t>(std::abs(int{a[c]} - int{b[c]}));
  return s;
}

#if CV_SIMD128
inline uint32_t sad_vector(const cv::v_uint8x16* a, const uint8_t* b, int stride_b, int rows) {
  uint32_t s = 0;
  for (int r = 0; r < rows; ++r, b += stride_b) s += cv::v_reduce_sad(a[r], cv::v_load(b));
  return s;
}
#endif

}  // namespace

std::string StereoMatchOptions::validate() const {
  std::ostringstream e;
  if (!(min_disparity_px >= 1 && max_disparity_px > min_disparity_px + 2 &&
        max_disparity_px <= kMaxDisparity - 2)) {
    e << "stereo: 1 <= min_disparity_px, min_disparity_px + 2 < max_disparity_px <= " << kMaxDisparity - 2
      << "\n";
  }
  if (patch_half_rows_px < 1 || patch_half_rows_px > 15) e << "stereo.patch_half_rows_px: 1..15\n";
  if (!(uniqueness_ratio > 0 && uniqueness_ratio <= 1)) e << "stereo.uniqueness_ratio: in (0, 1]\n";
  if (!(max_mean_abs_diff > 0)) e << "stereo.max_mean_abs_diff: > 0\n";
  if (!(disparity_sigma_px > 0)) e << "stereo.disparity_sigma_px: > 0\n";
  return e.str();
}

DepthModel stereo_depth_model(double f_px, double baseline_m, const StereoMatchOptions& opt) {
  DepthModel d;
  const double fb = f_px * baseline_m;
  d.scale_m_per_unit = 0.001;  // unused: stereo depth never travels as an image
  d.min_range_m = fb / opt.max_disparity_px;
  d.max_range_m = fb / opt.min_disparity_px;
  d.sigma_coeff_per_m = opt.disparity_sigma_px / fb;
  return d;
}

StereoMatcher::StereoMatcher(const StereoMatchOptions& opt) : opt_(opt) {}

void StereoMatcher::set_vector_path(bool on) { g_vector.store(on, std::memory_order_relaxed); }

bool StereoMatcher::match(const ImageView& left, const ImageView& right, const float* x_px, const float* y_px,
                          int n, float* disparity_px, StereoMatchStats* stats) const {
  std::fill(disparity_px, disparity_px + n, 0.0f);
  if (stats != nullptr) *stats = StereoMatchStats{};
  if (left.data == nullptr || right.data == nullptr || left.format != PixelFormat::kGray8 ||
      right.format != PixelFormat::kGray8 || left.width != right.width || left.height != right.height)
    return false;
  const int half = opt_.patch_half_rows_px, rows = 2 * half + 1;
  const int d_min = std::max(1, static_cast<int>(std::floor(opt_.min_disparity_px)) - 1);
  const int d_max = std::min(kMaxDisparity - 1, static_cast<int>(std::ceil(opt_.max_disparity_px)) + 1);
  const double max_sad = opt_.max_mean_abs_diff * kPatchCols * rows;
#if CV_SIMD128
  const bool vec = g_vector.load(std::memory_order_relaxed);
#endif
  uint32_t cost[kMaxDisparity + 1];
  for (int i = 0; i < n; ++i) {
    const int xc = static_cast<int>(std::lround(x_px[i]));
    const int yc = static_cast<int>(std::lround(y_px[i]));
    const int x0 = xc - kPatchLeft;  // first column of the left patch
    if (yc - half < 0 || yc + half >= left.height || x0 < 0 || x0 + kPatchCols > left.width) continue;
    // The right patch starts at x0 - d and must stay inside the image.
    const int d_hi = std::min(d_max, x0);
    if (d_hi < d_min + 2) continue;
    if (stats != nullptr) ++stats->searched;
    const uint8_t* lp = left.data + static_cast<size_t>(yc - half) * left.stride_bytes + x0;
    const uint8_t* rp = right.data + static_cast<size_t>(yc - half) * right.stride_bytes + x0;
    uint32_t best = std::numeric_limits<uint32_t>::max();
    int best_d = -1;
#if CV_SIMD128
    if (vec) {
      cv::v_uint8x16 patch[31];
      for (int r = 0; r < rows; ++r) patch[r] = cv::v_load(lp + static_cast<size_t>(r) * left.stride_bytes);
      for (int d = d_min; d <= d_hi; ++d) {
        const uint32_t s = sad_vector(patch, rp - d, right.stride_bytes, rows);
        cost[d] = s;
        if (s < best) best = s, best_d = d;
      }
    } else
#endif
    {
      for (int d = d_min; d <= d_hi; ++d) {
        const uint32_t s = sad_scalar(lp, rp - d, left.stride_bytes, right.stride_bytes, rows);
        cost[d] = s;
        if (s < best) best = s, best_d = d;
      }
    }
    // The extra shift searched at each end only serves the parabola: a minimum there is the range's edge.
    if (best_d <= d_min || best_d >= d_hi) continue;
    if (best > max_sad) continue;
    uint32_t second = std::numeric_limits<uint32_t>::max();
    for (int d = d_min; d <= d_hi; ++d)
      if (std::abs(d - best_d) > 1) second = std::min(second, cost[d]);
    if (second != std::numeric_limits<uint32_t>::max() &&
        static_cast<double>(best) >= opt_.uniqueness_ratio * static_cast<double>(second))
      continue;
    // Sub-pixel: the vertex of the parabola through the minimum and its neighbours.
    const double cm = cost[best_d - 1], c0 = cost[best_d], cp = cost[best_d + 1];
    const double den = cm - 2.0 * c0 + cp;
    const double delta = den > 0 ? std::clamp(0.5 * (cm - cp) / den, -0.5, 0.5) : 0.0;
    const double d = best_d + delta;
    if (d < opt_.min_disparity_px || d > opt_.max_disparity_px) continue;
    disparity_px[i] = static_cast<float>(d);
    if (stats != nullptr) ++stats->matched;
  }
  return true;
}

}  // namespace kestrel::core

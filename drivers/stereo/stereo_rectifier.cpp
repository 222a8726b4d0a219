#include "kestrel/drivers/stereo_rectifier.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/pixels.hpp"

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define KESTREL_REMAP_AVX2 1
#else
#define KESTREL_REMAP_AVX2 0
#endif

namespace kestrel::drivers {
namespace {

cv::Matx44d to_cv(const Mat4d& T) {
  cv::Matx44d m;
  for (int i = 0; i < 16; ++i) m.val[i] = T[static_cast<size_t>(i)];
  return m;
}

cv::Matx33d camera_matrix(const CameraIntrinsics& k) { return {k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1}; }

cv::Mat dist_coeffs(const CameraIntrinsics& k) {
  if (k.distortion == DistortionModel::kEquidistant)
    return (cv::Mat_<double>(4, 1) << k.dist[0], k.dist[1], k.dist[2], k.dist[3]);
  if (k.distortion == DistortionModel::kRadTan)
    return (cv::Mat_<double>(5, 1) << k.dist[0], k.dist[1], k.dist[2], k.dist[3], k.dist[4]);
  return cv::Mat::zeros(5, 1, CV_64F);
}

void check_intrinsics(const CameraIntrinsics& k, const std::string& field) {
  if (k.width <= 0 || k.height <= 0 || !(k.fx > 0) || !(k.fy > 0) || !std::isfinite(k.cx) ||
      !std::isfinite(k.cy))
    throw std::invalid_argument("stereo: " + field + ": no valid intrinsics (width, height, fx, fy > 0)");
  for (double d : k.dist)
    if (!std::isfinite(d)) throw std::invalid_argument("stereo: " + field + ".dist_coeffs: not finite");
}

[[noreturn]] void refuse(const std::string& why) {
  throw std::invalid_argument("stereo: cannot rectify: " + why);
}

}  // namespace

// Where each rectified pixel comes from, without a per-pixel table: streaming
// a word per pixel from memory took more time than the arithmetic
// (docs/stereo.md). Each row is cut into runs of `run` pixels over which the
// rectification map is taken as linear: a start and an increment in 16.16
// fixed point (a sixteenth of a byte per pixel at 16). The run is the longest
// of 16, 8, 4, 2, 1 that stays within 1/64 px of OpenCV's map at every pixel
// (1 is the map itself).
//
// Each pixel's source is the top-left pixel of its bilinear neighbourhood and
// the weights of the right and lower neighbours in 1/32 steps (OpenCV's
// INTER_TAB_SIZE). The vector path computes eight pixels at a time with AVX2
// gathers where the CPU has them; every path computes the same integers, so
// the output is the same. Our own remap rather than cv::remap, which hands its
// rows to OpenCV's thread pool, allocates per call and is slower on one core.
struct RemapRuns {
  static constexpr int kSteps = 32;  // weight steps per pixel
  static constexpr double kTolerancePx = 1.0 / 64;
  static constexpr double kFix = 65536.0;
  int width = 0, height = 0, run = 1, runs_per_row = 0;
  struct Run {
    int32_t sx, sy, dsx, dsy;  // 16.16, the start biased by half a weight step so that truncation rounds
  };
  std::vector<Run> runs;  // height x runs_per_row
  // Pixels the runs cannot sample safely (source outside the image or at its
  // last row or column, where the neighbourhood or a four-byte gather would
  // leave it): their exact source, done one by one after the fast loop.
  struct Fixup {
    uint32_t pixel;
    int32_t x0, y0;  // -1: no source pixel (black)
    uint8_t wx, wy;
  };
  std::vector<Fixup> fixups;
  double max_error_px = 0;

  static int32_t round_fix(double v) { return static_cast<int32_t>(v >= 0 ? v + 0.5 : v - 0.5); }

  static bool outside(float sx, float sy, int w, int h) {
    return !(sx >= 0 && sy >= 0 && sx <= static_cast<float>(w - 1) && sy <= static_cast<float>(h - 1));
  }

  // The runs at length `len`; returns the largest distance from the map over the pixels with a source, in px.
  double set_runs(const cv::Mat& map_x, const cv::Mat& map_y, int len) {
    run = len;
    runs_per_row = (width + run - 1) / run;
    runs.assign(static_cast<size_t>(height) * runs_per_row, Run{});
    constexpr double kBias = kFix / (2 * kSteps);
    double worst = 0;
    for (int y = 0; y < height; ++y) {
      const auto* mx = map_x.ptr<float>(y);
      const auto* my = map_y.ptr<float>(y);
      for (int r = 0; r < runs_per_row; ++r) {
        const int x0 = r * run, x1 = std::min(x0 + run, width - 1);  // x1: where the increment is aimed
        Run& u = runs[static_cast<size_t>(y) * runs_per_row + r];
        u.sx = round_fix(mx[x0] * kFix + kBias);
        u.sy = round_fix(my[x0] * kFix + kBias);
        u.dsx = x1 > x0 ? round_fix((mx[x1] - mx[x0]) / (x1 - x0) * kFix) : 0;
        u.dsy = x1 > x0 ? round_fix((my[x1] - my[x0]) / (x1 - x0) * kFix) : 0;
        for (int k = 0, x = x0; x < std::min(x0 + run, width); ++k, ++x) {
          if (outside(mx[x], my[x], width, height)) continue;
          worst = std::max(worst, std::abs((u.sx + k * u.dsx - kBias) / kFix - mx[x]));
          worst = std::max(worst, std::abs((u.sy + k * u.dsy - kBias) / kFix - my[x]));
        }
      }
    }
    return worst;
  }

  void build(const cv::Mat& map_x, const cv::Mat& map_y, int w_px, int h_px) {
    width = w_px;
    height = h_px;
    for (int len : {16, 8, 4, 2, 1}) {
      max_error_px = set_runs(map_x, map_y, len);
      if (max_error_px <= kTolerancePx) break;
    }
    fixups.clear();
    for (int y = 0; y < height; ++y) {
      for (int x = 0; x < width; ++x) {
        const float sx = map_x.at<float>(y, x), sy = map_y.at<float>(y, x);
        const auto i = static_cast<uint32_t>(static_cast<size_t>(y) * width + x);
        if (outside(sx, sy, width, height)) {
          fixups.push_back({i, -1, -1, 0, 0});
          continue;
        }
        const Run& u = runs[static_cast<size_t>(y) * runs_per_row + x / run];
        const int k = x % run;
        if (safe((u.sx + k * u.dsx) >> 16, (u.sy + k * u.dsy) >> 16)) continue;
        // The exact source, clamped onto the image as bilinear sampling at its last row and column needs.
        int x0 = static_cast<int>(std::floor(sx)), y0 = static_cast<int>(std::floor(sy));
        int wx = static_cast<int>(std::lround((sx - x0) * kSteps)),
            wy = static_cast<int>(std::lround((sy - y0) * kSteps));
        if (wx == kSteps) ++x0, wx = 0;
        if (wy == kSteps) ++y0, wy = 0;
        if (x0 >= width - 1) x0 = width - 2, wx = kSteps;
        if (y0 >= height - 1) y0 = height - 2, wy = kSteps;
        fixups.push_back({i, x0, y0, static_cast<uint8_t>(wx), static_cast<uint8_t>(wy)});
      }
    }
  }

  // Whether the fast loop may sample at (x0, y0): inside, with a right and a
  // lower neighbour, and a four-byte read from the lower row inside the image.
  bool safe(int x0, int y0) const {
    return x0 >= 0 && y0 >= 0 && x0 <= width - 2 && y0 <= height - 2 && !(y0 == height - 2 && x0 > width - 4);
  }

  static uint8_t sample(const uint8_t* p, int s, int wx, int wy) {
    const int top = p[0] * kSteps + (p[1] - p[0]) * wx;
    const int bottom = p[s] * kSteps + (p[s + 1] - p[s]) * wx;
    return static_cast<uint8_t>((top * kSteps + (bottom - top) * wy + kSteps * kSteps / 2) >> 10);
  }

  void apply(const uint8_t* src, int stride, uint8_t* dst, bool vector_path) {
    // Offsets are clamped into the safe span so that a pixel due a fix-up never reads outside the image.
    const int32_t max_offset = (height - 2) * stride + width - 4;
    for (int y = 0; y < height; ++y) {
      const Run* row = &runs[static_cast<size_t>(y) * runs_per_row];
      uint8_t* out = dst + static_cast<size_t>(y) * width;
      for (int r = 0; r < runs_per_row; ++r) {
        const Run u = row[r];
        const int x0 = r * run, n = std::min(run, width - x0);
        int k = 0;
#if KESTREL_REMAP_AVX2
        if (vector_path && stride < 32768) k = run_avx2(src, stride, max_offset, u, out + x0, n);
#else
        (void)vector_path;
#endif
        for (; k < n; ++k) {
          const int32_t sx = u.sx + k * u.dsx, sy = u.sy + k * u.dsy;
          const int32_t off = std::min(std::max((sy >> 16) * stride + (sx >> 16), 0), max_offset);
          out[x0 + k] = sample(src + off, stride, (sx >> 11) & 31, (sy >> 11) & 31);
        }
      }
    }
    for (const Fixup& f : fixups) {
      dst[f.pixel] =
          f.x0 < 0 ? 0 : sample(src + static_cast<size_t>(f.y0) * stride + f.x0, stride, f.wx, f.wy);
    }
  }

#if KESTREL_REMAP_AVX2
  // Eight pixels of a run per step: two 32-bit gathers bring each pixel's top
  // and bottom neighbour pairs, and pairwise 16-bit multiply-adds do the
  // offset and both interpolations; returns how many pixels it did (a multiple
  // of 8). Needs stride < 32768 (the caller checks).
  __attribute__((target("avx2"))) static int run_avx2(const uint8_t* src, int stride, int32_t max_offset,
                                                      const Run& u, uint8_t* out, int n) {
    const __m256i m31 = _mm256_set1_epi32(31), steps = _mm256_set1_epi32(kSteps);
    const __m256i half = _mm256_set1_epi32(kSteps * kSteps / 2);
    // madd with (row | x << 16) gives row * stride + x.
    const __m256i stride_one = _mm256_set1_epi32(stride | 1 << 16);
    const __m256i vmax = _mm256_set1_epi32(max_offset), zero = _mm256_setzero_si256();
    // The two neighbours' bytes of each gathered word into 16-bit halves.
    const __m256i spread = _mm256_setr_epi8(0, -1, 1, -1, 4, -1, 5, -1, 8, -1, 9, -1, 12, -1, 13, -1, 0, -1,
                                            1, -1, 4, -1, 5, -1, 8, -1, 9, -1, 12, -1, 13, -1);
    const __m256i iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    const int* top_row = reinterpret_cast<const int*>(src);
    const int* bottom_row = reinterpret_cast<const int*>(src + stride);
    __m256i sx =
        _mm256_add_epi32(_mm256_set1_epi32(u.sx), _mm256_mullo_epi32(iota, _mm256_set1_epi32(u.dsx)));
    __m256i sy =
        _mm256_add_epi32(_mm256_set1_epi32(u.sy), _mm256_mullo_epi32(iota, _mm256_set1_epi32(u.dsy)));
    const __m256i dsx8 = _mm256_set1_epi32(8 * u.dsx), dsy8 = _mm256_set1_epi32(8 * u.dsy);
    int k = 0;
    for (; k + 8 <= n; k += 8, sx = _mm256_add_epi32(sx, dsx8), sy = _mm256_add_epi32(sy, dsy8)) {
      const __m256i row_x = _mm256_blend_epi16(_mm256_srai_epi32(sy, 16), sx, 0xAA);
      __m256i off = _mm256_madd_epi16(row_x, stride_one);
      off = _mm256_min_epi32(_mm256_max_epi32(off, zero), vmax);
      // (32 - w) | w << 16: the weights of the two neighbours of a pair.
      const __m256i wx = _mm256_and_si256(_mm256_srli_epi32(sx, 11), m31);
      const __m256i wy = _mm256_and_si256(_mm256_srli_epi32(sy, 11), m31);
      const __m256i pair_x = _mm256_sub_epi32(_mm256_add_epi32(_mm256_slli_epi32(wx, 16), steps), wx);
      const __m256i pair_y = _mm256_sub_epi32(_mm256_add_epi32(_mm256_slli_epi32(wy, 16), steps), wy);
      const __m256i t = _mm256_shuffle_epi8(_mm256_i32gather_epi32(top_row, off, 1), spread);
      const __m256i b = _mm256_shuffle_epi8(_mm256_i32gather_epi32(bottom_row, off, 1), spread);
      const __m256i top = _mm256_madd_epi16(t, pair_x), bot = _mm256_madd_epi16(b, pair_x);
      const __m256i sum = _mm256_madd_epi16(_mm256_or_si256(top, _mm256_slli_epi32(bot, 16)), pair_y);
      const __m256i r = _mm256_srli_epi32(_mm256_add_epi32(sum, half), 10);
      // Packing works within 128-bit lanes: bytes 0-3 hold pixels 0-3, bytes 16-19 pixels 4-7.
      const __m256i r16 = _mm256_packus_epi32(r, r);
      const __m256i r8 = _mm256_packus_epi16(r16, r16);
      const auto lo = static_cast<uint32_t>(_mm256_extract_epi32(r8, 0));
      const auto hi = static_cast<uint32_t>(_mm256_extract_epi32(r8, 4));
      std::memcpy(out + k, &lo, 4);
      std::memcpy(out + k + 4, &hi, 4);
    }
    return k;
  }
#endif
};

bool cpu_has_avx2() {
#if KESTREL_REMAP_AVX2
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2") != 0;
#else
  return false;
#endif
}

struct StereoRectifier::Impl {
  RemapRuns left, right;
  std::vector<uint8_t> gray_l, gray_r;  // raw colour converted to grey
  std::vector<uint8_t> out_l, out_r;
  int width = 0, height = 0;
  // The pair is rectified already (a D4xx IR pair, a ZED, the simulator's): no remap, only grey conversion.
  bool identity = false;
  bool vector_path = cpu_has_avx2();
};

StereoRectifier::StereoRectifier(const Rig& rig) : rectified_(rig), impl_(std::make_unique<Impl>()) {
  if (!rig.stereo.present)
    throw std::invalid_argument("stereo: the rig has no stereo: section (no right camera)");
  const CameraIntrinsics& k0 = rig.rgb;
  const CameraIntrinsics& k1 = rig.stereo.intrinsics;
  check_intrinsics(k0, "camera");
  check_intrinsics(k1, "stereo");
  if (k0.width != k1.width || k0.height != k1.height) {
    refuse("camera and stereo differ in size (" + std::to_string(k0.width) + "x" + std::to_string(k0.height) +
           " vs " + std::to_string(k1.width) + "x" + std::to_string(k1.height) + ")");
  }
  const bool fisheye0 = k0.distortion == DistortionModel::kEquidistant;
  const bool fisheye1 = k1.distortion == DistortionModel::kEquidistant;
  if (fisheye0 != fisheye1)
    refuse("camera.distortion and stereo.distortion differ (equidistant with another model)");

  // OpenCV's R, T map left-camera coordinates into the right camera: T_C1C0 = T_BC1^-1 T_BC0.
  const cv::Matx44d T_C1C0 = to_cv(rig.stereo.T_BC1).inv() * to_cv(rig.T_BC);
  cv::Matx33d R;
  cv::Vec3d t;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) R(r, c) = T_C1C0(r, c);
    t[r] = T_C1C0(r, 3);
  }
  for (double v : R.val)
    if (!std::isfinite(v)) refuse("T_BC or stereo.T_BC1 is not finite or not invertible");
  const double baseline = cv::norm(t);
  if (!(baseline > 1e-3))
    refuse("baseline " + std::to_string(baseline) + " m between T_BC and stereo.T_BC1 (< 1 mm)");
  // The optical axes must look roughly the same way for rows to be shared.
  const double axis_cos = R(2, 2);
  if (axis_cos < std::cos(45.0 * M_PI / 180.0))
    refuse("the cameras' optical axes differ by more than 45 degrees (T_BC vs stereo.T_BC1)");
  // The rectified rows run along the baseline: a pair stacked vertically would need a transposed search.
  if (std::abs(t[0]) < std::abs(t[1]))
    refuse("the baseline is vertical (right camera above or below the left)");

  const cv::Size size(k0.width, k0.height);
  if (size.width > 32767 || size.height > 32767) refuse("images wider or taller than 32767 px");
  const size_t px = static_cast<size_t>(size.width) * static_cast<size_t>(size.height);
  impl_->width = size.width;
  impl_->height = size.height;
  impl_->gray_l.resize(px);
  impl_->gray_r.resize(px);
  // Rectified already: equal pinhole cameras, parallel axes, the right one along the left one's +x.
  const double rot_err = cv::norm(cv::Mat(R) - cv::Mat(cv::Matx33d::eye()));
  if (k0.distortion == DistortionModel::kNone && k1.distortion == DistortionModel::kNone && k0.fx == k1.fx &&
      k0.fy == k1.fy && k0.cx == k1.cx && k0.cy == k1.cy && rot_err < 1e-9 &&
      std::abs(t[1]) < 1e-9 * baseline && std::abs(t[2]) < 1e-9 * baseline && t[0] < 0) {
    impl_->identity = true;
    rectified_.rgb.dist = {};
    rectified_.stereo.rectified = true;
    rectified_.stereo.baseline_m = -t[0];
    rectified_.depth_camera.present = false;
    return;
  }
  const cv::Matx33d K0 = camera_matrix(k0), K1 = camera_matrix(k1);
  const cv::Mat D0 = dist_coeffs(k0), D1 = dist_coeffs(k1);
  cv::Mat R0, R1, P0, P1, Q, lx, ly, rx, ry;
  try {
    if (fisheye0) {
      cv::fisheye::stereoRectify(K0, D0, K1, D1, size, R, t, R0, R1, P0, P1, Q, cv::CALIB_ZERO_DISPARITY,
                                 size, 0.0, 1.0);
      cv::fisheye::initUndistortRectifyMap(K0, D0, R0, P0(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, lx, ly);
      cv::fisheye::initUndistortRectifyMap(K1, D1, R1, P1(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, rx, ry);
    } else {
      // alpha 0: only valid pixels, so no black border makes false corners.
      cv::stereoRectify(K0, D0, K1, D1, size, R, t, R0, R1, P0, P1, Q, cv::CALIB_ZERO_DISPARITY, 0.0, size);
      cv::initUndistortRectifyMap(K0, D0, R0, P0(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, lx, ly);
      cv::initUndistortRectifyMap(K1, D1, R1, P1(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, rx, ry);
    }
  } catch (const cv::Exception& e) {
    refuse(std::string("OpenCV: ") + e.what());
  }
  const double f = P0.at<double>(0, 0);
  const double b = -P1.at<double>(0, 3) / P1.at<double>(0, 0);
  if (!(std::isfinite(f) && f > 0 && std::isfinite(b))) refuse("the rectified projection is not finite");
  // With the right camera on the left of the left one, disparities would be negative.
  if (!(b > 0)) refuse("stereo.T_BC1 puts the right camera to the left of camera (swap cam0 and cam1)");

  CameraIntrinsics& k = rectified_.rgb;
  k.fx = f;
  k.fy = P0.at<double>(1, 1);
  k.cx = P0.at<double>(0, 2);
  k.cy = P0.at<double>(1, 2);
  k.distortion = DistortionModel::kNone;
  k.dist = {};
  // The rectified left camera: p_R0 = R0 p_C0, so T_B,R0 = T_BC0 * [R0^T].
  cv::Matx44d T_C0R0 = cv::Matx44d::eye();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) T_C0R0(r, c) = R0.at<double>(c, r);
  const cv::Matx44d T_BR0 = to_cv(rig.T_BC) * T_C0R0;
  for (int i = 0; i < 16; ++i) rectified_.T_BC[static_cast<size_t>(i)] = T_BR0.val[i];
  rectified_.stereo.rectified = true;
  rectified_.stereo.baseline_m = b;
  rectified_.depth_camera.present = false;

  impl_->left.build(lx, ly, size.width, size.height);
  impl_->right.build(rx, ry, size.width, size.height);
  impl_->out_l.resize(px);
  impl_->out_r.resize(px);
}

StereoRectifier::~StereoRectifier() = default;

bool StereoRectifier::vector_path() const { return impl_->vector_path; }

void StereoRectifier::set_vector_path(bool enabled) { impl_->vector_path = enabled && cpu_has_avx2(); }

namespace {

// The view's grey pixels: the view itself, or its colour converted into `gray`
// (BT.601 weights in 1/256). Null when refused (size or format).
const uint8_t* grey_of(const ImageView& v, int width, int height, std::vector<uint8_t>& gray, int* stride) {
  if (v.data == nullptr || v.width != width || v.height != height) return nullptr;
  if (v.format == PixelFormat::kGray8) {
    *stride = v.stride_bytes;
    return v.data;
  }
  if (v.format != PixelFormat::kRgb8 && v.format != PixelFormat::kBgr8) return nullptr;
  luma_plane(v, gray.data(), width);
  *stride = width;
  return gray.data();
}

}  // namespace

bool StereoRectifier::rectify(const ImageView& left, const ImageView& right, ImageView* left_out,
                              ImageView* right_out) {
  Impl& m = *impl_;
  *left_out = ImageView{};
  *right_out = ImageView{};
  int stride = 0;
  const uint8_t* l = grey_of(left, m.width, m.height, m.gray_l, &stride);
  if (l == nullptr) {
    ++refused_;
    return false;
  }
  if (m.identity) {
    *left_out = ImageView{m.width, m.height, stride, PixelFormat::kGray8, l};
  } else {
    m.left.apply(l, stride, m.out_l.data(), m.vector_path);
    *left_out = ImageView{m.width, m.height, m.width, PixelFormat::kGray8, m.out_l.data()};
  }
  if (right.data != nullptr) {
    const uint8_t* r = grey_of(right, m.width, m.height, m.gray_r, &stride);
    if (r == nullptr) {
      ++refused_;
    } else {
      if (m.identity) {
        *right_out = ImageView{m.width, m.height, stride, PixelFormat::kGray8, r};
      } else {
        m.right.apply(r, stride, m.out_r.data(), m.vector_path);
        *right_out = ImageView{m.width, m.height, m.width, PixelFormat::kGray8, m.out_r.data()};
      }
    }
  }
  return true;
}

}  // namespace kestrel::drivers

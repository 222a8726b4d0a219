// Stages of the ORB extractor (see orb_detail.hpp). Written out here rather
// than calling OpenCV because cv:: functions may allocate internally and the
// tracking thread must not.
#include "kestrel/core/orb_detail.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>

#include "simd.hpp"

namespace kestrel::core::orb_detail {

namespace {
constexpr double kPi = 3.14159265358979323846;
constexpr float kPiF = static_cast<float>(kPi);
std::atomic<bool> g_vector_paths{true};
}  // namespace

bool vector_paths() { return KESTREL_ORB_SIMD && g_vector_paths.load(std::memory_order_relaxed); }
void set_vector_paths(bool on) { g_vector_paths.store(on, std::memory_order_relaxed); }
const char* vector_isa() {
#if KESTREL_ORB_SIMD && CV_NEON
  return "NEON";
#elif KESTREL_ORB_SIMD && CV_SSE2
  return "SSE2";
#elif KESTREL_ORB_SIMD
  return "128-bit";
#else
  return "none";
#endif
}

std::array<int, 16> fast_circle_offsets(int stride) {
  static constexpr int kCircle[16][2] = {{0, -3}, {1, -3},  {2, -2},  {3, -1}, {3, 0},  {3, 1},
                                         {2, 2},  {1, 3},   {0, 3},   {-1, 3}, {-2, 2}, {-3, 1},
                                         {-3, 0}, {-3, -1}, {-2, -2}, {-1, -3}};
  std::array<int, 16> off{};
  for (int i = 0; i < 16; ++i) off[i] = kCircle[i][1] * stride + kCircle[i][0];
  return off;
}

int fast_score(const uint8_t* p, const std::array<int, 16>& offsets) {
  // d > 0: circle pixel darker than the centre. A darker arc survives every
  // threshold below its smallest d, a brighter arc every threshold below its
  // smallest -d; the score is the best arc's margin minus one (strict test).
  int d[25];
  const int c = p[0];
  for (int i = 0; i < 16; ++i) d[i] = c - p[offsets[i]];
  for (int i = 16; i < 25; ++i) d[i] = d[i - 16];
  int best = 0;
  for (int k = 0; k < 16; ++k) {
    int mn = d[k];
    int mx = d[k];
    for (int j = 1; j < 9; ++j) {
      mn = std::min(mn, d[k + j]);
      mx = std::max(mx, d[k + j]);
    }
    best = std::max(best, std::max(mn, -mx));
  }
  return best - 1;
}

// ---- area resampling -------------------------------------------------------------

namespace {

// Overlap of input pixel j = [j, j+1) with [a, b), as 8-bit fixed-point
// weights of three consecutive input pixels that sum to exactly 256.
void make_area_taps(int n_src, int n_dst, AreaTap* tab) {
  const double r = static_cast<double>(n_src) / n_dst;
  for (int i = 0; i < n_dst; ++i) {
    const double a = i * r;
    const double b = std::min((i + 1) * r, static_cast<double>(n_src));
    int first = static_cast<int>(std::floor(a));
    double w[3];
    for (int k = 0; k < 3; ++k) {
      const double lo = std::max(a, static_cast<double>(first + k));
      const double hi = std::min(b, static_cast<double>(first + k + 1));
      w[k] = std::max(0.0, hi - lo) / (b - a);
    }
    // Keep the three taps inside the input: slide the window left, shifting
    // weights right (the taps that fall outside have zero weight).
    int shift = std::max(0, first + 2 - (n_src - 1));
    shift = std::min(shift, first);
    first -= shift;
    double ws[3] = {0, 0, 0};
    for (int k = 0; k < 3; ++k)
      if (k + shift < 3) ws[k + shift] = w[k];
    AreaTap& t = tab[i];
    t.first = first;
    int sum = 0;
    int arg_max = 0;
    for (int k = 0; k < 3; ++k) {
      t.w[k] = static_cast<uint16_t>(std::lround(ws[k] * 256.0));
      sum += t.w[k];
      if (ws[k] > ws[arg_max]) arg_max = k;
    }
    t.w[arg_max] = static_cast<uint16_t>(t.w[arg_max] + (256 - sum));
  }
}

}  // namespace

namespace {

// out[x] = (sum_i w[i] * rows[i][x] + 128) >> 8 over n rows, weights summing
// to 256: every partial sum fits 16 bits, so the vector path runs 16 pixels
// per step and the scalar tail gives bit-identical results.
template <int N>
void weighted_rows(const uint8_t* const* rows, const uint16_t* w, uint8_t* out, int n) {
  int x = 0;
#if KESTREL_ORB_SIMD
  if (vector_paths()) {
    const cv::v_uint16x8 half = cv::v_setall_u16(128);
    cv::v_uint16x8 wv[N];
    for (int i = 0; i < N; ++i) wv[i] = cv::v_setall_u16(w[i]);
    for (; x + 16 <= n; x += 16) {
      cv::v_uint16x8 lo = half;
      cv::v_uint16x8 hi = half;
      for (int i = 0; i < N; ++i) {
        cv::v_uint16x8 a, b;
        cv::v_expand(cv::v_load(rows[i] + x), a, b);
        lo = cv::v_add_wrap(lo, cv::v_mul_wrap(a, wv[i]));
        hi = cv::v_add_wrap(hi, cv::v_mul_wrap(b, wv[i]));
      }
      cv::v_store(out + x, cv::v_pack(lo >> 8, hi >> 8));
    }
  }
#endif
  for (; x < n; ++x) {
    uint32_t acc = 128;
    for (int i = 0; i < N; ++i) acc += w[i] * rows[i][x];
    out[x] = static_cast<uint8_t>(acc >> 8);
  }
}

}  // namespace

std::size_t area_resize_tmp_bytes(int src_width, int dst_width) {
  // Scalar: one row. Vector: 16 rows, their transpose, and the transposed output.
  return 16 * (2 * static_cast<std::size_t>(src_width) + static_cast<std::size_t>(dst_width));
}

namespace {

#if KESTREL_ORB_SIMD
// A 16x16 byte block transposed: four rounds of interleaving row i with row
// i + 8 (SSE2's unpack, NEON's zip) carry element (r, c) to (c, r).
inline void transpose16x16(const uint8_t* src, int src_stride, uint8_t* dst, int dst_stride) {
  cv::v_uint8x16 r[16], a[16];
  auto round = [](const cv::v_uint8x16* in, cv::v_uint8x16* out) {
#pragma GCC unroll 8
    for (int i = 0; i < 8; ++i) cv::v_zip(in[i], in[i + 8], out[2 * i], out[2 * i + 1]);
  };
#pragma GCC unroll 16
  for (int i = 0; i < 16; ++i) r[i] = cv::v_load(src + i * src_stride);
  round(r, a);
  round(a, r);
  round(r, a);
  round(a, r);
#pragma GCC unroll 16
  for (int i = 0; i < 16; ++i) cv::v_store(dst + i * dst_stride, r[i]);
}

// rows x cols bytes (both >= 16), the ragged edges as blocks overlapping the
// previous ones (rewriting identical values).
void transpose(const uint8_t* src, int src_stride, int rows, int cols, uint8_t* dst, int dst_stride) {
  for (int y0 = 0; y0 < rows; y0 += 16) {
    const int y = std::min(y0, rows - 16);
    for (int x0 = 0; x0 < cols; x0 += 16) {
      const int x = std::min(x0, cols - 16);
      transpose16x16(src + y * src_stride + x, src_stride, dst + x * dst_stride + y, dst_stride);
    }
  }
}

// area_resize 16 output rows at a time. The horizontal taps read scattered
// pixels, which SSE2 cannot gather; transposed, 16 rows' worth of one column
// is a vector, so the horizontal pass becomes the same contiguous weighted sum
// as the vertical one, with the same rounding (bit for bit the scalar result).
void area_resize_vector(Plane src, MutPlane dst, uint8_t* tmp, const AreaTap* xtab, const AreaTap* ytab) {
  const int sw = src.width;
  uint8_t* rows16 = tmp;              // 16 x sw: vertically resampled
  uint8_t* cols16 = tmp + 16 * sw;    // sw x 16: the same, transposed
  uint8_t* out16 = cols16 + 16 * sw;  // dst.width x 16: resampled, transposed
  const cv::v_uint16x8 half = cv::v_setall_u16(128);
  for (int j0 = 0; j0 < dst.height; j0 += 16) {
    const int j = std::min(j0, dst.height - 16);
    for (int r = 0; r < 16; ++r) {
      const AreaTap& tp = ytab[j + r];
      const uint8_t* rows[3] = {src.at(0, tp.first), src.at(0, tp.first + 1), src.at(0, tp.first + 2)};
      weighted_rows<3>(rows, tp.w.data(), rows16 + r * sw, sw);
    }
    transpose(rows16, sw, 16, sw, cols16, 16);
    for (int i = 0; i < dst.width; ++i) {
      const AreaTap& t = xtab[i];
      const uint8_t* c = cols16 + t.first * 16;
      cv::v_uint16x8 lo = half, hi = half;
      for (int k = 0; k < 3; ++k) {
        cv::v_uint16x8 a, b;
        cv::v_expand(cv::v_load(c + 16 * k), a, b);
        const cv::v_uint16x8 w = cv::v_setall_u16(t.w[k]);
        lo = cv::v_add_wrap(lo, cv::v_mul_wrap(a, w));
        hi = cv::v_add_wrap(hi, cv::v_mul_wrap(b, w));
      }
      cv::v_store(out16 + i * 16, cv::v_pack(lo >> 8, hi >> 8));
    }
    transpose(out16, 16, dst.width, 16, dst.at(0, j), dst.stride);
  }
}
#endif

}  // namespace

void area_resize(Plane src, MutPlane dst, uint8_t* tmp, AreaTap* xtab, AreaTap* ytab) {
  make_area_taps(src.width, dst.width, xtab);
  make_area_taps(src.height, dst.height, ytab);
#if KESTREL_ORB_SIMD
  if (vector_paths() && src.width >= 16 && dst.width >= 16 && dst.height >= 16) {
    area_resize_vector(src, dst, tmp, xtab, ytab);
    return;
  }
#endif
  // Vertical first: contiguous in x (SIMD), then the horizontal 3-tap gather
  // on the already shorter set of rows.
  for (int j = 0; j < dst.height; ++j) {
    const AreaTap& tp = ytab[j];
    const uint8_t* rows[3] = {src.at(0, tp.first), src.at(0, tp.first + 1), src.at(0, tp.first + 2)};
    weighted_rows<3>(rows, tp.w.data(), tmp, src.width);
    uint8_t* d = dst.at(0, j);
    for (int i = 0; i < dst.width; ++i) {
      const AreaTap& t = xtab[i];
      const uint8_t* q = tmp + t.first;
      d[i] = static_cast<uint8_t>((t.w[0] * q[0] + t.w[1] * q[1] + t.w[2] * q[2] + 128) >> 8);
    }
  }
}

// ---- Gaussian blur ----------------------------------------------------------------

std::array<uint16_t, 2 * kBlurRadius + 1> gaussian_kernel7() {
  constexpr double kSigma = 2.0;
  double g[2 * kBlurRadius + 1];
  double sum = 0;
  for (int i = -kBlurRadius; i <= kBlurRadius; ++i) {
    g[i + kBlurRadius] = std::exp(-(i * i) / (2 * kSigma * kSigma));
    sum += g[i + kBlurRadius];
  }
  std::array<uint16_t, 2 * kBlurRadius + 1> k{};
  int isum = 0;
  for (int i = 0; i < 2 * kBlurRadius + 1; ++i) {
    k[i] = static_cast<uint16_t>(std::lround(256.0 * g[i] / sum));
    isum += k[i];
  }
  k[kBlurRadius] = static_cast<uint16_t>(k[kBlurRadius] + (256 - isum));  // exact unit gain
  return k;
}

void gaussian_blur7(Plane src, MutPlane dst, uint8_t* tmp) {
  static const std::array<uint16_t, 2 * kBlurRadius + 1> k = gaussian_kernel7();
  const int w = src.width;
  const int h = src.height;
  const int R = kBlurRadius;
  // Vertical pass (rows clamped at the borders) into tmp, 8-bit rounded:
  // half a grey level of error, invisible to BRIEF's comparisons, and it keeps
  // both passes in 16-bit SIMD lanes.
  for (int y = 0; y < h; ++y) {
    const uint8_t* rows[2 * R + 1];
    for (int i = -R; i <= R; ++i) rows[i + R] = src.at(0, std::clamp(y + i, 0, h - 1));
    weighted_rows<2 * R + 1>(rows, k.data(), tmp + static_cast<std::ptrdiff_t>(y) * w, w);
  }
  // Horizontal pass: the interior reads shifted row pointers; the R columns
  // at each side replicate the border.
  for (int y = 0; y < h; ++y) {
    const uint8_t* t = tmp + static_cast<std::ptrdiff_t>(y) * w;
    uint8_t* d = dst.at(0, y);
    auto clamped = [&](int x) {
      uint32_t acc = 128;
      for (int i = -R; i <= R; ++i) acc += k[i + R] * t[std::clamp(x + i, 0, w - 1)];
      return static_cast<uint8_t>(acc >> 8);
    };
    const int lo = std::min(R, w);
    const int hi = std::max(lo, w - R);
    for (int x = 0; x < lo; ++x) d[x] = clamped(x);
    if (hi > lo) {
      const uint8_t* shifted[2 * R + 1];
      for (int i = 0; i < 2 * R + 1; ++i) shifted[i] = t + lo + i - R;
      weighted_rows<2 * R + 1>(shifted, k.data(), d + lo, hi - lo);
    }
    for (int x = hi; x < w; ++x) d[x] = clamped(x);
  }
}

namespace {

// (k3 * c + k2 * (a2 + b2) + k1 * (a1 + b1) + k0 * (a0 + b0) + 128) >> 8 on
// 16-bit lanes: the kernel is symmetric, so three of its seven products are
// folded away. Sums of two pixels times a weight can exceed 16 bits, but the
// whole sum cannot (weights sum to 256), so wrapping arithmetic is exact.
#if KESTREL_ORB_SIMD
inline cv::v_uint16x8 blur_taps(const cv::v_uint16x8* r, const cv::v_uint16x8* k) {
  cv::v_uint16x8 acc = cv::v_mul_wrap(r[3], k[3]) + cv::v_setall_u16(128);
  acc = cv::v_add_wrap(acc, cv::v_mul_wrap(cv::v_add_wrap(r[2], r[4]), k[2]));
  acc = cv::v_add_wrap(acc, cv::v_mul_wrap(cv::v_add_wrap(r[1], r[5]), k[1]));
  acc = cv::v_add_wrap(acc, cv::v_mul_wrap(cv::v_add_wrap(r[0], r[6]), k[0]));
  return acc >> 8;
}
#endif

}  // namespace

void gaussian_blur7_patch(Plane src, int cx, int cy, uint8_t* out, uint8_t* tmp) {
  static const std::array<uint16_t, 2 * kBlurRadius + 1> k = gaussian_kernel7();
  const int R = kBlurRadius;
  const int P = kPatternRadius;
  constexpr int kOut = kBriefPatchSide;
  constexpr int kIn = kOut + 2 * R;  // columns the horizontal pass reads
  const int h = src.height;
  // Vertical pass over the patch's columns plus the horizontal support, rows
  // clamped as gaussian_blur7 clamps them; the columns need no clamping
  // (the caller keeps the patch kBriefPatchMargin inside the image), so every
  // value is the one gaussian_blur7 computes.
  const uint8_t* rows[kOut + 2 * R];
  for (int i = 0; i < kOut + 2 * R; ++i) rows[i] = src.at(cx - P - R, std::clamp(cy - P - R + i, 0, h - 1));
#if KESTREL_ORB_SIMD
  static_assert(kIn > 16 && kOut > 16 && kIn <= 48 && kOut <= 32,
                "the column blocks below assume these sizes");
  if (vector_paths()) {
    static_assert(kBlurRadius == 3, "blur_taps is the 7-tap kernel");
    cv::v_uint16x8 kv[2 * R + 1];
    for (int i = 0; i <= 2 * R; ++i) kv[i] = cv::v_setall_u16(k[i]);
    // Down each 16-column block, every source row is widened once and used
    // by the seven output rows it reaches; the last block overlaps the one
    // before it and rewrites identical values.
    for (const int x : {0, 16, kIn - 16}) {
      cv::v_uint16x8 lo[2 * R + 1], hi[2 * R + 1];
      for (int i = 0; i < 2 * R; ++i) cv::v_expand(cv::v_load(rows[i] + x), lo[i + 1], hi[i + 1]);
      for (int j = 0; j < kOut; ++j) {
#pragma GCC unroll 6
        for (int i = 0; i < 2 * R; ++i) {
          lo[i] = lo[i + 1];
          hi[i] = hi[i + 1];
        }
        cv::v_expand(cv::v_load(rows[j + 2 * R] + x), lo[2 * R], hi[2 * R]);
        cv::v_store(tmp + j * kIn + x, cv::v_pack(blur_taps(lo, kv), blur_taps(hi, kv)));
      }
    }
    for (int j = 0; j < kOut; ++j) {
      const uint8_t* t = tmp + j * kIn;
      for (const int x : {0, kOut - 16}) {
        cv::v_uint16x8 lo[2 * R + 1], hi[2 * R + 1];
        for (int i = 0; i <= 2 * R; ++i) cv::v_expand(cv::v_load(t + x + i), lo[i], hi[i]);
        cv::v_store(out + j * kOut + x, cv::v_pack(blur_taps(lo, kv), blur_taps(hi, kv)));
      }
    }
    return;
  }
#endif
  for (int j = 0; j < kOut; ++j) {
    for (int x = 0; x < kIn; ++x) {
      uint32_t acc = 128;
      for (int i = 0; i <= 2 * R; ++i) acc += k[i] * rows[j + i][x];
      tmp[j * kIn + x] = static_cast<uint8_t>(acc >> 8);
    }
  }
  for (int j = 0; j < kOut; ++j) {
    for (int x = 0; x < kOut; ++x) {
      uint32_t acc = 128;
      for (int i = 0; i <= 2 * R; ++i) acc += k[i] * tmp[j * kIn + x + i];
      out[j * kOut + x] = static_cast<uint8_t>(acc >> 8);
    }
  }
}

// ---- orientation ---------------------------------------------------------------------

std::array<int, kPatchRadius + 1> patch_umax() {
  std::array<int, kPatchRadius + 1> umax{};
  const int r2 = kPatchRadius * kPatchRadius + kPatchRadius;
  for (int v = 0; v <= kPatchRadius; ++v) {
    int u = 0;
    while ((u + 1) * (u + 1) + v * v <= r2) ++u;
    umax[v] = u;
  }
  return umax;
}

namespace {

// atan2(m01, m10) in [0, 2pi).
float moments_angle(int m10, int m01) {
  float ang = std::atan2(static_cast<float>(m01), static_cast<float>(m10));
  if (ang < 0) ang += 2.0f * kPiF;
  if (ang >= 2.0f * kPiF) ang = 0.0f;  // float rounding of -tiny + 2pi
  return ang;
}

}  // namespace

float ic_angle(Plane img, int x, int y, const std::array<int, kPatchRadius + 1>& umax) {
  const uint8_t* c = img.at(x, y);
  const int stride = img.stride;
  int m10 = 0;
  int m01 = 0;
#if KESTREL_ORB_SIMD
  if (vector_paths()) {
    static_assert(kPatchRadius == 15, "the 32 lanes below cover u = -15 .. 16");
    // u = -15 .. 16 as four 8-lane vectors; each row pair is masked to |u| <=
    // umax[v]. Products fit 16 bits (16 * 510), and pmaddwd-style dot
    // products sum them in 32: the same integers as the scalar loop, so the
    // same angle. Reads c - 15 .. c + 16, inside the image for a keypoint at
    // least kMinEdgeMargin (16) from the border.
    cv::v_int16x8 uv[4];
    for (int q = 0; q < 4; ++q) {
      uv[q] = cv::v_int16x8(static_cast<int16_t>(8 * q - 15), static_cast<int16_t>(8 * q - 14),
                            static_cast<int16_t>(8 * q - 13), static_cast<int16_t>(8 * q - 12),
                            static_cast<int16_t>(8 * q - 11), static_cast<int16_t>(8 * q - 10),
                            static_cast<int16_t>(8 * q - 9), static_cast<int16_t>(8 * q - 8));
    }
    auto widen = [](const uint8_t* p, cv::v_int16x8* out) {
      cv::v_uint16x8 a, b, e, f;
      cv::v_expand(cv::v_load(p), a, b);
      cv::v_expand(cv::v_load(p + 16), e, f);
      out[0] = cv::v_reinterpret_as_s16(a);
      out[1] = cv::v_reinterpret_as_s16(b);
      out[2] = cv::v_reinterpret_as_s16(e);
      out[3] = cv::v_reinterpret_as_s16(f);
    };
    cv::v_int32x4 acc10 = cv::v_setzero_s32(), acc01 = cv::v_setzero_s32();
    for (int v = 0; v <= kPatchRadius; ++v) {
      const cv::v_int16x8 d = cv::v_setall_s16(static_cast<int16_t>(umax[v]));
      const cv::v_int16x8 nd = cv::v_setall_s16(static_cast<int16_t>(-umax[v]));
      const cv::v_int16x8 vv = cv::v_setall_s16(static_cast<int16_t>(v));
      cv::v_int16x8 below[4], above[4];
      widen(c + v * stride - kPatchRadius, below);
      if (v == 0) {
        for (int q = 0; q < 4; ++q) above[q] = cv::v_setzero_s16();
      } else {
        widen(c - v * stride - kPatchRadius, above);
      }
      for (int q = 0; q < 4; ++q) {
        const cv::v_int16x8 inside = ~((uv[q] > d) | (uv[q] < nd));
        acc10 += cv::v_dotprod((below[q] + above[q]) & inside, uv[q]);
        acc01 += cv::v_dotprod((below[q] - above[q]) & inside, vv);
      }
    }
    m10 = cv::v_reduce_sum(acc10);
    m01 = cv::v_reduce_sum(acc01);
    return moments_angle(m10, m01);
  }
#endif
  for (int u = -kPatchRadius; u <= kPatchRadius; ++u) m10 += u * c[u];
  for (int v = 1; v <= kPatchRadius; ++v) {
    int v_sum = 0;
    const int d = umax[v];
    const uint8_t* below = c + v * stride;
    const uint8_t* above = c - v * stride;
    for (int u = -d; u <= d; ++u) {
      const int b = below[u];
      const int a = above[u];
      v_sum += b - a;
      m10 += u * (b + a);
    }
    m01 += v * v_sum;
  }
  return moments_angle(m10, m01);
}

// ---- BRIEF ------------------------------------------------------------------------------

namespace {

// splitmix64: tiny, and its output is fixed by its definition, unlike
// std::normal_distribution, whose values differ between standard libraries;
// the pattern (and so every stored descriptor) must not depend on the toolchain.
struct SplitMix64 {
  uint64_t s;
  uint64_t next() {
    uint64_t z = (s += 0x9e3779b97f4a7c15ULL);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
    return z ^ (z >> 31);
  }
  double uniform01() { return (static_cast<double>(next() >> 11) + 0.5) * (1.0 / 9007199254740992.0); }
};

}  // namespace

BriefPattern make_brief_pattern(uint64_t seed) {
  SplitMix64 rng{seed};
  constexpr double kSigma = kPatchDiameter / 5.0;  // BRIEF G II: sigma^2 = S^2 / 25
  constexpr int kR2 = kPatternRadius * kPatternRadius;
  auto gauss_point = [&](int8_t& px, int8_t& py) {
    for (;;) {
      // Box-Muller: two independent N(0, 1).
      const double u1 = rng.uniform01();
      const double u2 = rng.uniform01();
      const double m = std::sqrt(-2.0 * std::log(u1));
      const int x = static_cast<int>(std::lround(kSigma * m * std::cos(2.0 * kPi * u2)));
      const int y = static_cast<int>(std::lround(kSigma * m * std::sin(2.0 * kPi * u2)));
      if (x * x + y * y <= kR2) {
        px = static_cast<int8_t>(x);
        py = static_cast<int8_t>(y);
        return;
      }
    }
  };
  BriefPattern pat{};
  for (int i = 0; i < kBriefPairs;) {
    auto& p = pat[i];
    gauss_point(p[0], p[1]);
    gauss_point(p[2], p[3]);
    if (p[0] == p[2] && p[1] == p[3]) continue;  // a test against itself carries no bit
    bool dup = false;
    for (int j = 0; j < i && !dup; ++j) dup = pat[j] == p;
    if (!dup) ++i;
  }
  return pat;
}

BriefPoints brief_points(const BriefPattern& pattern) {
  BriefPoints p;
  for (int i = 0; i < 2 * kBriefPairs; ++i) {
    p.x[i] = pattern[i / 2][2 * (i % 2)];
    p.y[i] = pattern[i / 2][2 * (i % 2) + 1];
  }
  return p;
}

OrbDescriptor brief_describe(Plane blurred, int x, int y, float angle_rad, const BriefPattern& pattern) {
  return brief_describe(blurred, x, y, angle_rad, brief_points(pattern));
}

OrbDescriptor brief_describe(Plane blurred, int x, int y, float angle_rad, const BriefPoints& points) {
  const float c = std::cos(angle_rad);
  const float s = std::sin(angle_rad);
  const uint8_t* center = blurred.at(x, y);
  const int stride = blurred.stride;
  // Byte offsets of the rotated test points. Rotation by the keypoint angle in
  // image axes: the same rotation that carries the patch content, so the
  // tests follow the content. Rounded to nearest (ties to even, as the vector
  // conversion does; the scalar path matches it).
  alignas(16) int32_t off[2 * kBriefPairs];
  int i = 0;
#if KESTREL_ORB_SIMD
  if (vector_paths()) {
    const cv::v_float32x4 cv4 = cv::v_setall_f32(c), sv4 = cv::v_setall_f32(s),
                          stv = cv::v_setall_f32(static_cast<float>(stride));
    for (; i + 4 <= 2 * kBriefPairs; i += 4) {
      const cv::v_float32x4 px = cv::v_load_aligned(points.x.data() + i);
      const cv::v_float32x4 py = cv::v_load_aligned(points.y.data() + i);
      const cv::v_int32x4 rx = cv::v_round(cv4 * px - sv4 * py);
      const cv::v_int32x4 ry = cv::v_round(sv4 * px + cv4 * py);
      // ry * stride + rx, exactly, in float (|values| << 2^24).
      cv::v_store_aligned(off + i, cv::v_round(cv::v_cvt_f32(ry) * stv + cv::v_cvt_f32(rx)));
    }
  }
#endif
  for (; i < 2 * kBriefPairs; ++i) {
    const float px = points.x[i], py = points.y[i];
    const int rx = static_cast<int>(std::nearbyint(c * px - s * py));
    const int ry = static_cast<int>(std::nearbyint(s * px + c * py));
    off[i] = ry * stride + rx;
  }
  OrbDescriptor d{};
  for (int w = 0; w < 4; ++w) {
    uint64_t bits = 0;
    const int32_t* o = off + w * 128;
    for (int b = 0; b < 64; ++b) bits |= static_cast<uint64_t>(center[o[2 * b]] < center[o[2 * b + 1]]) << b;
    d[w] = bits;
  }
  return d;
}

}  // namespace kestrel::core::orb_detail

// OrbExtractor: pyramid -> FAST-9 with score -> 3x3 NMS -> grid bucketing ->
// intensity-centroid orientation -> steered BRIEF on a blurred level.
// All memory comes from the constructor (docs/orb.md, "Memory").
#include "kestrel/core/orb.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <sstream>
#include <stdexcept>

#include "kestrel/core/orb_detail.hpp"
#include "kestrel/pixels.hpp"
#include "simd.hpp"

namespace kestrel::core {

static_assert(OrbOptions::kMinEdgeMargin >= orb_detail::kBriefPatchMargin,
              "a keypoint's blurred BRIEF patch must fit inside the level");

using orb_detail::MutPlane;
using orb_detail::Plane;

// ---- options -------------------------------------------------------------------------

std::string OrbOptions::validate() const {
  std::ostringstream e;
  if (n_features < 1 || n_features > 100000) e << "n_features: " << n_features << " not in [1, 100000]\n";
  if (n_levels < 1 || n_levels > kMaxLevels)
    e << "n_levels: " << n_levels << " not in [1, " << kMaxLevels << "]\n";
  if (!(scale_factor > 1.0f && scale_factor <= 2.0f))
    e << "scale_factor: " << scale_factor << " not in (1, 2] (area resampling uses 3 taps)\n";
  if (fast_threshold < 1 || fast_threshold > 254)
    e << "fast_threshold: " << fast_threshold << " not in [1, 254]\n";
  if (fast_threshold_min < 1 || fast_threshold_min > fast_threshold)
    e << "fast_threshold_min: " << fast_threshold_min << " not in [1, fast_threshold]\n";
  if (edge_margin < kMinEdgeMargin || edge_margin > 1000) {
    e << "edge_margin: " << edge_margin << " not in [" << kMinEdgeMargin
      << ", 1000] (orientation patch radius 15 + 1)\n";
  }
  if (cell_size < 8 || cell_size > 4096) e << "cell_size: " << cell_size << " not in [8, 4096]\n";
  return e.str();
}

std::string OrbOptions::to_string() const {
  std::ostringstream s;
  s << "n_features: " << n_features << "\n"
    << "n_levels: " << n_levels << "\n"
    << "scale_factor: " << scale_factor << "\n"
    << "fast_threshold: " << fast_threshold << "\n"
    << "fast_threshold_min: " << fast_threshold_min << "\n"
    << "edge_margin_px: " << edge_margin << "\n"
    << "cell_size_px: " << cell_size << "\n"
    << "pattern_seed: 0x" << std::hex << pattern_seed << std::dec << "\n";
  return s.str();
}

const char* to_string(OrbStatus s) {
  switch (s) {
    case OrbStatus::kOk:
      return "ok";
    case OrbStatus::kNullImage:
      return "null or inconsistent image (data, width, height, stride)";
    case OrbStatus::kUnsupportedFormat:
      return "unsupported pixel format (Gray8, Rgb8, Bgr8 only)";
    case OrbStatus::kImageTooLarge:
      return "image larger than the extractor's preallocated maximum";
    case OrbStatus::kOutputTooSmall:
      return "OrbFeatures capacity below n_features";
  }
  return "unknown";
}

// ---- OrbFeatures ------------------------------------------------------------------------

void OrbFeatures::reserve(int capacity) {
  capacity = std::max(capacity, 0);
  kp_ = std::make_unique<OrbKeypoint[]>(static_cast<std::size_t>(capacity));
  desc_ = std::make_unique<OrbDescriptor[]>(static_cast<std::size_t>(capacity));
  capacity_ = capacity;
  size_ = 0;
}

OrbFeatures::OrbFeatures(const OrbFeatures& o) { *this = o; }

OrbFeatures& OrbFeatures::operator=(const OrbFeatures& o) {
  if (this == &o) return *this;
  if (capacity_ < o.size_) reserve(o.capacity_);
  std::copy(o.kp_.get(), o.kp_.get() + o.size_, kp_.get());
  std::copy(o.desc_.get(), o.desc_.get() + o.size_, desc_.get());
  size_ = o.size_;
  return *this;
}

bool OrbFeatures::push_back(const OrbKeypoint& kp, const OrbDescriptor& d) noexcept {
  if (size_ >= capacity_) return false;
  kp_[size_] = kp;
  desc_[size_] = d;
  ++size_;
  return true;
}

// ---- extractor ----------------------------------------------------------------------------

namespace {

struct Cand {
  uint16_t x;
  uint16_t y;
  uint16_t score;  // FAST score
  uint16_t cell;
};

// Strongest first; position breaks ties so the selection is the same on every
// standard library (nth_element is then deterministic).
inline bool by_fast(const Cand& a, const Cand& b) {
  if (a.score != b.score) return a.score > b.score;
  if (a.y != b.y) return a.y < b.y;
  return a.x < b.x;
}

// Smallest per-cell quota q with sum_c min(e[c], q) >= want (want <= sum e).
int water_level(const int32_t* e, int n, int want) {
  int lo = 1;
  int hi = 1;
  for (int c = 0; c < n; ++c) hi = std::max(hi, e[c]);
  while (lo < hi) {
    const int mid = (lo + hi) / 2;
    long s = 0;
    for (int c = 0; c < n; ++c) s += std::min(e[c], mid);
    if (s >= want) {
      hi = mid;
    } else {
      lo = mid + 1;
    }
  }
  return lo;
}

template <class T>
std::unique_ptr<T[]> alloc(std::size_t n) {
  return std::make_unique<T[]>(std::max<std::size_t>(n, 1));
}

int level_dim(int dim0, double scale) { return static_cast<int>(std::lround(dim0 / scale)); }

}  // namespace

struct OrbExtractor::Impl {
  // Level 0 grey (used only for colour input; grey input is read in place).
  std::unique_ptr<uint8_t[]> gray0;
  std::array<std::unique_ptr<uint8_t[]>, OrbOptions::kMaxLevels> level_buf;  // levels >= 1
  std::array<uint8_t, orb_detail::kBriefPatchSide * orb_detail::kBriefPatchSide> brief_patch{};
  std::array<uint8_t, orb_detail::kBriefPatchSide*(orb_detail::kBriefPatchSide + 2 * orb_detail::kBlurRadius)>
      brief_tmp{};
  std::unique_ptr<uint8_t[]> tmp8;  // area resampling's work space (area_resize_tmp_bytes)
  std::unique_ptr<orb_detail::AreaTap[]> xtab, ytab;
  std::unique_ptr<uint8_t[]> score_rows;    // 3-row ring for NMS
  std::unique_ptr<uint16_t[]> corner_cols;  // corners per ring row (x positions)
  std::array<int, 3> corner_count{};
  std::unique_ptr<Cand[]> cand, cand_sorted;
  std::size_t cand_capacity = 0;
  std::unique_ptr<int32_t[]> cell_all, cell_strong, cell_start, cell_take;
  std::unique_ptr<Cand[]> qth;  // the q-th best of each cell, for the remainder
  std::size_t max_cells = 0;
  std::unique_ptr<Cand[]> selected;
  orb_detail::BriefPoints pattern{};
  std::array<int, orb_detail::kPatchRadius + 1> umax{};
  std::size_t bytes = 0;

  // FAST corners at threshold t with 3x3 NMS, keypoint positions restricted
  // to [kx0, kx1] x [ky0, ky1]; appends to cand from n_cand on and returns the
  // new count. corners/overflow are incremented.
  int detect(Plane img, int kx0, int kx1, int ky0, int ky1, int t, int n_cand, int& corners, int& overflow);
};

OrbExtractor::OrbExtractor(const OrbOptions& opt, int max_width, int max_height) : opt_(opt) {
  const std::string err = opt.validate();
  if (!err.empty()) throw std::invalid_argument("OrbOptions: " + err);
  if (max_width < 1 || max_height < 1 || max_width > 16384 || max_height > 16384) {
    throw std::invalid_argument("OrbExtractor: max image size " + std::to_string(max_width) + "x" +
                                std::to_string(max_height) + " not in [1, 16384]^2");
  }
  max_w_ = max_width;
  max_h_ = max_height;

  // Budget per level: geometric in 1/s (a level's area shrinks by s^2, its
  // ring of features at a given density by about s), as ORB-SLAM does.
  const double f = 1.0 / opt.scale_factor;
  const double first = opt.n_features * (1.0 - f) / (1.0 - std::pow(f, opt.n_levels));
  int sum = 0;
  for (int l = 0; l < opt.n_levels; ++l) {
    level_scale_[l] = static_cast<float>(std::pow(static_cast<double>(opt.scale_factor), l));
    if (l + 1 < opt.n_levels) {
      level_budget_[l] = static_cast<int>(std::lround(first * std::pow(f, l)));
      sum += level_budget_[l];
    } else {
      level_budget_[l] = std::max(0, opt.n_features - sum);
    }
  }

  impl_ = std::make_unique<Impl>();
  Impl& m = *impl_;
  const std::size_t area0 = static_cast<std::size_t>(max_width) * max_height;
  m.gray0 = alloc<uint8_t>(area0);
  m.bytes += area0;
  for (int l = 1; l < opt.n_levels; ++l) {
    const std::size_t a = static_cast<std::size_t>(level_dim(max_width, level_scale_[l])) *
                          static_cast<std::size_t>(level_dim(max_height, level_scale_[l]));
    m.level_buf[l] = alloc<uint8_t>(a);
    m.bytes += a;
  }
  const std::size_t tmp_bytes = orb_detail::area_resize_tmp_bytes(max_width, max_width);
  m.tmp8 = alloc<uint8_t>(tmp_bytes);
  m.xtab = alloc<orb_detail::AreaTap>(max_width);
  m.ytab = alloc<orb_detail::AreaTap>(max_height);
  m.score_rows = alloc<uint8_t>(3 * static_cast<std::size_t>(max_width));
  m.corner_cols = alloc<uint16_t>(3 * static_cast<std::size_t>(max_width));
  // 3x3 NMS with a strict tie-break keeps no two 8-neighbours, so at most one
  // candidate per 2x2 block of the keypoint area, searched once: this is the
  // worst case, not a guess.
  m.cand_capacity =
      static_cast<std::size_t>((max_width + 1) / 2) * static_cast<std::size_t>((max_height + 1) / 2);
  m.cand = alloc<Cand>(m.cand_capacity);
  m.cand_sorted = alloc<Cand>(m.cand_capacity);
  m.max_cells = static_cast<std::size_t>(max_width / opt.cell_size + 2) *
                static_cast<std::size_t>(max_height / opt.cell_size + 2);
  if (m.max_cells > 65535) {
    throw std::invalid_argument("OrbExtractor: " + std::to_string(m.max_cells) +
                                " grid cells exceed 65535; raise cell_size");
  }
  m.cell_all = alloc<int32_t>(m.max_cells);
  m.cell_strong = alloc<int32_t>(m.max_cells);
  m.cell_start = alloc<int32_t>(m.max_cells + 1);
  m.cell_take = alloc<int32_t>(m.max_cells);
  m.qth = alloc<Cand>(m.max_cells);
  m.selected = alloc<Cand>(static_cast<std::size_t>(opt.n_features));
  m.bytes += tmp_bytes + sizeof(m.brief_patch) + sizeof(m.brief_tmp) +
             (max_width + max_height) * sizeof(orb_detail::AreaTap) +
             3 * static_cast<std::size_t>(max_width) * (1 + sizeof(uint16_t)) +
             2 * m.cand_capacity * sizeof(Cand) + m.max_cells * (4 * sizeof(int32_t) + sizeof(Cand)) +
             opt.n_features * sizeof(Cand);
  m.pattern = orb_detail::brief_points(orb_detail::make_brief_pattern(opt.pattern_seed));
  m.umax = orb_detail::patch_umax();
}

OrbExtractor::~OrbExtractor() = default;

std::size_t OrbExtractor::buffer_bytes() const noexcept { return impl_->bytes; }

namespace {

// Segment test only (no score): 9 contiguous set bits in a circular 16-bit mask.
inline bool has_arc9(uint32_t m16) {
  const uint32_t x = m16 | (m16 << 16);
  uint32_t r = x & (x >> 1);  // runs >= 2
  r &= r >> 2;                // >= 4
  r &= r >> 4;                // >= 8
  r &= x >> 8;                // >= 9
  return r != 0;
}

inline bool fast_segment_test(const uint8_t* p, const std::array<int, 16>& off, int t) {
  const int c = p[0];
  const int hi = c + t;
  const int lo = c - t;
  uint32_t bright = 0;
  uint32_t dark = 0;
  for (int i = 0; i < 16; ++i) {
    const int v = p[off[i]];
    bright |= static_cast<uint32_t>(v > hi) << i;
    dark |= static_cast<uint32_t>(v < lo) << i;
  }
  return has_arc9(bright) || has_arc9(dark);
}

#if KESTREL_ORB_SIMD
// Per lane, the best 9-pixel arc's smallest entry among the 16 circle
// differences d (saturated, so >= 0). Two arcs share their middle eight
// (k+1 .. k+8), which keeps the live registers few enough not to spill on
// SSE2's sixteen.
inline cv::v_uint8x16 best_arc9(const cv::v_uint8x16* d) {
  cv::v_uint8x16 best = cv::v_setzero_u8();
  // Unrolled so the circular indices are constants, not arithmetic.
#pragma GCC unroll 8
  for (int k = 0; k < 16; k += 2) {
    cv::v_uint8x16 mid = cv::v_min(d[(k + 1) & 15], d[(k + 2) & 15]);
#pragma GCC unroll 6
    for (int j = 3; j <= 8; ++j) mid = cv::v_min(mid, d[(k + j) & 15]);
    best = cv::v_max(best, cv::v_max(cv::v_min(mid, d[k]), cv::v_min(mid, d[(k + 9) & 15])));
  }
  return best;
}

// FAST scores + 1 of 16 pixels at p (0 where the prefilter already rules a
// corner out), for blocks with a pixel through the first prefilter stage. On
// saturated differences the best arc's smallest entry is fast_score + 1, so
// one computation gives both the segment test (> t) and the score, with no
// scalar scoring of the corners. Out of line: it runs for a minority of
// blocks and its register use would slow the prefilter loop.
// b, dk: stage one's bright and dark survivors (non-zero lanes), narrowed here.
__attribute__((noinline)) cv::v_uint8x16 fast_scores16(const uint8_t* p, const std::array<int, 16>& off,
                                                       cv::v_uint8x16 tv, cv::v_uint8x16 b,
                                                       cv::v_uint8x16 dk) {
  const cv::v_uint8x16 v = cv::v_load(p);
  const cv::v_uint8x16 hi = v + tv;
  const cv::v_uint8x16 lo = v - tv;
  const cv::v_uint8x16 zero = cv::v_setzero_u8();
  auto pair = [&](int k) {
    const cv::v_uint8x16 c0 = cv::v_load(p + off[k]);
    const cv::v_uint8x16 c1 = cv::v_load(p + off[k + 8]);
    b = cv::v_min(b, (c0 - hi) | (c1 - hi));
    dk = cv::v_min(dk, (lo - c0) | (lo - c1));
  };
  auto none = [&] { return cv::v_check_all((b | dk) == zero); };
  pair(2);
  pair(6);
  if (none()) return zero;
  pair(1);
  pair(3);
  pair(5);
  pair(7);
  if (none()) return zero;
  // A lane can pass the test on one side only (two 9-arcs of 16 overlap), so
  // a side no lane is still a candidate for cannot change a corner's score.
  cv::v_uint8x16 best = zero;
  cv::v_uint8x16 d[16];
  if (!cv::v_check_all(b == zero)) {
#pragma GCC unroll 16
    for (int k = 0; k < 16; ++k) d[k] = cv::v_load(p + off[k]) - v;
    best = best_arc9(d);
  }
  if (!cv::v_check_all(dk == zero)) {
#pragma GCC unroll 16
    for (int k = 0; k < 16; ++k) d[k] = v - cv::v_load(p + off[k]);
    best = cv::v_max(best, best_arc9(d));
  }
  return best;
}
#endif

}  // namespace

int OrbExtractor::Impl::detect(Plane img, int kx0, int kx1, int ky0, int ky1, int t, int n_cand, int& corners,
                               int& overflow) {
  const int w = img.width;
  const auto off = orb_detail::fast_circle_offsets(img.stride);
  // Scores are computed one pixel beyond the keypoint area so a corner on the
  // area's rim is still suppressed by a stronger neighbour outside it (the
  // edge margin keeps that pixel's circle inside the image).
  const int x0 = kx0 - 1;
  const int x1 = kx1 + 1;  // inclusive
  const int y0 = ky0 - 1;
  const int y1 = ky1 + 1;

  for (int y = y0; y <= y1; ++y) {
    const int ring = y % 3;
    uint8_t* srow = score_rows.get() + static_cast<std::size_t>(ring) * w;
    uint16_t* ccols = corner_cols.get() + static_cast<std::size_t>(ring) * w;
    int nc = 0;
#if KESTREL_ORB_SIMD
    const cv::v_uint8x16 tv = cv::v_setall_u8(static_cast<uint8_t>(t));
    const cv::v_uint8x16 zero = cv::v_setzero_u8();
    const cv::v_uint8x16 one = cv::v_setall_u8(1);
    // Lanes of the block at xb whose pixel may become a keypoint (the rim
    // columns x0 and x1 are scored for NMS only).
    auto area_lanes = [&](int xb) {
      unsigned m = 0xffffu;
      if (xb < kx0) m &= 0xffffu << (kx0 - xb);
      if (xb + 15 > kx1) m &= 0xffffu >> (xb + 15 - kx1);
      return m & 0xffffu;
    };
#endif
    std::memset(srow + x0, 0, static_cast<std::size_t>(x1 - x0 + 1));
    const uint8_t* row = img.at(0, y);

    auto corner = [&](int x) {
      const uint8_t* p = row + x;
      const int s = orb_detail::fast_score(p, off);
      srow[x] = static_cast<uint8_t>(std::clamp(s, 1, 255));
      ++corners;
      if (x >= kx0 && x <= kx1) ccols[nc++] = static_cast<uint16_t>(x);
    };
    auto check = [&](int x) {
      if (fast_segment_test(row + x, off, t)) corner(x);
    };

    int x = x0;
#if KESTREL_ORB_SIMD
    // Prefilter 16 pixels at once. A 9-pixel arc contains at least one pixel
    // of every opposite pair (k, k+8), so a corner needs, for all 8 pairs, one
    // of the two beyond the threshold on the same side. Tested in three
    // stages; nearly all pixels drop out in the first. A lane is "set" while
    // its byte is non-zero: saturating differences (u8 - and + saturate in
    // the universal intrinsics) OR as "either", min as "both".
    // Stage one inline (pairs (0, 8) and (4, 12)), the rest out of line.
    const int o0 = off[0], o4 = off[4], o8 = off[8], o12 = off[12];
    auto block = [&](int xb, unsigned lanes) __attribute__((always_inline)) {
      const uint8_t* p = row + xb;
      const cv::v_uint8x16 v = cv::v_load(p);
      const cv::v_uint8x16 hi = v + tv;
      const cv::v_uint8x16 lo = v - tv;
      const cv::v_uint8x16 c0 = cv::v_load(p + o0), c4 = cv::v_load(p + o4);
      const cv::v_uint8x16 c8 = cv::v_load(p + o8), c12 = cv::v_load(p + o12);
      const cv::v_uint8x16 b = cv::v_min((c0 - hi) | (c8 - hi), (c4 - hi) | (c12 - hi));
      const cv::v_uint8x16 d = cv::v_min((lo - c0) | (lo - c8), (lo - c4) | (lo - c12));
      if (cv::v_check_all((b | d) == zero)) return;
      const cv::v_uint8x16 best = fast_scores16(p, off, tv, b, d);
      const cv::v_uint8x16 is_corner = best > tv;
      // Overlapping lanes of a ragged end are rewritten with the same values.
      cv::v_store(srow + xb, (best - one) & is_corner);
      const unsigned mask = static_cast<unsigned>(cv::v_signmask(is_corner)) & lanes;
      if (mask == 0) return;
      corners += popcount64(mask);
      for (unsigned m = mask & area_lanes(xb); m != 0; m &= m - 1)
        ccols[nc++] = static_cast<uint16_t>(xb + __builtin_ctz(m));
    };
    if (orb_detail::vector_paths()) {
      for (; x + 15 <= x1; x += 16) block(x, 0xffffu);
      // The ragged end as one more block overlapping the last, with the lanes
      // already done masked off (small grid cells would otherwise spend most
      // of their time in the scalar loop).
      if (x <= x1 && x1 - x0 + 1 >= 16) {
        const int xb = x1 - 15;
        block(xb, (0xffffu << (x - xb)) & 0xffffu);
        x = x1 + 1;
      }
    }
#endif
    for (; x <= x1; ++x) check(x);
    corner_count[ring] = nc;

    // NMS on the previous row, now that its lower neighbours are scored.
    const int yc = y - 1;
    if (yc < ky0 || yc > ky1) continue;
    const int rc = yc % 3;
    const uint8_t* sp = score_rows.get() + static_cast<std::size_t>((yc + 2) % 3) * w;  // row yc-1
    const uint8_t* sc = score_rows.get() + static_cast<std::size_t>(rc) * w;
    const uint8_t* sn = srow;  // row yc+1
    const uint16_t* cols = corner_cols.get() + static_cast<std::size_t>(rc) * w;
    for (int i = 0; i < corner_count[rc]; ++i) {
      const int cx = cols[i];
      const int s = sc[cx];
      // Earlier neighbours (raster order) must be strictly weaker, later ones
      // not stronger: on a plateau the first pixel wins, and no two
      // 8-neighbours ever both survive.
      if (sp[cx - 1] >= s || sp[cx] >= s || sp[cx + 1] >= s || sc[cx - 1] >= s) continue;
      if (sc[cx + 1] > s || sn[cx - 1] > s || sn[cx] > s || sn[cx + 1] > s) continue;
      if (static_cast<std::size_t>(n_cand) >= cand_capacity) {
        ++overflow;
        continue;
      }
      cand[n_cand++] =
          Cand{static_cast<uint16_t>(cx), static_cast<uint16_t>(yc), static_cast<uint16_t>(s), 0};
    }
  }
  return n_cand;
}

OrbStatus OrbExtractor::extract(const ImageView& image, OrbFeatures& out) noexcept {
  out.clear();
  stats_ = OrbExtractStats{};
  if (image.data == nullptr || image.width <= 0 || image.height <= 0) return OrbStatus::kNullImage;
  if (image.format != PixelFormat::kGray8 && image.format != PixelFormat::kRgb8 &&
      image.format != PixelFormat::kBgr8)
    return OrbStatus::kUnsupportedFormat;
  const int bpp = bytes_per_pixel(image.format);
  if (image.stride_bytes < image.width * bpp) return OrbStatus::kNullImage;
  if (image.width > max_w_ || image.height > max_h_) return OrbStatus::kImageTooLarge;
  if (out.capacity() < opt_.n_features) return OrbStatus::kOutputTooSmall;

  Impl& m = *impl_;
  const int w0 = image.width;
  const int h0 = image.height;

  // Level 0: grey input is used in place; colour is converted (BT.601 luma,
  // 8-bit fixed point) into the preallocated buffer.
  Plane level{};
  if (image.format == PixelFormat::kGray8) {
    level = Plane{image.data, w0, h0, image.stride_bytes};
  } else {
    luma_plane(image, m.gray0.get(), w0);
    level = Plane{m.gray0.get(), w0, h0, w0};
  }

  const int margin = opt_.edge_margin;
  const int min_dim = 2 * margin + 1;
  int carry = 0;
  for (int l = 0; l < opt_.n_levels; ++l) {
    if (l > 0) {
      const int wl = level_dim(w0, level_scale_[l]);
      const int hl = level_dim(h0, level_scale_[l]);
      if (wl < min_dim || hl < min_dim) break;  // higher levels are smaller still
      MutPlane dst{m.level_buf[l].get(), wl, hl, wl};
      orb_detail::area_resize(level, dst, m.tmp8.get(), m.xtab.get(), m.ytab.get());
      level = dst.view();
    } else if (w0 < min_dim || h0 < min_dim) {
      break;
    }
    stats_.n_levels_used = l + 1;
    const int budget = level_budget_[l] + carry;
    stats_.budget[l] = budget;
    const int wl = level.width;
    const int hl = level.height;
    // Exact level-0 scale of this level (sizes are rounded, so not quite s^l).
    const float sx = static_cast<float>(w0) / wl;
    const float sy = static_cast<float>(h0) / hl;

    // ---- detection, then bucketing by a counting sort over grid cells ----
    const int kx1 = wl - 1 - margin;
    const int ky1 = hl - 1 - margin;
    const int rw = wl - 2 * margin;
    const int rh = hl - 2 * margin;
    const int nx = std::max(1, (rw + opt_.cell_size / 2) / opt_.cell_size);
    const int ny = std::max(1, (rh + opt_.cell_size / 2) / opt_.cell_size);
    const int cw = (rw + nx - 1) / nx;
    const int ch = (rh + ny - 1) / ny;
    const int n_cells = nx * ny;
    int32_t* all = m.cell_all.get();
    int32_t* strong = m.cell_strong.get();
    int32_t* start = m.cell_start.get();
    int32_t* take = m.cell_take.get();
    auto count_cells = [&](int n) {
      std::fill(all, all + n_cells, 0);
      std::fill(strong, strong + n_cells, 0);
      for (int i = 0; i < n; ++i) {
        Cand& c = m.cand[i];
        const int cx = std::min((c.x - margin) / cw, nx - 1);
        const int cy = std::min((c.y - margin) / ch, ny - 1);
        c.cell = static_cast<uint16_t>(cy * nx + cx);
        ++all[c.cell];
        if (c.score >= opt_.fast_threshold) ++strong[c.cell];
      }
    };
    int corners = 0;
    int overflow = 0;
    int n_cand = m.detect(level, margin, kx1, margin, ky1, opt_.fast_threshold, 0, corners, overflow);
    count_cells(n_cand);
    // ORB-SLAM's fallback: cells left empty at fast_threshold are searched
    // again at fast_threshold_min, so low-contrast regions still get features
    // without paying for the low threshold over the whole image.
    int weak_cells = 0;
    if (opt_.fast_threshold_min < opt_.fast_threshold) {
      for (int c = 0; c < n_cells; ++c) {
        if (all[c] > 0) continue;
        const int cx = c % nx;
        const int cy = c / nx;
        const int x_lo = margin + cx * cw;
        const int y_lo = margin + cy * ch;
        const int x_hi = std::min(x_lo + cw - 1, kx1);
        const int y_hi = std::min(y_lo + ch - 1, ky1);
        if (x_lo > x_hi || y_lo > y_hi) continue;
        const int before = n_cand;
        n_cand = m.detect(level, x_lo, x_hi, y_lo, y_hi, opt_.fast_threshold_min, n_cand, corners, overflow);
        weak_cells += n_cand > before ? 1 : 0;
      }
      count_cells(n_cand);
    }
    stats_.corners[l] = corners;
    stats_.candidates[l] = n_cand;
    stats_.candidate_overflow[l] = overflow;
    stats_.weak_cells[l] = weak_cells;

    start[0] = 0;
    for (int c = 0; c < n_cells; ++c) start[c + 1] = start[c] + all[c];
    std::copy(start, start + n_cells, take);  // reused as scatter cursor
    for (int i = 0; i < n_cand; ++i) m.cand_sorted[take[m.cand[i].cell]++] = m.cand[i];

    // Strong corners where a cell has any, its weak ones only where it has
    // none; everything found if that cannot meet the budget.
    int32_t* expose = take;
    long total = 0;
    for (int c = 0; c < n_cells; ++c) total += (expose[c] = strong[c] > 0 ? strong[c] : all[c]);
    if (total < budget) {
      total = 0;
      for (int c = 0; c < n_cells; ++c) total += (expose[c] = all[c]);
    }

    int n_sel = 0;
    Cand* sel = m.selected.get();
    const int want = static_cast<int>(std::min<long>(budget, total));
    if (want > 0) {
      const int q = water_level(expose, n_cells, want);
      // Every cell gives its best q-1; the remainder comes from the cells'
      // q-th best, strongest first.
      int n_qth = 0;
      for (int c = 0; c < n_cells; ++c) {
        const int e = expose[c];
        if (e == 0) continue;
        Cand* b = m.cand_sorted.get() + start[c];
        if (e >= q) {
          std::nth_element(b, b + (q - 1), b + all[c], by_fast);
          m.qth[n_qth++] = b[q - 1];
        } else if (e < all[c]) {
          std::nth_element(b, b + e, b + all[c], by_fast);  // the strong ones first
        }
        const int k = std::min(e, q - 1);
        for (int i = 0; i < k; ++i) sel[n_sel++] = b[i];
      }
      const int rest = want - n_sel;
      if (rest > 0) {
        std::nth_element(m.qth.get(), m.qth.get() + std::min(rest, n_qth), m.qth.get() + n_qth, by_fast);
        for (int i = 0; i < rest && i < n_qth; ++i) sel[n_sel++] = m.qth[i];
      }
      std::sort(sel, sel + n_sel, by_fast);
    }
    stats_.selected[l] = n_sel;
    carry = budget - n_sel;
    if (n_sel == 0) continue;

    // ---- orientation and descriptor ----
    for (int i = 0; i < n_sel; ++i) {
      const Cand& c = sel[i];
      OrbKeypoint kp;
      kp.x_level = static_cast<int16_t>(c.x);
      kp.y_level = static_cast<int16_t>(c.y);
      kp.level = static_cast<int16_t>(l);
      kp.x = (c.x + 0.5f) * sx - 0.5f;
      kp.y = (c.y + 0.5f) * sy - 0.5f;
      kp.response = c.score;
      kp.size = orb_detail::kPatchDiameter * level_scale_[l];
      kp.angle_rad = orb_detail::ic_angle(level, c.x, c.y, m.umax);
      // Only the patch BRIEF reads is blurred: a few hundred keypoints cover a
      // small part of a level (docs/orb.md, "Time per frame").
      orb_detail::gaussian_blur7_patch(level, c.x, c.y, m.brief_patch.data(), m.brief_tmp.data());
      constexpr int kSide = orb_detail::kBriefPatchSide;
      const Plane patch{m.brief_patch.data(), kSide, kSide, kSide};
      const OrbDescriptor d = orb_detail::brief_describe(patch, orb_detail::kPatternRadius,
                                                         orb_detail::kPatternRadius, kp.angle_rad, m.pattern);
      if (!out.push_back(kp, d)) break;  // cannot happen: capacity >= n_features checked above
    }
  }
  return OrbStatus::kOk;
}

// ---- matching (tests/tools) ----------------------------------------------------------------------

std::vector<OrbMatch> match_brute_force(const OrbDescriptor* query, int n_query, const OrbDescriptor* train,
                                        int n_train, float ratio, int max_distance) {
  std::vector<OrbMatch> matches;
  matches.reserve(static_cast<std::size_t>(std::max(0, n_query)));
  for (int i = 0; i < n_query; ++i) {
    BestTwoMatches m;
    for (int j = 0; j < n_train; ++j) m.offer(hamming_distance(query[i], train[j]), j);
    if (m.best_index < 0 || m.best > max_distance) continue;
    // With a single train descriptor there is no second: accept on distance.
    if (!m.passes_ratio(ratio)) continue;
    matches.push_back(OrbMatch{i, m.best_index, m.best});
  }
  return matches;
}

}  // namespace kestrel::core

// ORB extractor on synthetic images whose answer is known: rectangle corners,
// rotated analytic textures, blank and odd-sized frames, and the
// no-allocation guarantee of extract().
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <bitset>
#include <cmath>
#include <cstring>
#include <random>
#include <utility>
#include <vector>

#include "kestrel/core/orb.hpp"
#include "kestrel/core/orb_detail.hpp"
#include "kestrel/rt/alloc_counter.hpp"

using namespace kestrel;
using namespace kestrel::core;

namespace {

constexpr double kPi = 3.14159265358979323846;

struct Image {
  int w = 0, h = 0, ch = 1, stride = 0;
  std::vector<uint8_t> px;
  Image(int w_, int h_, int ch_ = 1, int pad = 0, uint8_t fill = 0)
      : w(w_), h(h_), ch(ch_), stride(w_ * ch_ + pad), px(static_cast<std::size_t>(stride) * h_, fill) {}
  uint8_t& at(int x, int y, int c = 0) { return px[static_cast<std::size_t>(y) * stride + x * ch + c]; }
  ImageView view(PixelFormat f = PixelFormat::kGray8) const { return ImageView{w, h, stride, f, px.data()}; }
  orb_detail::Plane plane() const { return orb_detail::Plane{px.data(), w, h, stride}; }
};

// A smooth random scene, defined everywhere so that rotated copies can be
// rendered exactly (no resampling error in the test itself).
struct BlobScene {
  struct Blob {
    double x, y, sigma, amp;
  };
  std::vector<Blob> blobs;
  double base = 110;
  BlobScene(uint32_t seed, double cx, double cy, double radius, int n) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> u(-1, 1), s(2.5, 7.0), a(-90, 90);
    for (int i = 0; i < n; ++i) blobs.push_back({cx + radius * u(rng), cy + radius * u(rng), s(rng), a(rng)});
  }
  double operator()(double x, double y) const {
    double v = base;
    for (const auto& b : blobs) {
      const double dx = x - b.x, dy = y - b.y;
      v += b.amp * std::exp(-(dx * dx + dy * dy) / (2 * b.sigma * b.sigma));
    }
    return std::clamp(v, 0.0, 255.0);
  }
  // The scene turned by phi (image axes) about (cx, cy): content at q moves
  // to c + R(phi) (q - c).
  Image render(int w, int h, double cx, double cy, double phi) const {
    Image im(w, h);
    const double c = std::cos(phi), s = std::sin(phi);
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        const double dx = x - cx, dy = y - cy;
        im.at(x, y) = static_cast<uint8_t>(std::lround((*this)(cx + c * dx + s * dy, cy - s * dx + c * dy)));
      }
    return im;
  }
};

Image noise_image(int w, int h, uint32_t seed, int blur_passes = 1) {
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> u(0, 255);
  std::vector<int> v(static_cast<std::size_t>(w) * h);
  for (auto& x : v) x = u(rng);
  // A little smoothing so corners are corners, not single-pixel noise.
  for (int p = 0; p < blur_passes; ++p) {
    std::vector<int> o(v.size());
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        int s = 0, n = 0;
        for (int dy = -1; dy <= 1; ++dy)
          for (int dx = -1; dx <= 1; ++dx) {
            const int xx = x + dx, yy = y + dy;
            if (xx < 0 || yy < 0 || xx >= w || yy >= h) continue;
            s += v[static_cast<std::size_t>(yy) * w + xx];
            ++n;
          }
        o[static_cast<std::size_t>(y) * w + x] = s / n;
      }
    v.swap(o);
  }
  Image im(w, h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) im.at(x, y) = static_cast<uint8_t>(v[static_cast<std::size_t>(y) * w + x]);
  return im;
}

double angle_diff(double a, double b) {
  double d = std::fmod(a - b, 2 * kPi);
  if (d > kPi) d -= 2 * kPi;
  if (d < -kPi) d += 2 * kPi;
  return d;
}

constexpr double kCornerTol = 2.5;  // px, see DetectsRectangleCornersAtTheRightPlaces

struct Corner {
  int x, y;
};

void fill_rect(Image& im, int x0, int y0, int x1, int y1, uint8_t v) {
  for (int y = y0; y < y1; ++y)
    for (int x = x0; x < x1; ++x) im.at(x, y) = v;
}

std::vector<Corner> rect_corners(int x0, int y0, int x1, int y1) {
  return {{x0, y0}, {x1 - 1, y0}, {x0, y1 - 1}, {x1 - 1, y1 - 1}};
}

double nearest(const OrbFeatures& f, double x, double y) {
  double best = 1e9;
  for (int i = 0; i < f.size(); ++i)
    best = std::min(best, std::hypot(f.keypoint(i).x - x, f.keypoint(i).y - y));
  return best;
}

}  // namespace

// ---- options --------------------------------------------------------------------------

TEST(OrbOptions, DefaultsValidAndPrinted) {
  OrbOptions o;
  EXPECT_EQ(o.validate(), "");
  const std::string s = o.to_string();
  for (const char* key : {"n_features: 300", "n_levels: 4", "scale_factor: 1.2", "fast_threshold: 20",
                          "fast_threshold_min: 7", "edge_margin_px: 16", "cell_size_px: 40", "pattern_seed"})
    EXPECT_NE(s.find(key), std::string::npos) << key;
}

TEST(OrbOptions, RejectsBadValuesNamingTheField) {
  OrbOptions o;
  o.n_levels = 0;
  o.scale_factor = 2.5f;
  o.fast_threshold_min = 30;
  o.edge_margin = 5;
  const std::string e = o.validate();
  EXPECT_NE(e.find("n_levels"), std::string::npos);
  EXPECT_NE(e.find("scale_factor"), std::string::npos);
  EXPECT_NE(e.find("fast_threshold_min"), std::string::npos);
  EXPECT_NE(e.find("edge_margin"), std::string::npos);
  EXPECT_THROW(OrbExtractor(o, 640, 480), std::invalid_argument);
  EXPECT_THROW(OrbExtractor(OrbOptions{}, 0, 480), std::invalid_argument);
}

TEST(OrbExtractor, LevelBudgetsAreGeometricAndSumToTotal) {
  OrbExtractor ex(OrbOptions{}, 752, 480);
  int sum = 0;
  for (int l = 0; l < 4; ++l) {
    sum += ex.level_budget(l);
    if (l > 0) {
      EXPECT_NEAR(static_cast<double>(ex.level_budget(l)) / ex.level_budget(l - 1), 1 / 1.2, 0.03);
      EXPECT_NEAR(ex.level_scale(l), std::pow(1.2, l), 1e-4);
    }
  }
  EXPECT_EQ(sum, 300);
}

// ---- FAST -------------------------------------------------------------------------------

TEST(OrbFast, ScoreIsLargestPassingThreshold) {
  Image im(16, 16, 1, 0, 100);
  const auto off = orb_detail::fast_circle_offsets(im.stride);
  uint8_t* c = &im.at(8, 8);
  EXPECT_EQ(orb_detail::fast_score(c, off), -1);  // flat: not a corner even at t = 0
  // 9 contiguous circle pixels darker by 30..50, the rest equal to the centre.
  for (int i = 0; i < 9; ++i) c[off[(i + 5) % 16]] = static_cast<uint8_t>(100 - 30 - 2 * i);
  EXPECT_EQ(orb_detail::fast_score(c, off), 29);  // the arc's weakest pixel differs by 30
  // Only 8 contiguous: not a corner.
  c[off[(8 + 5) % 16]] = 100;
  EXPECT_EQ(orb_detail::fast_score(c, off), -1);
  // Brighter arc of 12.
  for (int i = 0; i < 16; ++i) c[off[i]] = 100;
  for (int i = 0; i < 12; ++i) c[off[(i + 10) % 16]] = 160;
  EXPECT_EQ(orb_detail::fast_score(c, off), 59);
}

TEST(OrbFast, DetectsRectangleCornersAtTheRightPlaces) {
  Image im(320, 200, 1, 0, 40);
  std::vector<Corner> truth;
  fill_rect(im, 50, 40, 130, 110, 200);
  fill_rect(im, 180, 60, 270, 160, 120);
  for (auto c : rect_corners(50, 40, 130, 110)) truth.push_back(c);
  for (auto c : rect_corners(180, 60, 270, 160)) truth.push_back(c);
  OrbOptions o;
  o.n_levels = 1;
  OrbExtractor ex(o, 320, 200);
  OrbFeatures f(o.n_features);
  ASSERT_EQ(ex.extract(im.view(), f), OrbStatus::kOk);
  // On an ideal step corner the FAST score is flat along the inner diagonal
  // for a couple of pixels; NMS keeps the first of that plateau, so up to
  // 2 px from the geometric corner.
  for (const auto& c : truth) EXPECT_LE(nearest(f, c.x, c.y), kCornerTol) << "corner " << c.x << "," << c.y;
  // Nothing on edges or flat areas.
  for (int i = 0; i < f.size(); ++i) {
    double best = 1e9;
    for (const auto& c : truth)
      best = std::min<double>(best, std::hypot(f.keypoint(i).x - c.x, f.keypoint(i).y - c.y));
    EXPECT_LE(best, kCornerTol) << "spurious keypoint at " << f.keypoint(i).x << "," << f.keypoint(i).y;
  }
  EXPECT_EQ(f.size(), 8);
}

TEST(OrbFast, LowContrastCellsFallBackToMinThreshold) {
  // Strong corners on the left, contrast-12 corners (score 11) on the right,
  // in grid cells of their own.
  Image im(320, 160, 1, 0, 100);
  fill_rect(im, 40, 50, 100, 110, 220);
  fill_rect(im, 200, 50, 280, 110, 112);
  OrbOptions o;
  o.n_levels = 1;
  OrbFeatures f(o.n_features);
  {
    OrbExtractor ex(o, 320, 160);
    ASSERT_EQ(ex.extract(im.view(), f), OrbStatus::kOk);
    for (auto c : rect_corners(200, 50, 280, 110)) EXPECT_LE(nearest(f, c.x, c.y), kCornerTol);
    EXPECT_GT(ex.last_stats().weak_cells[0], 0);
  }
  o.fast_threshold_min = o.fast_threshold;  // no fallback: the weak rectangle vanishes
  OrbExtractor ex(o, 320, 160);
  ASSERT_EQ(ex.extract(im.view(), f), OrbStatus::kOk);
  for (auto c : rect_corners(40, 50, 100, 110)) EXPECT_LE(nearest(f, c.x, c.y), kCornerTol);
  for (auto c : rect_corners(200, 50, 280, 110)) EXPECT_GT(nearest(f, c.x, c.y), 10.0);
}

// ---- pyramid and blur --------------------------------------------------------------------

TEST(OrbPyramid, AreaResizeKeepsConstantsAndRamps) {
  Image src(301, 207);
  for (int y = 0; y < src.h; ++y)
    for (int x = 0; x < src.w; ++x) src.at(x, y) = static_cast<uint8_t>(x / 2 + y / 4);
  Image dst(251, 172);
  std::vector<uint8_t> tmp(orb_detail::area_resize_tmp_bytes(src.w, dst.w));
  std::vector<orb_detail::AreaTap> xt(dst.w), yt(dst.h);
  orb_detail::area_resize(src.plane(), orb_detail::MutPlane{dst.px.data(), dst.w, dst.h, dst.stride},
                          tmp.data(), xt.data(), yt.data());
  const double rx = double(src.w) / dst.w, ry = double(src.h) / dst.h;
  for (int y = 0; y < dst.h; ++y)
    for (int x = 0; x < dst.w; ++x) {
      // Mean of the (stepped) ramp over the covered area, approximately the
      // ramp at the mapped centre.
      const double sx = (x + 0.5) * rx - 0.5, sy = (y + 0.5) * ry - 0.5;
      EXPECT_NEAR(dst.at(x, y), sx / 2 + sy / 4 - 0.25 - 0.375, 1.6) << x << "," << y;
    }
  Image flat(97, 61, 1, 0, 173);
  Image small(80, 50);
  orb_detail::area_resize(flat.plane(), orb_detail::MutPlane{small.px.data(), small.w, small.h, small.stride},
                          tmp.data(), xt.data(), yt.data());
  for (auto v : small.px) ASSERT_EQ(v, 173);
}

TEST(OrbPyramid, GaussianKernelAndBlur) {
  const auto k = orb_detail::gaussian_kernel7();
  int sum = 0;
  for (auto v : k) sum += v;
  EXPECT_EQ(sum, 256);
  EXPECT_EQ(k[0], k[6]);
  EXPECT_GT(k[3], k[2]);
  Image flat(40, 30, 1, 0, 91), out(40, 30);
  std::vector<uint8_t> tmp(40 * 30);
  orb_detail::gaussian_blur7(flat.plane(), orb_detail::MutPlane{out.px.data(), 40, 30, 40}, tmp.data());
  for (auto v : out.px) ASSERT_EQ(v, 91);
  // An impulse spreads to the kernel's outer product.
  Image imp(21, 21);
  imp.at(10, 10) = 255;
  Image bl(21, 21);
  std::vector<uint8_t> tmp2(21 * 21);
  orb_detail::gaussian_blur7(imp.plane(), orb_detail::MutPlane{bl.px.data(), 21, 21, 21}, tmp2.data());
  EXPECT_NEAR(bl.at(10, 10), 255.0 * k[3] * k[3] / 65536.0, 1.0);
  EXPECT_EQ(bl.at(10, 14), 0);
  EXPECT_EQ(bl.at(9, 10), bl.at(11, 10));
}

// ---- orientation ---------------------------------------------------------------------------

TEST(OrbOrientation, UmaxDiscIsSymmetric) {
  const auto umax = orb_detail::patch_umax();
  EXPECT_EQ(umax[0], 15);
  for (int v = 0; v <= 15; ++v)
    for (int u = 0; u <= 15; ++u) EXPECT_EQ(u <= umax[v], v <= umax[u]) << u << "," << v;
}

TEST(OrbOrientation, RotatesWithThePatch) {
  const auto umax = orb_detail::patch_umax();
  std::vector<double> errs;
  for (uint32_t seed = 1; seed <= 12; ++seed) {
    BlobScene scene(seed, 32, 32, 12, 6);
    const Image base = scene.render(64, 64, 32, 32, 0);
    const float a0 = orb_detail::ic_angle(base.plane(), 32, 32, umax);
    for (double deg : {12.0, 30.0, 90.0, 145.0, 270.0}) {
      const double phi = deg * kPi / 180;
      const Image rot = scene.render(64, 64, 32, 32, phi);
      const float a1 = orb_detail::ic_angle(rot.plane(), 32, 32, umax);
      errs.push_back(std::abs(angle_diff(a1 - a0, phi)) * 180 / kPi);
    }
  }
  std::sort(errs.begin(), errs.end());
  const double median = errs[errs.size() / 2];
  const double p90 = errs[errs.size() * 9 / 10];
  std::printf("orientation error over %zu rotated patches: median %.2f deg, p90 %.2f deg, max %.2f deg\n",
              errs.size(), median, p90, errs.back());
  EXPECT_LT(median, 1.5);
  EXPECT_LT(p90, 4.0);
}

TEST(OrbOrientation, ExactForNinetyDegreeTurns) {
  // A 90-degree turn permutes pixels exactly and the disc maps onto itself.
  const auto umax = orb_detail::patch_umax();
  const Image a = noise_image(41, 41, 7);
  Image b(41, 41);
  for (int y = 0; y < 41; ++y)
    for (int x = 0; x < 41; ++x)
      b.at(40 - y, x) = a.px[static_cast<std::size_t>(y) * 41 + x];  // (x,y)->(-y,x)
  const float a0 = orb_detail::ic_angle(a.plane(), 20, 20, umax);
  const float a1 = orb_detail::ic_angle(b.plane(), 20, 20, umax);
  EXPECT_NEAR(angle_diff(a1 - a0, kPi / 2), 0.0, 1e-4);
}

// ---- BRIEF -------------------------------------------------------------------------------------

TEST(OrbBrief, PatternIsDeterministicAndInsideTheDisc) {
  const auto p1 = orb_detail::make_brief_pattern(42);
  const auto p2 = orb_detail::make_brief_pattern(42);
  const auto p3 = orb_detail::make_brief_pattern(43);
  EXPECT_EQ(p1, p2);
  EXPECT_NE(p1, p3);
  double spread = 0;
  for (const auto& t : p1) {
    EXPECT_LE(t[0] * t[0] + t[1] * t[1], 169);
    EXPECT_LE(t[2] * t[2] + t[3] * t[3], 169);
    EXPECT_FALSE(t[0] == t[2] && t[1] == t[3]);
    spread += t[0] * t[0] + t[1] * t[1] + t[2] * t[2] + t[3] * t[3];
  }
  // Gaussian sigma 6.2 truncated at 13: RMS coordinate about 5.4.
  const double rms = std::sqrt(spread / (4 * 256));
  EXPECT_GT(rms, 4.5);
  EXPECT_LT(rms, 6.2);
}

namespace {
struct SteerResult {
  int steered, unsteered;
};
SteerResult steer_distance(uint32_t seed, double deg) {
  const auto umax = orb_detail::patch_umax();
  const auto pattern = orb_detail::make_brief_pattern(OrbOptions{}.pattern_seed);
  BlobScene scene(seed, 40, 40, 14, 10);
  const Image a = scene.render(81, 81, 40, 40, 0);
  const Image b = scene.render(81, 81, 40, 40, deg * kPi / 180);
  Image ab(81, 81), bb(81, 81);
  std::vector<uint8_t> tmp(81 * 81);
  orb_detail::gaussian_blur7(a.plane(), orb_detail::MutPlane{ab.px.data(), 81, 81, 81}, tmp.data());
  orb_detail::gaussian_blur7(b.plane(), orb_detail::MutPlane{bb.px.data(), 81, 81, 81}, tmp.data());
  const float aa = orb_detail::ic_angle(a.plane(), 40, 40, umax);
  const float ba = orb_detail::ic_angle(b.plane(), 40, 40, umax);
  const auto da = orb_detail::brief_describe(ab.plane(), 40, 40, aa, pattern);
  const auto db = orb_detail::brief_describe(bb.plane(), 40, 40, ba, pattern);
  const auto ua = orb_detail::brief_describe(ab.plane(), 40, 40, 0, pattern);
  const auto ub = orb_detail::brief_describe(bb.plane(), 40, 40, 0, pattern);
  return {hamming_distance(da, db), hamming_distance(ua, ub)};
}
}  // namespace

TEST(OrbBrief, SteeringMakesDescriptorsRotationInvariant) {
  for (double deg : {30.0, 90.0}) {
    std::vector<int> st, un;
    for (uint32_t seed = 100; seed < 112; ++seed) {
      const auto r = steer_distance(seed, deg);
      st.push_back(r.steered);
      un.push_back(r.unsteered);
    }
    std::sort(st.begin(), st.end());
    std::sort(un.begin(), un.end());
    std::printf("rotation %.0f deg: steered Hamming median %d max %d; unsteered median %d\n", deg,
                st[st.size() / 2], st.back(), un[un.size() / 2]);
    // 256 bits: unrelated patches sit near 128, ORB matchers accept < ~50.
    EXPECT_LE(st[st.size() / 2], 30) << deg;
    EXPECT_LE(st.back(), 50) << deg;
    EXPECT_GE(un[un.size() / 2], 2 * st[st.size() / 2] + 20) << deg;
  }
}

TEST(OrbBrief, BitsAreBalancedOnTexture) {
  const Image im = noise_image(752, 480, 5, 2);
  OrbExtractor ex(OrbOptions{}, 752, 480);
  OrbFeatures f(300);
  ASSERT_EQ(ex.extract(im.view(), f), OrbStatus::kOk);
  ASSERT_GT(f.size(), 200);
  std::vector<int> ones(256, 0);
  for (int i = 0; i < f.size(); ++i)
    for (int b = 0; b < 256; ++b) ones[b] += (f.descriptor(i)[b / 64] >> (b % 64)) & 1u;
  // Steering aligns every patch with its intensity centroid, so tests along
  // that axis lean one way (the ORB paper's reason for learning rBRIEF); a
  // broken sampler or pattern shows up as (nearly) constant bits.
  int extreme = 0;
  int constant = 0;
  for (int b = 0; b < 256; ++b) {
    const double m = double(ones[b]) / f.size();
    if (m < 0.3 || m > 0.7) ++extreme;
    if (m < 0.05 || m > 0.95) ++constant;
  }
  std::printf("bits with mean outside [0.3, 0.7]: %d of 256; outside [0.05, 0.95]: %d\n", extreme, constant);
  EXPECT_EQ(constant, 0);
  EXPECT_LT(extreme, 26);
}

// The inline bit-slicing popcount the portable x86-64 build uses must agree
// with the library's count on every kind of word, not only random ones.
TEST(OrbMatch, Popcount64AgreesWithBitset) {
  std::mt19937_64 rng(11);
  std::vector<std::uint64_t> words{0, ~0ULL, 1, 1ULL << 63, 0x5555555555555555ULL, 0xAAAAAAAAAAAAAAAAULL};
  for (int i = 0; i < 64; ++i) words.push_back(~0ULL >> i);
  for (int i = 0; i < 20000; ++i) words.push_back(rng() & rng());  // sparse words too
  for (int i = 0; i < 20000; ++i) words.push_back(rng());
  for (const std::uint64_t w : words)
    ASSERT_EQ(popcount64(w), int(std::bitset<64>(w).count())) << std::hex << w;
}

TEST(OrbMatch, HammingAndRatioTest) {
  OrbDescriptor a{0, 0, 0, 0}, b{~0ULL, 0, 0, 1};
  EXPECT_EQ(hamming_distance(a, b), 65);
  EXPECT_EQ(hamming_distance(b, b), 0);
  std::mt19937_64 rng(3);
  std::vector<OrbDescriptor> q(50), t(50);
  for (auto& d : q) d = {rng(), rng(), rng(), rng()};
  for (int i = 0; i < 50; ++i) {
    t[(i * 7) % 50] = q[i];
    t[(i * 7) % 50][i % 4] ^= 0x11ULL;  // two flipped bits
  }
  auto m = match_brute_force(q.data(), 50, t.data(), 50, 0.8f);
  ASSERT_EQ(m.size(), 50u);
  for (const auto& x : m) {
    EXPECT_EQ(x.train, (x.query * 7) % 50);
    EXPECT_EQ(x.distance, 2);
  }
  // Two equally good candidates (3 bits off each): the ratio test rejects.
  std::vector<OrbDescriptor> dup = {q[0], q[0]};
  dup[0][0] ^= 0x7ULL;
  dup[1][1] ^= 0x70ULL;
  EXPECT_TRUE(match_brute_force(q.data(), 1, dup.data(), 2, 0.8f).empty());
  EXPECT_EQ(match_brute_force(q.data(), 1, dup.data(), 2, 1.01f).size(), 1u);
}

// ---- extractor behaviour -----------------------------------------------------------------------------

TEST(OrbExtractor, BudgetMetOnTextureAndMarginsRespected) {
  const Image im = noise_image(752, 480, 11);
  OrbOptions o;
  OrbExtractor ex(o, 752, 480);
  OrbFeatures f(o.n_features);
  ASSERT_EQ(ex.extract(im.view(), f), OrbStatus::kOk);
  EXPECT_EQ(f.size(), o.n_features);
  const auto& st = ex.last_stats();
  EXPECT_EQ(st.n_levels_used, 4);
  std::array<int, 4> per_level{};
  for (int i = 0; i < f.size(); ++i) {
    const auto& k = f.keypoint(i);
    ASSERT_GE(k.level, 0);
    ASSERT_LT(k.level, 4);
    ++per_level[k.level];
    const int wl = static_cast<int>(std::lround(752 / ex.level_scale(k.level)));
    const int hl = static_cast<int>(std::lround(480 / ex.level_scale(k.level)));
    EXPECT_GE(k.x_level, o.edge_margin);
    EXPECT_LE(k.x_level, wl - 1 - o.edge_margin);
    EXPECT_GE(k.y_level, o.edge_margin);
    EXPECT_LE(k.y_level, hl - 1 - o.edge_margin);
    EXPECT_GE(k.x, o.edge_margin);
    EXPECT_LE(k.x, 752 - 1 - o.edge_margin);
    EXPECT_GE(k.y, o.edge_margin);
    EXPECT_LE(k.y, 480 - 1 - o.edge_margin);
    EXPECT_GE(k.angle_rad, 0.0f);
    EXPECT_LT(k.angle_rad, 2 * kPi);
    EXPECT_NEAR(k.size, 31 * ex.level_scale(k.level), 1e-3);
    EXPECT_GE(k.response, o.fast_threshold_min);
  }
  for (int l = 0; l < 4; ++l) {
    EXPECT_EQ(per_level[l], st.selected[l]);
    EXPECT_EQ(st.selected[l], ex.level_budget(l)) << "level " << l;
    EXPECT_EQ(st.candidate_overflow[l], 0);
  }
}

TEST(OrbExtractor, BucketingSpreadsFeaturesOverTheImage) {
  // Strong texture on the left third, weak texture elsewhere: without a grid
  // the left third would take the whole budget.
  Image im = noise_image(752, 480, 13);
  for (int y = 0; y < 480; ++y)
    for (int x = 250; x < 752; ++x) im.at(x, y) = static_cast<uint8_t>(110 + (im.at(x, y) - 128) / 6);
  OrbExtractor ex(OrbOptions{}, 752, 480);
  OrbFeatures f(300);
  ASSERT_EQ(ex.extract(im.view(), f), OrbStatus::kOk);
  int right = 0;
  for (int i = 0; i < f.size(); ++i) right += f.keypoint(i).x > 260 ? 1 : 0;
  EXPECT_GT(right, f.size() / 3);
}

TEST(OrbExtractor, BlankImageGivesNothing) {
  Image im(640, 480, 1, 0, 128);
  OrbExtractor ex(OrbOptions{}, 640, 480);
  OrbFeatures f(300);
  EXPECT_EQ(ex.extract(im.view(), f), OrbStatus::kOk);
  EXPECT_EQ(f.size(), 0);
  Image black(640, 480);
  EXPECT_EQ(ex.extract(black.view(), f), OrbStatus::kOk);
  EXPECT_EQ(f.size(), 0);
}

TEST(OrbExtractor, SmallOddAndStridedImages) {
  OrbExtractor ex(OrbOptions{}, 752, 480);
  OrbFeatures f(300);
  for (auto [w, h] : {std::pair{320, 240}, std::pair{331, 257}, std::pair{97, 61}, std::pair{33, 33},
                      std::pair{20, 481}, std::pair{40, 480}, std::pair{1, 1}}) {
    const Image g = noise_image(w, h, 17);
    Image padded(w, h, 1, 13);
    for (int y = 0; y < h; ++y) std::memcpy(&padded.at(0, y), &g.px[static_cast<std::size_t>(y) * w], w);
    OrbFeatures a(300);
    const OrbStatus s = ex.extract(padded.view(), a);
    if (h > 480) {
      EXPECT_EQ(s, OrbStatus::kImageTooLarge);
      EXPECT_EQ(a.size(), 0);
      continue;
    }
    ASSERT_EQ(s, OrbStatus::kOk) << w << "x" << h;
    ASSERT_EQ(ex.extract(g.view(), f), OrbStatus::kOk);
    ASSERT_EQ(a.size(), f.size()) << "stride must not matter";
    for (int i = 0; i < a.size(); ++i) {
      EXPECT_EQ(a.descriptor(i), f.descriptor(i));
      EXPECT_GE(a.keypoint(i).x, 16);
      EXPECT_LE(a.keypoint(i).x, w - 17);
      EXPECT_GE(a.keypoint(i).y, 16);
      EXPECT_LE(a.keypoint(i).y, h - 17);
    }
    if (w >= 97 && h >= 61) {
      EXPECT_GT(a.size(), 0) << w << "x" << h;
    }
    if (w < 33 || h < 33) {
      EXPECT_EQ(a.size(), 0);
    }
  }
}

TEST(OrbExtractor, ColourInputMatchesItsLuma) {
  const Image g = noise_image(331, 257, 19);
  Image rgb(331, 257, 3, 7), bgr(331, 257, 3, 0), luma(331, 257);
  std::mt19937 rng(2);
  for (int y = 0; y < 257; ++y)
    for (int x = 0; x < 331; ++x) {
      const int r = g.px[static_cast<std::size_t>(y) * 331 + x];
      const int gg = (r * 3 + static_cast<int>(rng() % 64)) / 4 + 8;
      const int b = 255 - r;
      rgb.at(x, y, 0) = bgr.at(x, y, 2) = static_cast<uint8_t>(r);
      rgb.at(x, y, 1) = bgr.at(x, y, 1) = static_cast<uint8_t>(std::min(gg, 255));
      rgb.at(x, y, 2) = bgr.at(x, y, 0) = static_cast<uint8_t>(b);
      luma.at(x, y) = static_cast<uint8_t>((77 * r + 150 * std::min(gg, 255) + 29 * b + 128) >> 8);
    }
  OrbExtractor ex(OrbOptions{}, 640, 480);
  OrbFeatures fr(300), fb(300), fg(300);
  ASSERT_EQ(ex.extract(rgb.view(PixelFormat::kRgb8), fr), OrbStatus::kOk);
  ASSERT_EQ(ex.extract(bgr.view(PixelFormat::kBgr8), fb), OrbStatus::kOk);
  ASSERT_EQ(ex.extract(luma.view(), fg), OrbStatus::kOk);
  ASSERT_GT(fg.size(), 100);
  ASSERT_EQ(fr.size(), fg.size());
  ASSERT_EQ(fb.size(), fg.size());
  for (int i = 0; i < fg.size(); ++i) {
    EXPECT_EQ(fr.descriptor(i), fg.descriptor(i));
    EXPECT_EQ(fb.descriptor(i), fg.descriptor(i));
  }
}

TEST(OrbExtractor, BadInputIsReportedNotCrashed) {
  OrbExtractor ex(OrbOptions{}, 320, 240);
  OrbFeatures f(300), small(10);
  const Image g = noise_image(320, 240, 1);
  ImageView v = g.view();
  v.data = nullptr;
  EXPECT_EQ(ex.extract(v, f), OrbStatus::kNullImage);
  v = g.view();
  v.stride_bytes = 100;
  EXPECT_EQ(ex.extract(v, f), OrbStatus::kNullImage);
  v = g.view();
  v.format = PixelFormat::kDepthU16;
  EXPECT_EQ(ex.extract(v, f), OrbStatus::kUnsupportedFormat);
  const Image big = noise_image(321, 240, 1);
  EXPECT_EQ(ex.extract(big.view(), f), OrbStatus::kImageTooLarge);
  EXPECT_EQ(ex.extract(g.view(), small), OrbStatus::kOutputTooSmall);
  EXPECT_EQ(f.size(), 0);
  EXPECT_STRNE(to_string(OrbStatus::kImageTooLarge), "unknown");
}

TEST(OrbExtractor, DeterministicAcrossInstances) {
  const Image g = noise_image(640, 480, 23);
  OrbExtractor a(OrbOptions{}, 640, 480), b(OrbOptions{}, 752, 480);
  OrbFeatures fa(300), fb(300);
  ASSERT_EQ(a.extract(g.view(), fa), OrbStatus::kOk);
  ASSERT_EQ(b.extract(g.view(), fb), OrbStatus::kOk);
  ASSERT_EQ(a.extract(g.view(), fa), OrbStatus::kOk);  // second call on the same instance: same answer
  ASSERT_EQ(fa.size(), fb.size());
  for (int i = 0; i < fa.size(); ++i) {
    EXPECT_EQ(std::memcmp(&fa.keypoint(i), &fb.keypoint(i), sizeof(OrbKeypoint)), 0);
    EXPECT_EQ(fa.descriptor(i), fb.descriptor(i));
  }
}

// The vector paths (SSE2 on x86-64, NEON on AArch64: the aarch64 preset runs
// this under qemu) against the scalar reference: FAST prefilter and segment
// test, area resampling and blur, BRIEF's rotated offsets. Bit-identical
// features or the vector code is wrong. Widths that are not multiples of 16
// and a padded stride exercise the ragged ends.
TEST(OrbExtractor, VectorPathsGiveTheScalarReferenceBitForBit) {
  std::printf("vector paths: %s\n", orb_detail::vector_isa());
  if (!orb_detail::vector_paths())
    GTEST_SKIP() << "SKIPPED LOUDLY: this target has no vector paths (vector_isa none); scalar only";
  struct Case {
    int w, h, pad;
    uint32_t seed;
  };
  for (const Case c :
       {Case{640, 480, 0, 41}, Case{752, 480, 0, 43}, Case{331, 257, 5, 47}, Case{97, 61, 3, 53}}) {
    const Image tex = noise_image(c.w, c.h, c.seed);
    Image im(c.w, c.h, 1, c.pad);
    for (int y = 0; y < c.h; ++y)
      for (int x = 0; x < c.w; ++x) im.at(x, y) = tex.px[static_cast<std::size_t>(y) * tex.stride + x];
    OrbExtractor ex(OrbOptions{}, 752, 480);
    OrbFeatures vec(300), ref(300);
    ASSERT_EQ(ex.extract(im.view(), vec), OrbStatus::kOk);
    orb_detail::set_vector_paths(false);
    const OrbStatus st = ex.extract(im.view(), ref);
    const OrbExtractStats ref_stats = ex.last_stats();
    orb_detail::set_vector_paths(true);
    ASSERT_EQ(st, OrbStatus::kOk);
    ASSERT_EQ(ex.extract(im.view(), vec), OrbStatus::kOk);
    EXPECT_EQ(ex.last_stats().corners, ref_stats.corners) << c.w << "x" << c.h << ": FAST corners per level";
    ASSERT_EQ(vec.size(), ref.size()) << c.w << "x" << c.h;
    EXPECT_GT(vec.size(), c.w >= 331 ? 200 : 5) << c.w << "x" << c.h;
    int differ = 0;
    for (int i = 0; i < vec.size(); ++i)
      differ += std::memcmp(&vec.keypoint(i), &ref.keypoint(i), sizeof(OrbKeypoint)) != 0 ||
                vec.descriptor(i) != ref.descriptor(i);
    EXPECT_EQ(differ, 0) << c.w << "x" << c.h << ": features that differ from the scalar reference";
  }
  // The stages one by one, on sizes with ragged ends (area resampling works
  // in blocks of 16 rows and columns; 64 rows is a whole number of them, 61
  // is not, and 16 is the smallest the vector path takes).
  const Image src = noise_image(203, 77, 59);
  auto run_stages = [&](std::vector<uint8_t>& blurred, std::vector<uint8_t>& resized) {
    std::vector<uint8_t> tmp(static_cast<std::size_t>(src.w) * src.h);
    blurred.assign(tmp.size(), 0);
    orb_detail::gaussian_blur7(src.plane(), orb_detail::MutPlane{blurred.data(), src.w, src.h, src.w},
                               tmp.data());
    resized.clear();
    for (const auto& [dw, dh] :
         {std::pair{169, 64}, std::pair{170, 61}, std::pair{16, 16}, std::pair{101, 40}}) {
      std::vector<orb_detail::AreaTap> xt(static_cast<std::size_t>(dw)), yt(static_cast<std::size_t>(dh));
      std::vector<uint8_t> rtmp(orb_detail::area_resize_tmp_bytes(src.w, dw));
      std::vector<uint8_t> out(static_cast<std::size_t>(dw) * dh, 0);
      orb_detail::area_resize(src.plane(), orb_detail::MutPlane{out.data(), dw, dh, dw}, rtmp.data(),
                              xt.data(), yt.data());
      resized.insert(resized.end(), out.begin(), out.end());
    }
  };
  std::vector<uint8_t> bv, rv, bs, rs;
  run_stages(bv, rv);
  orb_detail::set_vector_paths(false);
  run_stages(bs, rs);
  orb_detail::set_vector_paths(true);
  EXPECT_EQ(bv, bs) << "blur";
  EXPECT_EQ(rv, rs) << "area resampling";
  // BRIEF's patch blur is the whole-image blur, cut out, on both paths; the
  // centres include the closest the extractor allows to every border.
  constexpr int kSide = orb_detail::kBriefPatchSide;
  constexpr int kM = orb_detail::kBriefPatchMargin;
  constexpr int kP = orb_detail::kPatternRadius;
  for (const bool vector : {true, false}) {
    orb_detail::set_vector_paths(vector);
    std::array<uint8_t, kSide * kSide> patch{};
    std::array<uint8_t, kSide*(kSide + 2 * orb_detail::kBlurRadius)> ptmp{};
    int differ = 0;
    for (const auto& [cx, cy] :
         {std::pair{kM, kM}, std::pair{src.w - 1 - kM, src.h - 1 - kM}, std::pair{kM, 40}, std::pair{101, kM},
          std::pair{77, 38}, std::pair{src.w - 1 - kM, 20}}) {
      orb_detail::gaussian_blur7_patch(src.plane(), cx, cy, patch.data(), ptmp.data());
      for (int v = -kP; v <= kP; ++v)
        for (int u = -kP; u <= kP; ++u)
          differ += patch[static_cast<std::size_t>((v + kP) * kSide + u + kP)] !=
                    bs[static_cast<std::size_t>((cy + v) * src.w + cx + u)];
    }
    EXPECT_EQ(differ, 0) << (vector ? "vector" : "scalar") << " patch blur against the whole-image blur";
  }
  orb_detail::set_vector_paths(true);
}

TEST(OrbExtractor, ExtractNeverAllocates) {
  ASSERT_TRUE(rt::alloc_hook_linked());
  const Image tex = noise_image(752, 480, 29);
  const Image small = noise_image(331, 257, 31);
  Image rgb(640, 480, 3);
  for (std::size_t i = 0; i < rgb.px.size(); ++i) rgb.px[i] = tex.px[i % tex.px.size()];
  const Image blank(752, 480, 1, 0, 77);
  OrbExtractor ex(OrbOptions{}, 752, 480);
  OrbFeatures f(300);
  std::printf("extractor buffers: %zu bytes for 752x480\n", ex.buffer_bytes());
  rt::AllocCountScope scope;  // from the very first call on: the constructor did all of it
  for (int rep = 0; rep < 3; ++rep) {
    EXPECT_EQ(ex.extract(tex.view(), f), OrbStatus::kOk);
    EXPECT_EQ(f.size(), 300);
    EXPECT_EQ(ex.extract(small.view(), f), OrbStatus::kOk);
    EXPECT_EQ(ex.extract(rgb.view(PixelFormat::kRgb8), f), OrbStatus::kOk);
    EXPECT_EQ(ex.extract(blank.view(), f), OrbStatus::kOk);
    EXPECT_EQ(ex.extract(tex.view(PixelFormat::kYuyv), f), OrbStatus::kUnsupportedFormat);
  }
  EXPECT_EQ(scope.count(), 0u) << scope.bytes() << " bytes allocated inside extract()";
}

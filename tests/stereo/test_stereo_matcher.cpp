// The row search of core/stereo on images whose disparity is known by
// construction: a smooth random texture, the right image the same texture
// sampled d pixels further along the row. Also: no match on a flat wall, the
// vector path equals the scalar one, no allocation per call.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include "kestrel/core/stereo_matcher.hpp"
#include "kestrel/rt/alloc_counter.hpp"

namespace {

using kestrel::ImageView;
using kestrel::PixelFormat;
using kestrel::core::StereoMatcher;
using kestrel::core::StereoMatchOptions;
using kestrel::core::StereoMatchStats;

// Sum of random sinusoids: continuous, so a sub-pixel shift is exact.
struct Texture {
  struct Wave {
    double fx, fy, phase, amp;
  };
  std::vector<Wave> waves;
  explicit Texture(uint32_t seed) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> f(0.05, 0.6), ph(0, 6.283), a(4, 14);
    for (int i = 0; i < 24; ++i) waves.push_back({f(rng), f(rng) * (i % 2 ? 1 : -1), ph(rng), a(rng)});
  }
  double at(double x, double y) const {
    double v = 128;
    for (const Wave& w : waves) v += w.amp * std::sin(w.fx * x + w.fy * y + w.phase);
    return std::clamp(v, 0.0, 255.0);
  }
};

struct Pair {
  int w = 640, h = 480;
  std::vector<uint8_t> left, right;
  ImageView lv() const { return {w, h, w, PixelFormat::kGray8, left.data()}; }
  ImageView rv() const { return {w, h, w, PixelFormat::kGray8, right.data()}; }
};

Pair make_pair(const Texture& t, double disparity_px) {
  Pair p;
  p.left.resize(static_cast<size_t>(p.w * p.h));
  p.right.resize(p.left.size());
  for (int y = 0; y < p.h; ++y)
    for (int x = 0; x < p.w; ++x) {
      p.left[static_cast<size_t>(y * p.w + x)] = static_cast<uint8_t>(std::lround(t.at(x, y)));
      // A point seen at left column x is seen at right column x - d: right(u) = texture(u + d).
      p.right[static_cast<size_t>(y * p.w + x)] =
          static_cast<uint8_t>(std::lround(t.at(x + disparity_px, y)));
    }
  return p;
}

void grid_points(int w, int h, std::vector<float>& x, std::vector<float>& y) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> jitter(-0.4f, 0.4f);
  for (int gy = 20; gy < h - 20; gy += 24)
    for (int gx = 120; gx < w - 20; gx += 24) {
      x.push_back(static_cast<float>(gx) + jitter(rng));
      y.push_back(static_cast<float>(gy) + jitter(rng));
    }
}

TEST(StereoMatcher, RecoversKnownSubPixelDisparities) {
  const Texture tex(11);
  std::vector<float> x, y;
  grid_points(640, 480, x, y);
  std::vector<float> d(x.size());
  const StereoMatcher m;
  for (double truth : {4.3, 17.5, 40.8, 77.25}) {
    const Pair p = make_pair(tex, truth);
    StereoMatchStats st;
    ASSERT_TRUE(m.match(p.lv(), p.rv(), x.data(), y.data(), static_cast<int>(x.size()), d.data(), &st));
    std::vector<double> err;
    for (float v : d)
      if (v > 0) err.push_back(std::abs(v - truth));
    ASSERT_GT(err.size(), 0.9 * x.size())
        << "disparity " << truth << ": only " << err.size() << " of " << x.size();
    std::sort(err.begin(), err.end());
    const double median = err[err.size() / 2], p95 = err[err.size() * 95 / 100];
    std::printf("[ figure ] disparity %.2f px: %zu/%zu matched, |error| median %.3f px, p95 %.3f px\n", truth,
                err.size(), x.size(), median, p95);
    EXPECT_LT(median, 0.15) << "disparity " << truth;
    EXPECT_LT(p95, 0.35) << "disparity " << truth;
    EXPECT_LT(err.back(), 1.0) << "disparity " << truth << ": a gross mismatch";
  }
}

TEST(StereoMatcher, FlatImageAndOutOfRangeGiveNoMatch) {
  Pair flat;
  flat.left.assign(static_cast<size_t>(flat.w * flat.h), 90);
  flat.right = flat.left;
  std::vector<float> x, y;
  grid_points(640, 480, x, y);
  std::vector<float> d(x.size(), -1.0f);
  const StereoMatcher m;
  StereoMatchStats st;
  ASSERT_TRUE(m.match(flat.lv(), flat.rv(), x.data(), y.data(), static_cast<int>(x.size()), d.data(), &st));
  EXPECT_GT(st.searched, 0);
  EXPECT_EQ(st.matched, 0);
  for (float v : d) EXPECT_EQ(v, 0.0f);

  // A true disparity beyond the searched range must not be matched to something inside it.
  StereoMatchOptions o;
  o.max_disparity_px = 30;
  const Pair far = make_pair(Texture(3), 60.0);
  const StereoMatcher narrow(o);
  ASSERT_TRUE(
      narrow.match(far.lv(), far.rv(), x.data(), y.data(), static_cast<int>(x.size()), d.data(), &st));
  EXPECT_LT(st.matched, st.searched / 10) << "most out-of-range points must stay unmatched";

  // Images that do not fit: refused, everything zero.
  Pair small = make_pair(Texture(3), 5.0);
  ImageView bad = small.rv();
  bad.width = 320;
  EXPECT_FALSE(m.match(small.lv(), bad, x.data(), y.data(), static_cast<int>(x.size()), d.data()));
  for (float v : d) EXPECT_EQ(v, 0.0f);
}

TEST(StereoMatcher, VectorPathEqualsScalarAndAllocatesNothing) {
  const Pair p = make_pair(Texture(5), 23.6);
  std::vector<float> x, y;
  grid_points(640, 480, x, y);
  const int n = static_cast<int>(x.size());
  std::vector<float> dv(x.size()), ds(x.size());
  const StereoMatcher m;
  StereoMatcher::set_vector_path(true);
  m.match(p.lv(), p.rv(), x.data(), y.data(), n, dv.data());
  StereoMatcher::set_vector_path(false);
  m.match(p.lv(), p.rv(), x.data(), y.data(), n, ds.data());
  StereoMatcher::set_vector_path(true);
  EXPECT_EQ(dv, ds);

  ASSERT_TRUE(kestrel::rt::alloc_hook_linked());
  kestrel::rt::AllocCountScope scope;
  for (int k = 0; k < 20; ++k) m.match(p.lv(), p.rv(), x.data(), y.data(), n, dv.data());
  EXPECT_EQ(scope.count(), 0u) << "the row search allocated on the tracking thread";
}

// The bench figure of docs/stereo.md: 300 features (the tracker's budget) at VGA.
TEST(StereoMatcher, TimingAtVga) {
  const Pair p = make_pair(Texture(9), 31.2);
  std::vector<float> x, y;
  grid_points(640, 480, x, y);
  x.resize(300);
  y.resize(300);
  std::vector<float> d(300);
  const StereoMatcher m;
  for (bool vec : {true, false}) {
    StereoMatcher::set_vector_path(vec);
    std::vector<double> ms;
    for (int k = 0; k < 50; ++k) {
      const auto t0 = std::chrono::steady_clock::now();
      m.match(p.lv(), p.rv(), x.data(), y.data(), 300, d.data());
      ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
    }
    std::sort(ms.begin(), ms.end());
    std::printf(
        "[ figure ] row search, 300 features, VGA, disparities 2..96, %s: median %.3f ms, max %.3f ms\n",
        vec ? "vector" : "scalar", ms[ms.size() / 2], ms.back());
    // Generous (a shared, loaded machine): the goal is 1.5 ms, the figure is in docs/stereo.md.
    if (vec) {
      EXPECT_LT(ms[ms.size() / 2], 5.0);
    }
  }
  StereoMatcher::set_vector_path(true);
}

}  // namespace

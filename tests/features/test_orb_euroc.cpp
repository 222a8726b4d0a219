// Our ORB against cv::ORB on real EuRoC V1_01 images, same budget (300
// features, 4 levels, scale 1.2, FAST 20), same protocol (docs/orb.md):
//  - consecutive frames, reference motion from KLT (forward-backward checked);
//  - each frame against a warped copy of itself (known affine: rotation and
//    scale), which tests the invariances the first part cannot (the MAV barely
//    moves in these 95 frames).
// Repeatability: share of frame-k keypoints with a frame-k+1 keypoint within
// 3 px of their true image. Precision: share of brute-force Hamming matches
// (ratio 0.8, our matcher for both) that land within 3 px of the true image.
// Only keypoints whose true image lies >= 32 px inside the second frame count.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include "orb_eval.hpp"
#include "test_data.hpp"

using namespace kestrel;
using namespace kestrel::test;

namespace {

constexpr const char* kSeq = "euroc/V1_01_easy_first95";

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0 : v[v.size() / 2];
}

class OrbEuroc : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    if (!std::filesystem::exists(shared_path(kSeq))) return;
    frames_ = load_euroc_cam0(shared_path(std::string(kSeq) + "/mav0"));
  }
  static std::vector<cv::Mat> frames_;
};
std::vector<cv::Mat> OrbEuroc::frames_;

}  // namespace

namespace {

struct Protocol {
  Scores consecutive;
  std::vector<Scores> warped;  // one per kWarps entry
  double coverage = 0;         // mean share of 48x48 blocks holding a keypoint
};

struct Warp {
  const char* name;
  double deg, scale;
};
constexpr Warp kWarps[] = {{"rotate 30 deg", 30, 1.0},
                           {"rotate 90 deg", 90, 1.0},
                           {"scale 1/1.2", 0, 1 / 1.2},
                           {"rotate 15, scale 1.15", 15, 1.15}};

double coverage(const Features& f, cv::Size sz) {
  constexpr int kB = 48;
  const int nx = (sz.width - 64) / kB, ny = (sz.height - 64) / kB;
  std::vector<char> hit(static_cast<std::size_t>(nx * ny), 0);
  for (const auto& p : f.pts) {
    const int bx = static_cast<int>((p.x - 32) / kB), by = static_cast<int>((p.y - 32) / kB);
    if (p.x >= 32 && p.y >= 32 && bx < nx && by < ny) hit[static_cast<std::size_t>(by * nx + bx)] = 1;
  }
  return double(std::count(hit.begin(), hit.end(), 1)) / hit.size();
}

// The whole protocol for one extractor: `run` maps a grey frame to features.
template <class Run>
Protocol evaluate(const std::vector<cv::Mat>& frames, Run run) {
  Protocol r;
  std::vector<Features> f;
  for (const auto& im : frames) {
    f.push_back(run(im));
    r.coverage += coverage(f.back(), im.size()) / frames.size();
  }
  for (std::size_t k = 0; k + 1 < frames.size(); ++k)
    accumulate(r.consecutive, f[k], f[k + 1], klt_map(frames[k], frames[k + 1], f[k].pts),
               frames[k + 1].size());
  for (const auto& w : kWarps) {
    Scores s;
    for (std::size_t k = 0; k < frames.size(); k += 5) {
      const cv::Mat A = cv::getRotationMatrix2D(cv::Point2f(375.5f, 239.5f), w.deg, w.scale);
      cv::Mat b;
      cv::warpAffine(frames[k], b, A, frames[k].size(), cv::INTER_LINEAR, cv::BORDER_CONSTANT, cv::Scalar(0));
      accumulate(s, f[k], run(b), affine_map(A, f[k].pts), b.size());
    }
    r.warped.push_back(s);
  }
  return r;
}

void print_protocol(const char* title, const Protocol& ours, const Protocol& cvp) {
  std::printf("%s\n  %-24s %-26s %-12s %-12s %-12s\n", title, "case", "extractor", "repeatab.", "precision",
              "good/pair");
  auto row = [](const char* c, const char* e, const Scores& s, double pairs) {
    std::printf("  %-24s %-26s %-12.3f %-12.3f %-12.1f\n", c, e, s.repeatability(), s.precision(),
                s.match_good / pairs);
  };
  row("consecutive (KLT)", "kestrel", ours.consecutive, 94);
  row("", "cv::ORB HARRIS_SCORE", cvp.consecutive, 94);
  for (std::size_t i = 0; i < ours.warped.size(); ++i) {
    row(kWarps[i].name, "kestrel", ours.warped[i], 19);
    row("", "cv::ORB HARRIS_SCORE", cvp.warped[i], 19);
  }
  std::printf("  coverage (48 px blocks with a keypoint): kestrel %.3f, cv::ORB %.3f\n", ours.coverage,
              cvp.coverage);
}

Protocol run_cv_protocol(const std::vector<cv::Mat>& frames) {
  auto orb = make_cv_orb(300, 4, cv::ORB::HARRIS_SCORE);
  return evaluate(frames, [&](const cv::Mat& im) { return run_opencv(*orb, im); });
}

Protocol run_ours_protocol(const std::vector<cv::Mat>& frames, const core::OrbOptions& opt) {
  core::OrbExtractor ex(opt, 752, 480);
  core::OrbFeatures scratch(opt.n_features);
  return evaluate(frames, [&](const cv::Mat& im) { return run_ours(ex, scratch, im); });
}

}  // namespace

// Like for like: cv::ORB has no grid and no second threshold, so ours runs
// with one cell and fast_threshold_min = fast_threshold. This isolates the
// detector, pyramid, orientation and descriptor, and holds them to the
// brief's bar on every case.
TEST_F(OrbEuroc, LikeForLikeMatchesOpenCv) {
  KESTREL_REQUIRE_SHARED(kSeq);
  ASSERT_EQ(frames_.size(), 95u);
  core::OrbOptions opt;
  opt.cell_size = 4096;
  opt.fast_threshold_min = opt.fast_threshold;
  const Protocol ours = run_ours_protocol(frames_, opt);
  const Protocol cvp = run_cv_protocol(frames_);
  print_protocol("EuRoC V1_01 cam0, 300 features, 4 levels, 3 px; kestrel WITHOUT grid bucketing:", ours,
                 cvp);
  EXPECT_GE(ours.consecutive.rep_total, 90 * 200) << "too few trusted tracks for a comparison";
  EXPECT_GE(ours.consecutive.repeatability(), 0.9 * cvp.consecutive.repeatability());
  EXPECT_GE(ours.consecutive.precision(), cvp.consecutive.precision() - 0.05);
  for (std::size_t i = 0; i < ours.warped.size(); ++i) {
    EXPECT_GE(ours.warped[i].rep_total, 1000) << kWarps[i].name;
    EXPECT_GE(ours.warped[i].repeatability(), 0.9 * cvp.warped[i].repeatability()) << kWarps[i].name;
    EXPECT_GE(ours.warped[i].precision(), cvp.warped[i].precision() - 0.05) << kWarps[i].name;
  }
}

// The tracker's configuration (defaults: 40 px cells, fallback threshold 7).
// Spreading 300 features over the image trades repeatability (a cell's
// second-best corner is less stable than the image's strongest) for coverage
// and unambiguous matches; docs/orb.md has the numbers. Held to: better
// coverage; on consecutive frames precision within 0.05 of cv::ORB and
// repeatability within 15 %; on the warps at least as many correct matches
// per pair as cv::ORB (precision there is printed, not asserted: at 90 deg it
// is below cv::ORB's, see docs/orb.md "Gaps").
TEST_F(OrbEuroc, DefaultConfigTradeOff) {
  KESTREL_REQUIRE_SHARED(kSeq);
  ASSERT_EQ(frames_.size(), 95u);
  const Protocol ours = run_ours_protocol(frames_, core::OrbOptions{});
  const Protocol cvp = run_cv_protocol(frames_);
  print_protocol("EuRoC V1_01 cam0, 300 features, 4 levels, 3 px; kestrel defaults (grid 40 px, fallback 7):",
                 ours, cvp);
  EXPECT_GE(ours.coverage, cvp.coverage);
  EXPECT_GE(ours.consecutive.repeatability(), 0.85 * cvp.consecutive.repeatability());
  EXPECT_GE(ours.consecutive.precision(), cvp.consecutive.precision() - 0.05);
  for (std::size_t i = 0; i < ours.warped.size(); ++i)
    EXPECT_GE(ours.warped[i].match_good, cvp.warped[i].match_good) << kWarps[i].name;
}

TEST_F(OrbEuroc, TimePerFrameSideBySide) {
  KESTREL_REQUIRE_SHARED(kSeq);
  ASSERT_EQ(frames_.size(), 95u);
  const core::OrbOptions opt;
  core::OrbExtractor ex(opt, 752, 480);
  core::OrbFeatures f(opt.n_features);
  auto harris = make_cv_orb(opt.n_features, opt.n_levels, cv::ORB::HARRIS_SCORE);
  const int threads = cv::getNumThreads();
  cv::setNumThreads(1);  // one core each: ours is single-threaded
  std::vector<double> t_ours, t_cv;
  std::vector<cv::KeyPoint> kps;
  cv::Mat desc;
  for (int rep = 0; rep < 2; ++rep)  // first pass warms caches; keep the second
    for (const auto& im : frames_) {
      const ImageView v{im.cols, im.rows, static_cast<int>(im.step[0]), PixelFormat::kGray8, im.data};
      auto t0 = std::chrono::steady_clock::now();
      ASSERT_EQ(ex.extract(v, f), core::OrbStatus::kOk);
      auto t1 = std::chrono::steady_clock::now();
      harris->detectAndCompute(im, cv::noArray(), kps, desc);
      auto t2 = std::chrono::steady_clock::now();
      if (rep == 0) continue;
      t_ours.push_back(std::chrono::duration<double, std::milli>(t1 - t0).count());
      t_cv.push_back(std::chrono::duration<double, std::milli>(t2 - t1).count());
    }
  cv::setNumThreads(threads);
  std::printf("time per 752x480 frame, median of %zu (one thread): kestrel ORB %.2f ms, cv::ORB %.2f ms\n",
              t_ours.size(), median(t_ours), median(t_cv));
  // Not a timing test (label unit, shared machine): only a sanity bound far
  // above the 10 ms target; bench_orb measures properly. Unoptimised and
  // sanitizer builds (the debug preset) measure nothing about speed.
#if defined(NDEBUG) && !defined(__SANITIZE_ADDRESS__) && !defined(__SANITIZE_THREAD__)
  EXPECT_LT(median(t_ours), 50.0);
#endif
}

// Time per frame, our ORB vs cv::ORB (HARRIS_SCORE and FAST_SCORE), same
// budget (300), same 4 levels, on the 95 real EuRoC V1_01 cam0 frames, cycled;
// also a 640x480 crop. cv::ORB runs on one thread, as ours does.
// Run: bench_orb --benchmark_repetitions=5 --benchmark_report_aggregates_only=true
#include <benchmark/benchmark.h>

#include <cstdio>
#include <filesystem>
#include <opencv2/core/utility.hpp>

#include "orb_eval.hpp"

using namespace kestrel;

namespace {

const std::vector<cv::Mat>& frames(int w) {
  static std::vector<cv::Mat> full = [] {
    const std::string dir = test::shared_data_dir_nogtest() + "/euroc/V1_01_easy_first95/mav0";
    if (!std::filesystem::exists(dir)) {
      std::fprintf(stderr, "SKIPPED: ../shared/data not found (%s)\n", dir.c_str());
      return std::vector<cv::Mat>{};
    }
    return test::load_euroc_cam0(dir);
  }();
  static std::vector<cv::Mat> cropped = [] {
    std::vector<cv::Mat> out;
    for (const auto& f : full) out.push_back(f(cv::Rect(56, 0, 640, 480)).clone());
    return out;
  }();
  return w == 752 ? full : cropped;
}

void BM_KestrelOrb(benchmark::State& st) {
  const int w = static_cast<int>(st.range(0));
  const auto& fr = frames(w);
  if (fr.empty()) {
    st.SkipWithError("SKIPPED: ../shared/data not found");
    return;
  }
  core::OrbExtractor ex(core::OrbOptions{}, w, 480);
  core::OrbFeatures f(300);
  std::size_t i = 0;
  long n = 0;
  for (auto _ : st) {
    const cv::Mat& im = fr[i++ % fr.size()];
    const ImageView v{im.cols, im.rows, static_cast<int>(im.step[0]), PixelFormat::kGray8, im.data};
    benchmark::DoNotOptimize(ex.extract(v, f));
    n += f.size();
  }
  st.counters["features"] = benchmark::Counter(static_cast<double>(n), benchmark::Counter::kAvgIterations);
}

void BM_OpenCvOrb(benchmark::State& st) {
  const int w = static_cast<int>(st.range(0));
  const auto& fr = frames(w);
  if (fr.empty()) {
    st.SkipWithError("SKIPPED: ../shared/data not found");
    return;
  }
  cv::setNumThreads(1);
  auto orb = test::make_cv_orb(300, 4, st.range(1) ? cv::ORB::HARRIS_SCORE : cv::ORB::FAST_SCORE);
  std::vector<cv::KeyPoint> kps;
  cv::Mat desc;
  std::size_t i = 0;
  long n = 0;
  for (auto _ : st) {
    orb->detectAndCompute(fr[i++ % fr.size()], cv::noArray(), kps, desc);
    n += static_cast<long>(kps.size());
  }
  st.counters["features"] = benchmark::Counter(static_cast<double>(n), benchmark::Counter::kAvgIterations);
}

}  // namespace

BENCHMARK(BM_KestrelOrb)->Arg(752)->Arg(640)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_OpenCvOrb)
    ->ArgNames({"w", "harris"})
    ->Args({752, 1})
    ->Args({752, 0})
    ->Args({640, 1})
    ->Unit(benchmark::kMillisecond);
BENCHMARK_MAIN();

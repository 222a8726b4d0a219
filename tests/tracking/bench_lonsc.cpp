// LONSC vs 2-point RANSAC vs OpenCV solvePnPRansac on identical simulated
// RGB-D correspondence sets (tests/tracking/lonsc_sim.hpp). Prints the
// comparison table of docs/lonsc.md, then runs Google Benchmark timings.
//
//   bench_lonsc [--trials=200] [--table_only] [--no_table] [benchmark flags]
#include <benchmark/benchmark.h>

#include <cstdio>
#include <cstring>
#include <memory>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "lonsc_eval.hpp"

namespace kc = kestrel::core;
namespace kt = kestrel::test;

namespace {

// OpenCV: 6-DoF, no IMU. The conversion to cv::Mat is inside the timed call
// (a few microseconds; it is what a caller would pay).
struct OpenCvPnpMethod {
  int flags;
  bool refine_lm;
  int iterations = 2000;  // the adaptive stop (confidence 0.99) ends far earlier at low outlier rates
  OpenCvPnpMethod(int f, bool lm) : flags(f), refine_lm(lm) {}
  kt::MethodOutput operator()(const kt::SimFrame& f) {
    kt::MethodOutput o;
    const kc::PinholeK K = kt::kinect_k();
    std::vector<cv::Point3d> obj;
    std::vector<cv::Point2d> img;
    obj.reserve(f.c.size());
    img.reserve(f.c.size());
    for (const auto& c : f.c) {
      obj.emplace_back(c.p_prev.x(), c.p_prev.y(), c.p_prev.z());
      img.emplace_back(c.u_cur.x(), c.u_cur.y());
    }
    const cv::Matx33d Kcv(K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1);
    cv::Mat rvec, tvec;
    std::vector<int> inl;
    o.ok = cv::solvePnPRansac(obj, img, Kcv, cv::noArray(), rvec, tvec, false, iterations, 3.0f, 0.99, inl,
                              flags);
    if (o.ok && refine_lm && inl.size() >= 4) {
      std::vector<cv::Point3d> oi;
      std::vector<cv::Point2d> ii;
      for (int i : inl) {
        oi.push_back(obj[static_cast<std::size_t>(i)]);
        ii.push_back(img[static_cast<std::size_t>(i)]);
      }
      cv::solvePnPRefineLM(oi, ii, Kcv, cv::noArray(), rvec, tvec);
    }
    o.mask_vec.assign(f.c.size(), 0);
    if (!o.ok) return o;
    for (int i : inl) o.mask_vec[static_cast<std::size_t>(i)] = 1;
    cv::Mat Rm;
    cv::Rodrigues(rvec, Rm);
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) o.R(r, c) = Rm.at<double>(r, c);
    o.t = Eigen::Vector3d(tvec.at<double>(0), tvec.at<double>(1), tvec.at<double>(2));
    return o;
  }
};

// The estimators own fixed buffers and are not copyable; std::function needs copies.
template <class M>
kt::Method wrap(std::shared_ptr<M> m) {
  return [m](const kt::SimFrame& f) { return (*m)(f); };
}

struct Scenario {
  std::string name;
  kt::SimConfig cfg;
};

std::vector<Scenario> scenarios() {
  std::vector<Scenario> s;
  for (double f : {0.0, 0.1, 0.3, 0.5, 0.7}) {
    Scenario sc;
    sc.name = "uniform outliers " + std::to_string(int(f * 100 + 0.5)) + " %";
    sc.cfg.outlier_frac = f;
    s.push_back(sc);
  }
  for (double f : {0.3, 0.5, 0.7}) {
    Scenario sc;
    sc.name = "structured outliers " + std::to_string(int(f * 100 + 0.5)) + " % (2/3 one moving object)";
    sc.cfg.outlier_frac = f;
    sc.cfg.structured = true;
    s.push_back(sc);
  }
  {
    Scenario sc;
    sc.name = "uniform 50 %, match cost uninformative";
    sc.cfg.outlier_frac = 0.5;
    sc.cfg.outlier_cost_mean = sc.cfg.inlier_cost_mean;
    sc.cfg.outlier_cost_sd = sc.cfg.inlier_cost_sd;
    s.push_back(sc);
  }
  for (double e : {1.0, 2.0}) {
    Scenario sc;
    sc.name = "uniform 30 %, IMU rotation error " + std::to_string(int(e)) + "-" +
              std::to_string(int(e) + 1) + " deg";
    sc.cfg.outlier_frac = 0.3;
    sc.cfg.imu_err_min_deg = e;
    sc.cfg.imu_err_max_deg = e + 1.0;
    s.push_back(sc);
  }
  return s;
}

void print_table(int trials) {
  std::printf("# bench_lonsc: %d trials per scenario, 300 correspondences, 640x480 f=525, depth 0.5-5 m,\n",
              trials);
  std::printf(
      "# sigma_z = 0.0025 z^2, pixel noise 0.7 px, motion <= 5 deg / 5 cm, IMU error 0.1-0.3 deg unless "
      "noted,\n");
  std::printf("# threshold 3 px for every method. Medians over trials; 'bad' = failed or t error > 2 cm.\n");
  {
    // Options print themselves (OpenVINS habit): the table is reproducible from its header.
    std::ostringstream ss;
    ss << "# options: " << kc::LonscOptions{} << "\n#          " << kc::RansacOptions{} << "\n#          "
       << kc::PoseRefineOptions{};
    std::printf("%s\n", ss.str().c_str());
  }
  uint64_t base = 1000;
  for (const Scenario& sc : scenarios()) {
    std::printf("\n### %s\n\n", sc.name.c_str());
    kt::print_header(stdout);
    struct Row {
      std::string name;
      kt::Method m;
    };
    const kc::LonscOptions paper = kc::LonscOptions::paper();
    kc::LonscOptions longest_only;
    longest_only.candidate_runs = 1;
    kc::LonscOptions pair_model;
    pair_model.grow_model = false;
    std::vector<Row> rows;
    rows.push_back({"LONSC by_match_cost",
                    wrap(std::make_shared<kt::LonscMethod>(kc::CorrespondenceOrder::kByMatchCost, false))});
    rows.push_back({"LONSC by_match_cost + GN(4)",
                    wrap(std::make_shared<kt::LonscMethod>(kc::CorrespondenceOrder::kByMatchCost, true))});
    rows.push_back({"LONSC as_given (raster)",
                    wrap(std::make_shared<kt::LonscMethod>(kc::CorrespondenceOrder::kAsGiven, false))});
    rows.push_back(
        {"LONSC hilbert", wrap(std::make_shared<kt::LonscMethod>(kc::CorrespondenceOrder::kHilbert, false))});
    rows.push_back({"LONSC shuffled",
                    wrap(std::make_shared<kt::LonscMethod>(kc::CorrespondenceOrder::kShuffled, false))});
    rows.push_back({"LONSC by_match_cost, longest run only",
                    wrap(std::make_shared<kt::LonscMethod>(kc::CorrespondenceOrder::kByMatchCost, false,
                                                           longest_only))});
    rows.push_back(
        {"LONSC by_match_cost, 2-pt run model",
         wrap(std::make_shared<kt::LonscMethod>(kc::CorrespondenceOrder::kByMatchCost, false, pair_model))});
    rows.push_back(
        {"LONSC paper-literal, by_match_cost",
         wrap(std::make_shared<kt::LonscMethod>(kc::CorrespondenceOrder::kByMatchCost, false, paper))});
    rows.push_back({"RANSAC 2-pt (IMU R)", wrap(std::make_shared<kt::RansacMethod>(false))});
    rows.push_back({"RANSAC 2-pt + GN(4)", wrap(std::make_shared<kt::RansacMethod>(true))});
    rows.push_back({"OpenCV solvePnPRansac ITERATIVE",
                    wrap(std::make_shared<OpenCvPnpMethod>(cv::SOLVEPNP_ITERATIVE, false))});
    rows.push_back({"OpenCV solvePnPRansac AP3P + LM",
                    wrap(std::make_shared<OpenCvPnpMethod>(cv::SOLVEPNP_AP3P, true))});
    for (auto& r : rows) {
      // Warm caches and lazily initialised OpenCV state once, untimed.
      kt::run_trials(sc.cfg, r.m, 2, base + 999999);
      kt::print_row(stdout, kt::summarize(r.name, kt::run_trials(sc.cfg, r.m, trials, base)));
    }
    std::fflush(stdout);
    base += 10000;
  }
}

// ---- Google Benchmark: per-call time on one fixed 30 % frame ---------------

const kt::SimFrame& frame30() {
  static const kt::SimFrame f = [] {
    kt::SimConfig cfg;
    cfg.outlier_frac = 0.3;
    return kt::simulate(cfg, 77);
  }();
  return f;
}
const kt::SimFrame& frame(int pct) {
  static kt::SimFrame fs[10];
  static bool made[10] = {};
  const int k = pct / 10;
  if (!made[k]) {
    kt::SimConfig cfg;
    cfg.outlier_frac = pct / 100.0;
    fs[k] = kt::simulate(cfg, 77 + static_cast<uint64_t>(pct));
    made[k] = true;
  }
  return fs[k];
}

void BM_LonscByCost(benchmark::State& st) {
  const kt::SimFrame& f = frame(static_cast<int>(st.range(0)));
  kc::LonscEstimator est(1024);
  kc::CorrespondenceOrderer ord(1024);
  std::vector<uint32_t> order(1024);
  for (auto _ : st) {
    ord.order(kc::CorrespondenceOrder::kByMatchCost, f.c.data(), f.c.size(), order.data());
    auto r = est.estimate(f.R_imu, kt::kinect_k(), f.c.data(), f.c.size(), order.data());
    benchmark::DoNotOptimize(r);
  }
}
void BM_LonscAsGiven(benchmark::State& st) {
  const kt::SimFrame& f = frame(static_cast<int>(st.range(0)));
  kc::LonscEstimator est(1024);
  for (auto _ : st) {
    auto r = est.estimate(f.R_imu, kt::kinect_k(), f.c.data(), f.c.size());
    benchmark::DoNotOptimize(r);
  }
}
void BM_Ransac2pt(benchmark::State& st) {
  const kt::SimFrame& f = frame(static_cast<int>(st.range(0)));
  kc::TwoPointRansac est(1024);
  for (auto _ : st) {
    auto r = est.estimate(f.R_imu, kt::kinect_k(), f.c.data(), f.c.size());
    benchmark::DoNotOptimize(r);
  }
}
void BM_GaussNewton4(benchmark::State& st) {
  const kt::SimFrame& f = frame30();
  kc::LonscEstimator est(1024);
  const auto r = est.estimate(f.R_imu, kt::kinect_k(), f.c.data(), f.c.size());
  for (auto _ : st) {
    Eigen::Matrix3d R = f.R_imu;
    Eigen::Vector3d t = r.t;
    auto res = kc::refine_pose_gauss_newton(&R, &t, kt::kinect_k(), f.c.data(), f.c.size(),
                                            est.inlier_indices(), r.num_inliers);
    benchmark::DoNotOptimize(res);
  }
}
void BM_OpenCvPnpRansac(benchmark::State& st) {
  const kt::SimFrame& f = frame(static_cast<int>(st.range(0)));
  OpenCvPnpMethod m(cv::SOLVEPNP_ITERATIVE, false);
  for (auto _ : st) {
    auto o = m(f);
    benchmark::DoNotOptimize(o);
  }
}
BENCHMARK(BM_LonscByCost)->Arg(0)->Arg(30)->Arg(50)->Arg(70)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_LonscAsGiven)->Arg(30)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_Ransac2pt)->Arg(0)->Arg(30)->Arg(50)->Arg(70)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_GaussNewton4)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_OpenCvPnpRansac)->Arg(30)->Unit(benchmark::kMicrosecond);

}  // namespace

int main(int argc, char** argv) {
  int trials = 200;
  bool table = true, bench = true;
  std::vector<char*> rest;
  for (int i = 0; i < argc; ++i) {
    if (i > 0 && std::strncmp(argv[i], "--trials=", 9) == 0) {
      trials = std::max(1, std::atoi(argv[i] + 9));
    } else if (i > 0 && std::strcmp(argv[i], "--table_only") == 0) {
      bench = false;
    } else if (i > 0 && std::strcmp(argv[i], "--no_table") == 0) {
      table = false;
    } else {
      rest.push_back(argv[i]);
    }
  }
  cv::setNumThreads(1);  // single-core comparison, like the tracking thread
  if (table) print_table(trials);
  if (!bench) return 0;
  int n = static_cast<int>(rest.size());
  benchmark::Initialize(&n, rest.data());
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}

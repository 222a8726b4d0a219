// Ours vs Ceres on identical sliding-window problems (S=3,N=5 and S=2,N=3),
// plus a per-keyframe latency table (p50/p99) over a sliding synthetic flight.
//   bench_window [--frames=400] [google benchmark flags]
#include <benchmark/benchmark.h>

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "kestrel/core/ceres_window.hpp"
#include "kestrel/core/window_optimizer.hpp"
#include "window_sim.hpp"

namespace {

using namespace kestrel;
using core::NavState;
using core::WindowOptimizer;
using core::WindowOptions;

int g_frames = 400;

// A window after sliding through 24 frames (prior active), newest frame perturbed.
struct Snapshot {
  std::vector<test::SimFrame> frames;
  std::unique_ptr<WindowOptimizer> w;
  std::vector<NavState> xs;
  std::vector<Eigen::Vector3d> ls;

  Snapshot(int S, int N) {
    test::SimConfig c;
    c.seed = 90 + S * 10 + N;
    test::SimWorld world(c);
    frames = world.frames(24, 0.0);
    WindowOptions o = test::sim_options(S, N);
    o.time_budget_ms = 1e4;
    w = std::make_unique<WindowOptimizer>(test::sim_K(), test::sim_T_BC(), o);
    std::mt19937_64 rng(5);
    for (std::size_t k = 0; k < frames.size(); ++k) {
      w->add_frame(
          test::frame_input(frames[k], test::perturb(frames[k].truth, rng, 0.03, 0.017, k == 0), k == 0));
      if (k + 1 < frames.size()) w->optimize_ours();
    }
    save();
  }
  void save() {
    const core::WindowProblem& P = w->problem();
    for (const auto& s : P.states) xs.push_back(s.x);
    for (const auto& l : P.lms) ls.push_back(l.p_W);
  }
  void restore() {
    core::WindowProblem& P = w->problem();
    for (std::size_t i = 0; i < xs.size(); ++i) P.states[i].x = xs[i];
    for (std::size_t i = 0; i < ls.size(); ++i) P.lms[i].p_W = ls[i];
  }
};

void BM_Solve(benchmark::State& state) {
  const int S = static_cast<int>(state.range(0)), N = static_cast<int>(state.range(1));
  const bool ceres = state.range(2) != 0;
  Snapshot snap(S, N);
  double iters = 0, ms = 0, n = 0;
  for (auto _ : state) {
    state.PauseTiming();
    snap.restore();
    state.ResumeTiming();
    const WindowOptimizer::Result r =
        ceres ? core::solve_window_ceres(snap.w->problem()) : snap.w->optimize_ours();
    benchmark::DoNotOptimize(r.cost_final);
    iters += r.iterations;
    ms += r.solve_ms;
    n += 1;
  }
  state.counters["iterations"] = iters / std::max(1.0, n);
  state.counters["solve_ms"] = ms / std::max(1.0, n);
  state.counters["landmarks"] = snap.w->num_landmarks();
  state.SetLabel(std::string(ceres ? "ceres" : "ours") + " S=" + std::to_string(S) +
                 " N=" + std::to_string(N));
}
BENCHMARK(BM_Solve)->Args({3, 5, 0})->Args({3, 5, 1})->Args({2, 3, 0})->Args({2, 3, 1})->Unit(
    benchmark::kMillisecond);

struct Lat {
  double p50 = 0, p99 = 0, mean = 0, ate = 0;
};

Lat sliding(int S, int N, WindowOptions::Solver solver, int n_frames) {
  test::SimConfig c;
  c.seed = 51;
  test::SimWorld world(c);
  const std::vector<test::SimFrame> frames = world.frames(n_frames, 0.0);
  WindowOptions o = test::sim_options(S, N);
  o.solver = solver;
  WindowOptimizer w(test::sim_K(), test::sim_T_BC(), o);
  std::mt19937_64 rng(77);
  std::vector<double> ms;
  double se = 0;
  for (std::size_t k = 0; k < frames.size(); ++k) {
    const NavState g = k == 0 ? test::perturb(frames[0].truth, rng, 0.0, 0.01, true)
                              : core::predict(w.latest(), frames[k].pim);
    w.add_frame(test::frame_input(frames[k], g, k == 0));
    const WindowOptimizer::Result r = w.optimize();
    if (frames[k].keyframe) ms.push_back(r.solve_ms);
    se += (w.latest().p_WB - frames[k].truth.p_WB).squaredNorm();
  }
  std::sort(ms.begin(), ms.end());
  Lat l;
  l.p50 = ms[ms.size() / 2];
  l.p99 = ms[std::min(ms.size() - 1, static_cast<std::size_t>(0.99 * ms.size()))];
  for (double m : ms) l.mean += m / ms.size();
  l.ate = std::sqrt(se / frames.size());
  return l;
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<char*> args;
  for (int i = 0; i < argc; ++i) {
    if (std::strncmp(argv[i], "--frames=", 9) == 0) {
      g_frames = std::max(20, std::atoi(argv[i] + 9));
    } else {
      args.push_back(argv[i]);
    }
  }
  int n = static_cast<int>(args.size());
  benchmark::Initialize(&n, args.data());
  benchmark::RunSpecifiedBenchmarks();
  std::printf(
      "\nSliding synthetic flight, %d frames at 20 fps (10 keyframes/s), default options "
      "(max_iterations 8, budget 35 ms); optimizer latency per keyframe:\n",
      g_frames);
  std::printf("%-6s %-6s %10s %10s %10s %10s\n", "window", "solver", "p50_ms", "p99_ms", "mean_ms", "ATE_m");
  for (const auto& sn : {std::pair<int, int>{3, 5}, std::pair<int, int>{2, 3}}) {
    for (const auto solver : {WindowOptions::Solver::kOurs, WindowOptions::Solver::kCeres}) {
      const Lat l = sliding(sn.first, sn.second, solver, g_frames);
      std::printf("S%dN%d   %-6s %10.3f %10.3f %10.3f %10.4f\n", sn.first, sn.second,
                  solver == WindowOptions::Solver::kOurs ? "ours" : "ceres", l.p50, l.p99, l.mean, l.ate);
    }
  }
  return 0;
}

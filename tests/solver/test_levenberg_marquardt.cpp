// The loop's rules (levenberg_marquardt.hpp) one at a time, on a problem that
// replays scripted steps, then both rule sets on a small curve fit. The window
// and the bundle adjustment are checked through the loop by their own tests
// (tests/window, tests/map: against Ceres' minimum).
#include <gtest/gtest.h>

#include <array>
#include <chrono>
#include <cmath>
#include <thread>
#include <vector>

#include "kestrel/core/levenberg_marquardt.hpp"
#include "kestrel/rt/alloc_counter.hpp"

namespace kestrel::core {
namespace {

struct Scripted {
  struct Attempt {
    bool solved = true;
    double predicted = 1.0;
    bool negligible = false;
    double new_cost = 0.0;
  };
  std::vector<Attempt> script;
  std::size_t next = 0;
  Attempt current;
  std::vector<double> lambdas;
  int linearized = 0, tried = 0, accepted = 0, rejected = 0;
  std::chrono::milliseconds solve_sleep{0};

  void linearize() { ++linearized; }
  bool solve(double lambda, lm::Step* step) {
    lambdas.push_back(lambda);
    current = script.at(next++);
    step->predicted_decrease = current.predicted;
    step->negligible = current.negligible;
    if (solve_sleep.count() > 0) std::this_thread::sleep_for(solve_sleep);
    return current.solved;
  }
  double try_step() {
    ++tried;
    return current.new_cost;
  }
  void accept() { ++accepted; }
  void reject() { ++rejected; }
};

lm::Rules window_rules() {
  lm::Rules r;
  r.max_iterations = 10;
  r.function_tolerance = 1e-10;
  return r;
}

// The bundle adjustment's (Ceres') rules.
lm::Rules ceres_rules() {
  lm::Rules r;
  r.max_iterations = 10;
  r.min_lambda = 1e-16;
  r.max_lambda = 1e32;
  r.min_relative_decrease = 1e-3;
  r.function_tolerance = 1e-6;
  r.function_tolerance_on_rejected_steps = true;
  r.min_model_decrease = 1e-12;
  r.try_negligible_step = false;
  return r;
}

TEST(LevenbergMarquardt, DampingFollowsNielsen) {
  Scripted p;
  // Rejected, rejected (nu doubles each time), taken at rho = 1 (lambda / 3,
  // nu back to 2), rejected, then the iterations run out.
  p.script = std::vector<Scripted::Attempt>{{true, 1.0, false, 20.0},
                                            {true, 1.0, false, 20.0},
                                            {true, 1.0, false, 9.0},
                                            {true, 1.0, false, 20.0},
                                            {true, 1.0, false, 20.0}};
  lm::Rules r = window_rules();
  r.max_iterations = 5;
  const lm::Outcome out = lm::minimize(p, 10.0, r);
  ASSERT_EQ(p.lambdas.size(), 5u);
  EXPECT_DOUBLE_EQ(p.lambdas[0], 1e-4);
  EXPECT_DOUBLE_EQ(p.lambdas[1], 2e-4);
  EXPECT_DOUBLE_EQ(p.lambdas[2], 8e-4);
  EXPECT_DOUBLE_EQ(p.lambdas[3], 8e-4 / 3.0);
  EXPECT_DOUBLE_EQ(p.lambdas[4], 8e-4 / 3.0 * 2.0);
  EXPECT_EQ(out.stop, lm::Stop::kMaxIterations);
  EXPECT_EQ(out.iterations, 5);
  EXPECT_EQ(out.cost, 9.0);
  EXPECT_EQ(p.accepted, 1);
  EXPECT_EQ(p.rejected, 4);
  EXPECT_EQ(p.linearized, 2);  // at the start and after the step taken
}

TEST(LevenbergMarquardt, DampingIsClampedBelow) {
  Scripted p;
  p.script.assign(10, {true, 1.0, false, 0.0});
  double cost = 1e6;
  for (auto& a : p.script) a.new_cost = (cost *= 0.5);  // rho = actual / 1: large, so lambda / 3 each time
  lm::Rules r = window_rules();
  r.min_lambda = 1e-5;
  r.function_tolerance = 0;
  lm::minimize(p, 1e6, r);
  EXPECT_DOUBLE_EQ(p.lambdas[1], 1e-4 / 3.0);
  EXPECT_DOUBLE_EQ(p.lambdas.back(), 1e-5);
}

TEST(LevenbergMarquardt, WindowRulesTakeAnyDecreaseCeresRulesWantTheModelsAgreement) {
  // The model predicts no decrease, yet the cost falls.
  {
    Scripted p;
    p.script = std::vector<Scripted::Attempt>{{true, -1.0, false, 9.0}, {true, 1.0, false, 9.0}};
    lm::Rules r = window_rules();
    r.max_iterations = 1;
    const lm::Outcome out = lm::minimize(p, 10.0, r);
    EXPECT_EQ(p.tried, 1);
    EXPECT_EQ(p.accepted, 1);
    EXPECT_EQ(out.cost, 9.0);
  }
  {
    Scripted p;
    p.script = std::vector<Scripted::Attempt>{{true, -1.0, false, 9.0}, {true, 1.0, false, 9.0}};
    lm::Rules r = ceres_rules();
    r.max_iterations = 2;
    const lm::Outcome out = lm::minimize(p, 10.0, r);
    EXPECT_EQ(p.tried, 1);  // only the second: the first is not tried
    EXPECT_DOUBLE_EQ(p.lambdas[1], 2e-4);
    EXPECT_EQ(out.cost, 9.0);
  }
  // A decrease of 1e-4 of the predicted one: taken by the window's rules,
  // refused by Ceres' (1e-3).
  for (const bool ceres : {false, true}) {
    Scripted p;
    p.script = std::vector<Scripted::Attempt>{{true, 1.0, false, 10.0 - 1e-4}};
    lm::Rules r = ceres ? ceres_rules() : window_rules();
    r.max_iterations = 1;
    r.function_tolerance = 0;
    lm::minimize(p, 10.0, r);
    EXPECT_EQ(p.accepted, ceres ? 0 : 1) << (ceres ? "ceres" : "window");
  }
}

TEST(LevenbergMarquardt, NegligibleStepEndsTheSolveTriedOrNot) {
  for (const bool try_it : {true, false}) {
    Scripted p;
    p.script = std::vector<Scripted::Attempt>{{true, 1.0, true, 9.5}, {true, 1.0, false, 1.0}};
    lm::Rules r = window_rules();
    r.try_negligible_step = try_it;
    const lm::Outcome out = lm::minimize(p, 10.0, r);
    EXPECT_EQ(out.stop, lm::Stop::kConverged);
    EXPECT_EQ(out.iterations, 1);
    EXPECT_EQ(p.tried, try_it ? 1 : 0);
    EXPECT_EQ(out.cost, try_it ? 9.5 : 10.0);
  }
  // Tried and refused: still the end.
  Scripted p;
  p.script = std::vector<Scripted::Attempt>{{true, 1.0, true, 11.0}, {true, 1.0, false, 1.0}};
  const lm::Outcome out = lm::minimize(p, 10.0, window_rules());
  EXPECT_EQ(out.stop, lm::Stop::kConverged);
  EXPECT_EQ(p.rejected, 1);
  EXPECT_EQ(out.cost, 10.0);
}

TEST(LevenbergMarquardt, FunctionToleranceOnTakenAndOptionallyRejectedSteps) {
  // Taken: a decrease of 1e-12 of the cost ends the solve.
  {
    Scripted p;
    p.script = std::vector<Scripted::Attempt>{{true, 1e-12, false, 10.0 - 1e-11}, {true, 1.0, false, 1.0}};
    const lm::Outcome out = lm::minimize(p, 10.0, window_rules());
    EXPECT_EQ(out.stop, lm::Stop::kConverged);
    EXPECT_EQ(p.accepted, 1);
  }
  // Rejected (the cost rose by 1e-7 of itself): Ceres' rules stop, the
  // window's go on with more damping.
  for (const bool ceres : {false, true}) {
    Scripted p;
    p.script = std::vector<Scripted::Attempt>{{true, 1.0, false, 10.0 + 1e-6}, {true, 1.0, false, 1.0}};
    lm::Rules r = ceres ? ceres_rules() : window_rules();
    r.max_iterations = 2;
    const lm::Outcome out = lm::minimize(p, 10.0, r);
    EXPECT_EQ(out.iterations, ceres ? 1 : 2) << (ceres ? "ceres" : "window");
    EXPECT_EQ(out.cost, ceres ? 10.0 : 1.0);
  }
}

TEST(LevenbergMarquardt, ModelWithNothingToGainEndsCeresSolve) {
  Scripted p;
  p.script = std::vector<Scripted::Attempt>{{true, 1e-12, false, 5.0}};
  const lm::Outcome out = lm::minimize(p, 10.0, ceres_rules());
  EXPECT_EQ(out.stop, lm::Stop::kConverged);
  EXPECT_EQ(p.tried, 0);
}

TEST(LevenbergMarquardt, FailedSolvesDampMoreUntilNoProgress) {
  Scripted p;
  p.script.assign(20, {false, 0.0, false, 0.0});
  lm::Rules r = window_rules();
  r.max_iterations = 20;
  r.max_lambda = 1.0;  // 1e-4 * 2 * 4 * 8 * 16 * 32 > 1 after five failures
  const lm::Outcome out = lm::minimize(p, 10.0, r);
  EXPECT_EQ(out.stop, lm::Stop::kNoProgress);
  EXPECT_EQ(out.iterations, 5);
  EXPECT_EQ(p.tried, 0);
  EXPECT_EQ(out.cost, 10.0);
}

TEST(LevenbergMarquardt, NonFiniteCostIsRefused) {
  Scripted p;
  p.script = std::vector<Scripted::Attempt>{{true, 1.0, false, NAN}, {true, 1.0, false, 9.0}};
  lm::Rules r = ceres_rules();  // a NaN must not count as within tolerance either
  r.max_iterations = 2;
  const lm::Outcome out = lm::minimize(p, 10.0, r);
  EXPECT_EQ(p.rejected, 1);
  EXPECT_EQ(p.accepted, 1);
  EXPECT_EQ(out.cost, 9.0);
}

TEST(LevenbergMarquardt, TimeBudgetStopsAfterTheIterationThatSpentIt) {
  Scripted p;
  p.script.assign(5, {true, 1.0, false, 20.0});
  p.solve_sleep = std::chrono::milliseconds(5);
  lm::Rules r = window_rules();
  r.time_budget_ms = 1.0;
  const lm::Outcome out = lm::minimize(p, 10.0, r);
  EXPECT_EQ(out.stop, lm::Stop::kTimeBudget);
  EXPECT_EQ(out.iterations, 1);
}

// y = a exp(b t) on noisy samples: both rule sets reach the same minimum,
// with a zero gradient there, and the loop allocates nothing.
struct ExpFit {
  static constexpr int kN = 20;
  std::array<double, kN> t{}, y{};
  std::array<double, 2> x{1.0, 0.0}, cand{}, dx{}, g{}, D{};
  std::array<double, 4> H{};  // row-major 2x2

  ExpFit() {
    for (int i = 0; i < kN; ++i) {
      t[i] = i / (kN - 1.0);
      y[i] = 2.0 * std::exp(-1.5 * t[i]) + 0.01 * std::sin(7.0 * i);
    }
  }
  double cost_at(const std::array<double, 2>& v) const {
    double c = 0;
    for (int i = 0; i < kN; ++i) {
      const double r = v[0] * std::exp(v[1] * t[i]) - y[i];
      c += 0.5 * r * r;
    }
    return c;
  }
  void linearize() {
    H = {};
    g = {};
    for (int i = 0; i < kN; ++i) {
      const double e = std::exp(x[1] * t[i]);
      const double r = x[0] * e - y[i];
      const double j0 = e, j1 = x[0] * t[i] * e;
      H[0] += j0 * j0;
      H[1] += j0 * j1;
      H[3] += j1 * j1;
      g[0] += j0 * r;
      g[1] += j1 * r;
    }
    H[2] = H[1];
    for (int k = 0; k < 2; ++k) D[k] = std::fmin(std::fmax(H[3 * k], 1e-6), 1e32);
  }
  bool solve(double lambda, lm::Step* step) {
    const double a = H[0] + lambda * D[0], b = H[1], d = H[3] + lambda * D[1];
    const double det = a * d - b * b;
    if (!(det > 0)) return false;
    dx = {(-g[0] * d + g[1] * b) / det, (-g[1] * a + g[0] * b) / det};
    step->predicted_decrease =
        0.5 * (-(g[0] * dx[0] + g[1] * dx[1]) + lambda * (D[0] * dx[0] * dx[0] + D[1] * dx[1] * dx[1]));
    step->negligible = std::hypot(dx[0], dx[1]) <= 1e-12 * (std::hypot(x[0], x[1]) + 1e-12);
    return true;
  }
  double try_step() {
    cand = {x[0] + dx[0], x[1] + dx[1]};
    return cost_at(cand);
  }
  void accept() { x = cand; }
  void reject() {}
};

TEST(LevenbergMarquardt, BothRuleSetsReachTheSameMinimumWithoutAllocating) {
  ExpFit window_fit, ceres_fit;
  lm::Rules wr = window_rules(), cr = ceres_rules();
  wr.max_iterations = cr.max_iterations = 100;
  wr.function_tolerance = cr.function_tolerance = 1e-14;
  rt::AllocCountScope allocs;
  const lm::Outcome wo = lm::minimize(window_fit, window_fit.cost_at(window_fit.x), wr);
  const lm::Outcome co = lm::minimize(ceres_fit, ceres_fit.cost_at(ceres_fit.x), cr);
  EXPECT_EQ(allocs.count(), 0u);
  EXPECT_EQ(wo.stop, lm::Stop::kConverged);
  EXPECT_EQ(co.stop, lm::Stop::kConverged);
  EXPECT_NEAR(window_fit.x[0], 2.0, 0.02);
  EXPECT_NEAR(window_fit.x[1], -1.5, 0.05);
  EXPECT_NEAR(window_fit.x[0], ceres_fit.x[0], 1e-6);
  EXPECT_NEAR(window_fit.x[1], ceres_fit.x[1], 1e-6);
  EXPECT_DOUBLE_EQ(wo.cost, window_fit.cost_at(window_fit.x));
  window_fit.linearize();
  EXPECT_LT(std::hypot(window_fit.g[0], window_fit.g[1]), 1e-6);
}

}  // namespace
}  // namespace kestrel::core

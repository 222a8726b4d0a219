// One Levenberg-Marquardt loop for every least-squares problem of core: the
// sliding window (window_optimizer.cpp) and the map's bundle adjustment
// (bundle_adjustment.cpp). The loop owns the trust region (the damping, its
// Nielsen update, the stops and the time budget); the problem owns its
// unknowns, its linearisation and its damped Schur solve.
//
// The two problems keep the rules each was tuned and tested with (Rules
// below, docs/optimizer.md "One loop"): the window takes any step that lowers
// the cost, the bundle adjustment follows Ceres' rules so that it lands on
// Ceres' minimum. Both are options of this one loop rather than two loops.
//
// A Problem provides, with no allocation (the loop allocates nothing either):
//   void linearize();        // Jacobians at the current estimate
//   bool solve(double lambda, lm::Step* step);
//                            // (J'J + lambda D) dx = -J'r; false: no usable step
//   double try_step();       // the cost at the estimate moved by the step
//   void accept();           // the tried step becomes the estimate
//   void reject();           // the estimate stays what it was before try_step()
#pragma once

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>

namespace kestrel::core::lm {

struct Rules {
  int max_iterations = 8;
  // Wall-clock bound of one minimize() in ms, checked after each iteration;
  // <= 0: none.
  double time_budget_ms = 0;
  // The damping scales the diagonal of J'J: lambda = 1 / Ceres' trust radius.
  double initial_lambda = 1e-4;
  double min_lambda = 1e-12;
  // Past this, no step can lower the cost: the solve stops (kNoProgress).
  double max_lambda = 1e16;
  // A tried step is taken when the cost falls and its actual / predicted
  // decrease exceeds this. Negative: any decrease is taken, even where the
  // model predicted none. Not negative: a step the model predicts no
  // decrease for is not tried.
  double min_relative_decrease = -1;
  // Converged when a step changes the cost by at most this fraction of it:
  // on taken steps, and also on rejected ones when
  // function_tolerance_on_rejected_steps (Ceres).
  double function_tolerance = 1e-10;
  bool function_tolerance_on_rejected_steps = false;
  // Converged when the model predicts a decrease of at most this fraction of
  // the cost, before the step is tried (Ceres' gradient-side stop). Negative:
  // off.
  double min_model_decrease = -1;
  // A negligible step (Step::negligible, the problem's own measure) ends the
  // solve as converged. true: it is tried first and taken if it lowers the
  // cost; false (Ceres): it is not tried.
  bool try_negligible_step = true;
};

// What the problem's damped solve reports besides the step itself.
struct Step {
  double predicted_decrease = 0;  // of the model, at this damping
  bool negligible = false;        // too small to change the unknowns
};

enum class Stop : std::uint8_t { kConverged, kMaxIterations, kTimeBudget, kNoProgress };

inline const char* to_string(Stop s) {
  switch (s) {
    case Stop::kConverged:
      return "converged";
    case Stop::kMaxIterations:
      return "max_iterations";
    case Stop::kTimeBudget:
      return "time_budget";
    case Stop::kNoProgress:
      return "no_progress";
  }
  return "?";
}

struct Outcome {
  Stop stop = Stop::kMaxIterations;
  int iterations = 0;  // damped solves, taken or not
  double cost = 0;     // at the estimate the problem holds on return
};

// cost: the problem's cost at its current estimate. t0: when the solve's
// time budget started (the caller's set-up counts against it).
template <class Problem>
Outcome minimize(Problem& problem, double cost, const Rules& rules,
                 std::chrono::steady_clock::time_point t0 = std::chrono::steady_clock::now()) {
  const auto over_budget = [&] {
    return rules.time_budget_ms > 0 &&
           std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count() >
               rules.time_budget_ms;
  };
  Outcome out;
  out.cost = cost;
  double lambda = rules.initial_lambda, nu = 2.0;
  // Nielsen's rule: more damping after each failure, growing geometrically
  // while they last.
  const auto damp_more = [&] {
    lambda *= nu;
    nu *= 2.0;
    return lambda <= rules.max_lambda;
  };
  bool linearize = true;
  const bool model_must_agree = rules.min_relative_decrease >= 0;
  // Tries the solved step, takes or refuses it; true when that ends the solve.
  const auto try_step = [&](const Step& step) {
    const double new_cost = problem.try_step();
    const double actual = out.cost - new_cost;
    const double rho = step.predicted_decrease > 0 ? actual / step.predicted_decrease : 0.0;
    const bool tolerance = std::isfinite(new_cost) && std::abs(actual) <= rules.function_tolerance * out.cost;
    if (std::isfinite(new_cost) && actual > 0.0 && (!model_must_agree || rho > rules.min_relative_decrease)) {
      problem.accept();
      const double t = 2.0 * rho - 1.0;
      lambda = std::max(rules.min_lambda, lambda * std::max(1.0 / 3.0, 1.0 - t * t * t));
      nu = 2.0;
      out.cost = new_cost;
      linearize = true;
      if (tolerance || step.negligible) out.stop = Stop::kConverged;
      return tolerance || step.negligible;
    }
    problem.reject();
    if (step.negligible || (tolerance && rules.function_tolerance_on_rejected_steps)) {
      out.stop = Stop::kConverged;
      return true;
    }
    if (damp_more()) return false;
    out.stop = Stop::kNoProgress;
    return true;
  };
  while (out.iterations < rules.max_iterations) {
    if (linearize) {
      problem.linearize();
      linearize = false;
    }
    ++out.iterations;
    Step step;
    const bool solved = problem.solve(lambda, &step);
    if (solved && !rules.try_negligible_step && step.negligible) {
      out.stop = Stop::kConverged;
      break;
    }
    if (solved && rules.min_model_decrease >= 0 &&
        std::abs(step.predicted_decrease) <= rules.min_model_decrease * out.cost) {
      out.stop = Stop::kConverged;
      break;
    }
    if (!solved || (model_must_agree && !(step.predicted_decrease > 0))) {
      if (!damp_more()) {
        out.stop = Stop::kNoProgress;
        break;
      }
    } else if (try_step(step)) {
      break;
    }
    if (over_budget()) {
      out.stop = Stop::kTimeBudget;
      break;
    }
  }
  return out;
}

}  // namespace kestrel::core::lm

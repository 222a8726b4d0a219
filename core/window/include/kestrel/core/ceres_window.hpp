// The sliding-window problem (window_problem.hpp) solved by Ceres 2.1: the
// same residual functions wrapped as analytic ceres::CostFunctions, the same
// right-perturbation tangent on SO(3) (a ceres::Manifold), the same gauge and
// marginalisation prior (as a residual e + J dx). Used as the reference in the
// cross-check tests and as the selectable solver `solver: ceres`. It builds a
// ceres::Problem per call, so unlike ours it allocates.
#pragma once

#include "kestrel/core/window_optimizer.hpp"
#include "kestrel/core/window_problem.hpp"

namespace kestrel::core {

struct CeresWindowOptions {
  // <= 0: take WindowOptions' max_iterations / time_budget_ms / function_tolerance.
  int max_iterations = 0;
  double time_budget_ms = 0;
  double function_tolerance = 0;
  double gradient_tolerance = 1e-14;
  double parameter_tolerance = 1e-12;
};

// Solves in place (states and landmark positions of P are updated).
WindowOptimizer::Result solve_window_ceres(WindowProblem& P, const CeresWindowOptions& o = {});

// Ceres' evaluation of the cost at P's current estimates (0.5 sum rho + priors).
double ceres_window_cost(const WindowProblem& P);

}  // namespace kestrel::core

// One shared checker for every analytic Jacobian in the project (STYLE.md:
// "every Jacobian has a numerical test that fails"). Residuals on manifolds
// are checked through their own perturbation: the caller supplies
// r(delta) = residual(x [+] delta), and the checker differentiates that
// numerically around delta = 0 with central differences.
#pragma once

#include <gtest/gtest.h>

#include <Eigen/Core>
#include <cmath>
#include <functional>
#include <sstream>

namespace kestrel::test {

inline Eigen::MatrixXd numeric_jacobian(
    const std::function<Eigen::VectorXd(const Eigen::VectorXd&)>& r_of_delta, int delta_dim,
    double h = 1e-6) {
  const Eigen::VectorXd r0 = r_of_delta(Eigen::VectorXd::Zero(delta_dim));
  Eigen::MatrixXd J(r0.size(), delta_dim);
  for (int i = 0; i < delta_dim; ++i) {
    Eigen::VectorXd d = Eigen::VectorXd::Zero(delta_dim);
    d[i] = h;
    const Eigen::VectorXd rp = r_of_delta(d);
    d[i] = -h;
    const Eigen::VectorXd rm = r_of_delta(d);
    J.col(i) = (rp - rm) / (2.0 * h);
  }
  return J;
}

// Passes when every entry agrees within abs_tol + rel_tol * max|J_numeric|;
// on failure prints both matrices and the worst entry.
inline ::testing::AssertionResult jacobian_matches(const Eigen::MatrixXd& analytic,
                                                   const Eigen::MatrixXd& numeric, double rel_tol = 1e-5,
                                                   double abs_tol = 1e-7) {
  if (analytic.rows() != numeric.rows() || analytic.cols() != numeric.cols()) {
    return ::testing::AssertionFailure() << "Jacobian size " << analytic.rows() << "x" << analytic.cols()
                                         << " but numeric is " << numeric.rows() << "x" << numeric.cols();
  }
  if (!analytic.allFinite())
    return ::testing::AssertionFailure() << "analytic Jacobian has non-finite entries";
  const double scale = numeric.cwiseAbs().maxCoeff();
  const double tol = abs_tol + rel_tol * scale;
  Eigen::Index r = 0, c = 0;
  const double worst = (analytic - numeric).cwiseAbs().maxCoeff(&r, &c);
  if (worst <= tol) return ::testing::AssertionSuccess();
  std::ostringstream s;
  s << "Jacobian mismatch: worst |diff| " << worst << " at (" << r << "," << c << ") > tol " << tol
    << "\nanalytic:\n"
    << analytic << "\nnumeric:\n"
    << numeric;
  return ::testing::AssertionFailure() << s.str();
}

// Convenience: check J_analytic against r(delta) in one call.
inline ::testing::AssertionResult check_jacobian(
    const Eigen::MatrixXd& analytic, const std::function<Eigen::VectorXd(const Eigen::VectorXd&)>& r_of_delta,
    double rel_tol = 1e-5, double abs_tol = 1e-7, double h = 1e-6) {
  return jacobian_matches(analytic, numeric_jacobian(r_of_delta, static_cast<int>(analytic.cols()), h),
                          rel_tol, abs_tol);
}

}  // namespace kestrel::test

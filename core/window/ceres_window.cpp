#include "kestrel/core/ceres_window.hpp"

#include <ceres/ceres.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <functional>
#include <memory>
#include <utility>
#include <vector>

#include "kestrel/core/so3.hpp"

namespace kestrel::core {
namespace {

constexpr int kDim = kWindowStateDim;
using RowMajor = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// Pose block [p_WB (3), q_WB (x, y, z, w)] with our tangent [dp, dphi] (right
// perturbation). PlusJacobian is the "lift" [I6; 0]: the cost functions below
// return d r / d tangent in the first six ambient columns (and zero in the
// seventh), so Ceres' chain rule J_ambient * PlusJacobian yields exactly the
// tangent Jacobian our solver uses.
class PoseManifold final : public ceres::Manifold {
 public:
  int AmbientSize() const override { return 7; }
  int TangentSize() const override { return 6; }
  bool Plus(const double* x, const double* delta, double* x_plus_delta) const override {
    const Eigen::Quaterniond q(x[6], x[3], x[4], x[5]);
    const Eigen::Quaterniond qn =
        (q * so3::exp_quat(Eigen::Vector3d(delta[3], delta[4], delta[5]))).normalized();
    for (int i = 0; i < 3; ++i) x_plus_delta[i] = x[i] + delta[i];
    x_plus_delta[3] = qn.x();
    x_plus_delta[4] = qn.y();
    x_plus_delta[5] = qn.z();
    x_plus_delta[6] = qn.w();
    return true;
  }
  bool PlusJacobian(const double* /*x*/, double* jacobian) const override {
    Eigen::Map<Eigen::Matrix<double, 7, 6, Eigen::RowMajor>> J(jacobian);
    J.setZero();
    J.topLeftCorner<6, 6>().setIdentity();
    return true;
  }
  bool Minus(const double* y, const double* x, double* y_minus_x) const override {
    const Eigen::Quaterniond qx(x[6], x[3], x[4], x[5]), qy(y[6], y[3], y[4], y[5]);
    for (int i = 0; i < 3; ++i) y_minus_x[i] = y[i] - x[i];
    const Eigen::Vector3d phi = so3::Log((qx.conjugate() * qy).toRotationMatrix());
    for (int i = 0; i < 3; ++i) y_minus_x[3 + i] = phi[i];
    return true;
  }
  bool MinusJacobian(const double* /*x*/, double* jacobian) const override {
    Eigen::Map<Eigen::Matrix<double, 6, 7, Eigen::RowMajor>> J(jacobian);
    J.setZero();
    J.topLeftCorner<6, 6>().setIdentity();
    return true;
  }
};

NavState to_nav(const double* pose, const double* sb) {
  NavState x;
  x.p_WB = Eigen::Vector3d(pose[0], pose[1], pose[2]);
  x.q_WB = Eigen::Quaterniond(pose[6], pose[3], pose[4], pose[5]);
  if (sb) {
    x.v_WB = Eigen::Vector3d(sb[0], sb[1], sb[2]);
    x.bg_rps = Eigen::Vector3d(sb[3], sb[4], sb[5]);
    x.ba_mps2 = Eigen::Vector3d(sb[6], sb[7], sb[8]);
  }
  return x;
}

// Every residual block of the twin differentiates on its own: central
// differences in each parameter block's tangent space (a pose's [dp, dphi]
// through PoseManifold::Plus, the other blocks additive) around the residuals
// of window_problem.hpp evaluated without their Jacobians. The twin thus shares
// the residuals with our solver but not the analytic Jacobians, so the
// cross-check (tests/window) catches an error in those too (issue 45 item 6).
// The derivative columns go into the first six ambient columns of a pose,
// which PoseManifold's lift [I6; 0] passes through unchanged. (Ceres' own
// NumericDiffCostFunction differentiates in the ambient space, the quaternion's
// four numbers, which that lift would then misread as tangent columns.)
using ResidualFn = std::function<void(double const* const* params, double* residuals)>;

constexpr int kPoseAmbient = 7;

class NumericTangentCost final : public ceres::CostFunction {
 public:
  // `blocks`: the ambient size of each parameter block; a block of 7 is a pose.
  NumericTangentCost(int rows, const std::vector<int>& blocks, ResidualFn f) : f_(std::move(f)) {
    set_num_residuals(rows);
    *mutable_parameter_block_sizes() = blocks;
  }
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    f_(params, residuals);
    if (jacobians == nullptr) return true;
    const int rows = num_residuals();
    const std::vector<int>& sizes = parameter_block_sizes();
    const int n_blocks = static_cast<int>(sizes.size());
    std::vector<std::vector<double>> x(n_blocks);
    std::vector<const double*> ptr(n_blocks);
    for (int b = 0; b < n_blocks; ++b) {
      x[b].assign(params[b], params[b] + sizes[b]);
      ptr[b] = x[b].data();
    }
    Eigen::VectorXd r_plus(rows), r_minus(rows);
    for (int b = 0; b < n_blocks; ++b) {
      if (jacobians[b] == nullptr) continue;
      Eigen::Map<RowMajor> J(jacobians[b], rows, sizes[b]);
      J.setZero();
      const bool pose = sizes[b] == kPoseAmbient;
      const int tangent = pose ? 6 : sizes[b];
      for (int t = 0; t < tangent; ++t) {
        const double h = step(params[b], t, pose);
        perturb(params[b], sizes[b], t, h, pose, x[b].data());
        f_(ptr.data(), r_plus.data());
        perturb(params[b], sizes[b], t, -h, pose, x[b].data());
        f_(ptr.data(), r_minus.data());
        J.col(t) = (r_plus - r_minus) / (2.0 * h);
      }
      x[b].assign(params[b], params[b] + sizes[b]);
    }
    return true;
  }

 private:
  // About the cube root of machine epsilon, scaled by the coordinate: the
  // balance of central differences' truncation and rounding errors. A
  // rotation's tangent is dimensionless (radians), so its step is absolute.
  static double step(const double* x, int t, bool pose) {
    constexpr double kRelStep = 1e-6;
    if (pose && t >= 3) return kRelStep;
    return kRelStep * std::max(1.0, std::abs(x[t]));
  }
  // out = x0 moved by h along tangent direction t (the whole block is written).
  static void perturb(const double* x0, int size, int t, double h, bool pose, double* out) {
    if (pose) {
      double delta[6] = {0, 0, 0, 0, 0, 0};
      delta[t] = h;
      PoseManifold().Plus(x0, delta, out);
      return;
    }
    std::copy(x0, x0 + size, out);
    out[t] += h;
  }

  ResidualFn f_;
};

// Writes a fixed-size residual vector into Ceres' residual array.
template <class V>
void put(const V& v, double* out) {
  Eigen::Map<Eigen::Matrix<double, V::RowsAtCompileTime, 1>> m(out);
  m = v;
}

ceres::CostFunction* numeric_cost(int rows, const std::vector<int>& blocks, ResidualFn f) {
  return new NumericTangentCost(rows, blocks, std::move(f));
}

NavState speed_bias(const double* sb) {
  NavState x;
  x.v_WB = Eigen::Vector3d(sb[0], sb[1], sb[2]);
  x.bg_rps = Eigen::Vector3d(sb[3], sb[4], sb[5]);
  x.ba_mps2 = Eigen::Vector3d(sb[6], sb[7], sb[8]);
  return x;
}

// Parameters: pose, landmark, and the time offset t_d when it is estimated.
ceres::CostFunction* visual_cost(const WindowProblem& P, const WindowObs& o) {
  const bool with_td = P.estimate_td();
  const int rows = o.depth_m > 0.0 ? 3 : 2;
  std::vector<int> blocks = {kPoseAmbient, 3};
  if (with_td) blocks.push_back(1);
  return numeric_cost(rows, blocks, [&P, o, with_td, rows](double const* const* params, double* residuals) {
    const Eigen::Vector3d l(params[1][0], params[1][1], params[1][2]);
    const double td_s = with_td ? params[2][0] : P.td_s;
    Eigen::Vector3d r;
    // Behind the camera: contributes nothing, exactly as in our solver.
    if (visual_residual(P, to_nav(params[0], nullptr), l, o, td_s, &r, nullptr, nullptr, nullptr) == 0)
      r.setZero();
    for (int i = 0; i < rows; ++i) residuals[i] = r(i);
  });
}

// Marginalisation prior 1/2 |e + J (x [-] x0)|^2 over the prior's states,
// parameters (pose, speed/bias) per state, and t_d - td0 last (one more
// parameter block) when the prior holds t_d.
ceres::CostFunction* prior_cost(Eigen::VectorXd e, Eigen::MatrixXd J, std::vector<NavState> x0, bool with_td,
                                double td0_s) {
  const int rows = static_cast<int>(e.size());
  std::vector<int> blocks;
  for (std::size_t k = 0; k < x0.size(); ++k) {
    blocks.push_back(kPoseAmbient);
    blocks.push_back(9);
  }
  if (with_td) blocks.push_back(1);
  return numeric_cost(rows, blocks,
                      [e = std::move(e), J = std::move(J), x0 = std::move(x0), with_td, td0_s](
                          double const* const* params, double* residuals) {
                        const int k_n = static_cast<int>(x0.size());
                        Eigen::VectorXd dx(kDim * k_n + (with_td ? 1 : 0));
                        for (int k = 0; k < k_n; ++k) {
                          dx.segment<kDim>(kDim * k) =
                              state_minus(to_nav(params[2 * k], params[2 * k + 1]), x0[k]);
                        }
                        if (with_td) dx(kDim * k_n) = params[2 * k_n][0] - td0_s;
                        Eigen::Map<Eigen::VectorXd>(residuals, e.size()) = e + J * dx;
                      });
}

struct CeresWindow {
  ceres::Problem problem;
  std::vector<std::array<double, 7>> pose;  // by slot
  std::vector<std::array<double, 9>> sb;
  std::vector<int> lm_index;  // active landmark indices
  std::vector<std::array<double, 3>> lm;
  double td_s = 0.0;  // the time offset's parameter block (estimate_td)
  int n_residual_blocks = 0;

  explicit CeresWindow(const WindowProblem& P) : problem(options()) {
    pose.resize(P.max_states);
    sb.resize(P.max_states);
    auto* manifold = new PoseManifold;  // owned by the problem (deleted once)
    for (int k = 0; k < P.n_states; ++k) {
      const int s = P.order[k];
      const NavState& x = P.states[s].x;
      pose[s] = {x.p_WB.x(), x.p_WB.y(), x.p_WB.z(), x.q_WB.x(), x.q_WB.y(), x.q_WB.z(), x.q_WB.w()};
      sb[s] = {x.v_WB.x(),   x.v_WB.y(),    x.v_WB.z(),    x.bg_rps.x(), x.bg_rps.y(),
               x.bg_rps.z(), x.ba_mps2.x(), x.ba_mps2.y(), x.ba_mps2.z()};
      problem.AddParameterBlock(pose[s].data(), 7, manifold);
      problem.AddParameterBlock(sb[s].data(), 9);
    }
    td_s = P.td_s;
    if (P.estimate_td()) {
      problem.AddParameterBlock(&td_s, 1);
      problem.AddResidualBlock(numeric_cost(1, {1},
                                            [&P](double const* const* params, double* residuals) {
                                              residuals[0] = time_offset_prior_residual(P, params[0][0]);
                                            }),
                               nullptr, &td_s);
      ++n_residual_blocks;
    }
    for (int i = 0; i < static_cast<int>(P.lms.size()); ++i)
      if (P.lms[i].used && P.lms[i].active()) lm_index.push_back(i);
    lm.resize(lm_index.size());
    ceres::LossFunction* loss = P.opt.huber_px > 0.0 ? new ceres::HuberLoss(P.opt.huber_px) : nullptr;
    for (std::size_t a = 0; a < lm_index.size(); ++a) {
      const WindowLandmark& L = P.lms[lm_index[a]];
      lm[a] = {L.p_W.x(), L.p_W.y(), L.p_W.z()};
      for (int j = 0; j < L.n_obs; ++j) {
        const int s = L.obs_slot[j];
        if (P.estimate_td()) {
          problem.AddResidualBlock(visual_cost(P, P.obs_of(s)[L.obs_idx[j]]), loss, pose[s].data(),
                                   lm[a].data(), &td_s);
        } else {
          problem.AddResidualBlock(visual_cost(P, P.obs_of(s)[L.obs_idx[j]]), loss, pose[s].data(),
                                   lm[a].data());
        }
        ++n_residual_blocks;
      }
      if (L.has_prior) {
        problem.AddResidualBlock(
            numeric_cost(3, {3},
                         [&L](double const* const* params, double* residuals) {
                           put(landmark_prior_residual(
                                   L, Eigen::Vector3d(params[0][0], params[0][1], params[0][2])),
                               residuals);
                         }),
            loss, lm[a].data());
        ++n_residual_blocks;
      }
    }
    for (int k = 0; k < P.n_states; ++k) {
      const int j = P.order[k];
      const WindowState& sj = P.states[j];
      if (!sj.has_imu) continue;
      const int i = sj.imu_prev;
      problem.AddResidualBlock(
          numeric_cost(15, {kPoseAmbient, 9, kPoseAmbient, 9},
                       [&P, &sj](double const* const* params, double* residuals) {
                         put(imu_bias_residual(P, sj, to_nav(params[0], params[1]),
                                               to_nav(params[2], params[3]), nullptr, nullptr),
                             residuals);
                       }),
          nullptr, pose[i].data(), sb[i].data(), pose[j].data(), sb[j].data());
      ++n_residual_blocks;
    }
    for (int k = 0; k < P.n_states; ++k) {
      const int s = P.order[k];
      if (!P.states[s].zero_velocity) continue;
      const double inv_sigma = 1.0 / P.opt.zero_velocity_sigma_mps;
      problem.AddResidualBlock(numeric_cost(3, {9},
                                            [inv_sigma](double const* const* params, double* residuals) {
                                              for (int i = 0; i < 3; ++i)
                                                residuals[i] = params[0][i] * inv_sigma;
                                            }),
                               nullptr, sb[s].data());
      ++n_residual_blocks;
    }
    for (int k = 0; k < P.n_states; ++k) {
      const int s = P.order[k];
      if (!P.states[s].has_pose_prior) continue;
      const WindowState& st = P.states[s];
      problem.AddResidualBlock(numeric_cost(6, {kPoseAmbient},
                                            [&st](double const* const* params, double* residuals) {
                                              put(pose_prior_residual(st, to_nav(params[0], nullptr)),
                                                  residuals);
                                            }),
                               nullptr, pose[s].data());
      ++n_residual_blocks;
    }
    for (int k = 0; k < P.n_states; ++k) {
      const int s = P.order[k];
      if (!P.states[s].hold) continue;
      const WindowState& st = P.states[s];
      problem.AddResidualBlock(numeric_cost(9, {9},
                                            [&P, &st](double const* const* params, double* residuals) {
                                              put(hold_residual(P, st, speed_bias(params[0])), residuals);
                                            }),
                               nullptr, sb[s].data());
      ++n_residual_blocks;
    }
    if (P.gauge_rotation_active()) {
      problem.AddResidualBlock(numeric_cost(3, {kPoseAmbient},
                                            [&P](double const* const* params, double* residuals) {
                                              put(gauge_rotation_residual(P, to_nav(params[0], nullptr)),
                                                  residuals);
                                            }),
                               nullptr, pose[P.gauge_slot].data());
      ++n_residual_blocks;
    }
    if (P.gauge_active()) {
      problem.AddResidualBlock(numeric_cost(4, {kPoseAmbient},
                                            [&P](double const* const* params, double* residuals) {
                                              put(gauge_residual(P, to_nav(params[0], nullptr)), residuals);
                                            }),
                               nullptr, pose[P.gauge_slot].data());
      ++n_residual_blocks;
    }
    if (P.prior_active) add_prior(P);
  }

  void add_prior(const WindowProblem& P) {
    std::vector<int> slots;
    for (int k = 0; k < P.n_states; ++k)
      if (P.states[P.order[k]].in_prior) slots.push_back(P.order[k]);
    const bool with_td = P.estimate_td() && P.td_in_prior;
    const int T = P.td_index();
    const int ds = kDim * static_cast<int>(slots.size());
    const int d = ds + (with_td ? 1 : 0);
    if (d == 0) return;
    Eigen::MatrixXd H(d, d);
    Eigen::VectorXd g(d);
    for (int a = 0; a < static_cast<int>(slots.size()); ++a) {
      g.segment<kDim>(kDim * a) = P.prior_g.segment<kDim>(kDim * slots[a]);
      for (int b = 0; b < static_cast<int>(slots.size()); ++b) {
        H.block<kDim, kDim>(kDim * a, kDim * b) =
            P.prior_H.block<kDim, kDim>(kDim * slots[a], kDim * slots[b]);
      }
      if (with_td) {
        H.block<kDim, 1>(kDim * a, ds) = P.prior_H.block<kDim, 1>(kDim * slots[a], T);
        H.block<1, kDim>(ds, kDim * a) = P.prior_H.block<1, kDim>(T, kDim * slots[a]);
      }
    }
    if (with_td) {
      H(ds, ds) = P.prior_H(T, T);
      g(ds) = P.prior_g(T);
    }
    // H = U S U' -> J = S^1/2 U', e = S^-1/2 U' g (OKVIS' MarginalizationError).
    Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(0.5 * (H + H.transpose()));
    const double lmax = std::max(eig.eigenvalues().maxCoeff(), 1e-300);
    std::vector<int> keep;
    for (int i = 0; i < d; ++i)
      if (eig.eigenvalues()(i) > 1e-10 * lmax) keep.push_back(i);
    if (keep.empty()) return;
    Eigen::MatrixXd J(keep.size(), d);
    Eigen::VectorXd e(keep.size());
    for (std::size_t q = 0; q < keep.size(); ++q) {
      const double s = eig.eigenvalues()(keep[q]);
      const Eigen::VectorXd u = eig.eigenvectors().col(keep[q]);
      J.row(q) = std::sqrt(s) * u.transpose();
      e(q) = u.dot(g) / std::sqrt(s);
    }
    std::vector<NavState> x0;
    std::vector<double*> blocks;
    for (int s : slots) {
      x0.push_back(P.states[s].x0);
      blocks.push_back(pose[s].data());
      blocks.push_back(sb[s].data());
    }
    if (with_td) blocks.push_back(&td_s);
    problem.AddResidualBlock(prior_cost(e, J, x0, with_td, P.td0_s), nullptr, blocks);
    ++n_residual_blocks;
  }

  static ceres::Problem::Options options() {
    ceres::Problem::Options o;
    // Residual blocks share one loss and one manifold: the problem deletes each once.
    o.loss_function_ownership = ceres::TAKE_OWNERSHIP;
    o.manifold_ownership = ceres::TAKE_OWNERSHIP;
    return o;
  }

  void write_back(WindowProblem& P) const {
    for (int k = 0; k < P.n_states; ++k) {
      const int s = P.order[k];
      const NavState x = to_nav(pose[s].data(), sb[s].data());
      NavState& y = P.states[s].x;
      y.p_WB = x.p_WB;
      y.q_WB = x.q_WB.normalized();
      y.v_WB = x.v_WB;
      y.bg_rps = x.bg_rps;
      y.ba_mps2 = x.ba_mps2;
    }
    for (std::size_t a = 0; a < lm_index.size(); ++a)
      P.lms[lm_index[a]].p_W = Eigen::Vector3d(lm[a][0], lm[a][1], lm[a][2]);
    if (P.estimate_td()) P.td_s = td_s;
  }
};

}  // namespace

WindowOptimizer::Result solve_window_ceres(WindowProblem& P, const CeresWindowOptions& o) {
  const auto t0 = std::chrono::steady_clock::now();
  WindowOptimizer::Result res;
  if (P.n_states == 0) {
    res.status = WindowOptimizer::Status::kEmpty;
    return res;
  }
  CeresWindow cw(P);
  ceres::Solver::Options so;
  so.linear_solver_type = ceres::DENSE_SCHUR;
  so.minimizer_type = ceres::TRUST_REGION;
  so.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
  so.num_threads = 1;
  so.logging_type = ceres::SILENT;
  so.minimizer_progress_to_stdout = false;
  so.max_num_iterations = o.max_iterations > 0 ? o.max_iterations : P.opt.max_iterations;
  const double budget_ms = o.time_budget_ms > 0 ? o.time_budget_ms : P.opt.time_budget_ms;
  so.max_solver_time_in_seconds = budget_ms * 1e-3;
  so.function_tolerance = o.function_tolerance > 0 ? o.function_tolerance : P.opt.function_tolerance;
  so.gradient_tolerance = o.gradient_tolerance;
  so.parameter_tolerance = o.parameter_tolerance;
  auto* ordering = new ceres::ParameterBlockOrdering;
  for (auto& l : cw.lm) ordering->AddElementToGroup(l.data(), 0);
  for (int k = 0; k < P.n_states; ++k) {
    ordering->AddElementToGroup(cw.pose[P.order[k]].data(), 1);
    ordering->AddElementToGroup(cw.sb[P.order[k]].data(), 1);
  }
  if (P.estimate_td()) ordering->AddElementToGroup(&cw.td_s, 1);
  so.linear_solver_ordering.reset(ordering);
  ceres::Solver::Summary summary;
  ceres::Solve(so, &cw.problem, &summary);
  cw.write_back(P);
  res.iterations = summary.num_successful_steps + summary.num_unsuccessful_steps;
  res.cost_initial = summary.initial_cost;
  res.cost_final = summary.final_cost;
  res.landmarks = static_cast<int>(cw.lm.size());
  res.residuals = cw.n_residual_blocks;
  res.ok = summary.IsSolutionUsable();
  res.solve_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  if (summary.termination_type == ceres::CONVERGENCE) {
    res.status = WindowOptimizer::Status::kConverged;
  } else if (summary.termination_type == ceres::NO_CONVERGENCE) {
    res.status = summary.total_time_in_seconds * 1e3 >= budget_ms ? WindowOptimizer::Status::kTimeBudget
                                                                  : WindowOptimizer::Status::kMaxIterations;
  } else {
    res.status = WindowOptimizer::Status::kFailed;
  }
  return res;
}

double ceres_window_cost(const WindowProblem& P) {
  if (P.n_states == 0) return 0.0;
  CeresWindow cw(P);
  double cost = 0.0;
  cw.problem.Evaluate(ceres::Problem::EvaluateOptions(), &cost, nullptr, nullptr, nullptr);
  return cost;
}

}  // namespace kestrel::core

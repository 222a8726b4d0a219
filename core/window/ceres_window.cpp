#include "kestrel/core/ceres_window.hpp"

#include <ceres/ceres.h>

#include <Eigen/Eigenvalues>
#include <chrono>
#include <cmath>
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

// Writes d r / d tangent (rows x 15 or rows x 6) into the pose (rows x 7) and
// speed/bias (rows x 9) ambient Jacobians.
template <class M>
void split_jacobian(const M& J15, int rows, double* j_pose, double* j_sb) {
  if (j_pose) {
    Eigen::Map<RowMajor> Jp(j_pose, rows, 7);
    Jp.setZero();
    Jp.leftCols(6) = J15.leftCols(6);
  }
  if (j_sb) {
    Eigen::Map<RowMajor> Js(j_sb, rows, 9);
    Js = J15.rightCols(9);
  }
}

// Parameters: pose, landmark, and the time offset t_d when it is estimated.
class VisualCost final : public ceres::CostFunction {
 public:
  VisualCost(const WindowProblem& P, const WindowObs& o) : P_(P), o_(o), with_td_(P.estimate_td()) {
    rows_ = o.depth_m > 0.0 ? 3 : 2;
    set_num_residuals(rows_);
    mutable_parameter_block_sizes()->push_back(7);
    mutable_parameter_block_sizes()->push_back(3);
    if (with_td_) mutable_parameter_block_sizes()->push_back(1);
  }
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    const NavState x = to_nav(params[0], nullptr);
    const Eigen::Vector3d l(params[1][0], params[1][1], params[1][2]);
    const double td_s = with_td_ ? params[2][0] : P_.td_s;
    Eigen::Vector3d r, Jt;
    Matrix36d Jp;
    Eigen::Matrix3d Jl;
    const bool want = jacobians != nullptr;
    if (visual_residual(P_, x, l, o_, td_s, &r, want ? &Jp : nullptr, want ? &Jl : nullptr,
                        want ? &Jt : nullptr) == 0) {
      // Behind the camera: contributes nothing, exactly as in our solver.
      r.setZero();
      Jp.setZero();
      Jl.setZero();
      Jt.setZero();
    }
    for (int i = 0; i < rows_; ++i) residuals[i] = r(i);
    if (want) {
      if (jacobians[0]) {
        Eigen::Map<RowMajor> J(jacobians[0], rows_, 7);
        J.setZero();
        J.leftCols(6) = Jp.topRows(rows_);
      }
      if (jacobians[1]) {
        Eigen::Map<RowMajor> J(jacobians[1], rows_, 3);
        J = Jl.topRows(rows_);
      }
      if (with_td_ && jacobians[2])
        for (int i = 0; i < rows_; ++i) jacobians[2][i] = Jt(i);
    }
    return true;
  }

 private:
  const WindowProblem& P_;
  WindowObs o_;
  bool with_td_;
  int rows_ = 2;
};

class TimeOffsetPriorCost final : public ceres::SizedCostFunction<1, 1> {
 public:
  explicit TimeOffsetPriorCost(const WindowProblem& P) : P_(P) {}
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    double J = 0.0;
    residuals[0] = time_offset_prior_residual(P_, params[0][0], &J);
    if (jacobians && jacobians[0]) jacobians[0][0] = J;
    return true;
  }

 private:
  const WindowProblem& P_;
};

class ImuCost final : public ceres::SizedCostFunction<15, 7, 9, 7, 9> {
 public:
  ImuCost(const WindowProblem& P, const WindowState& sj) : P_(P), sj_(sj) {}
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    const NavState xi = to_nav(params[0], params[1]);
    const NavState xj = to_nav(params[2], params[3]);
    Matrix15d Ji, Jj;
    const bool want = jacobians != nullptr;
    const Vector15d r = imu_bias_residual(P_, sj_, xi, xj, want ? &Ji : nullptr, want ? &Jj : nullptr);
    Eigen::Map<Vector15d> res(residuals);
    res = r;
    if (want) {
      split_jacobian(Ji, 15, jacobians[0], jacobians[1]);
      split_jacobian(Jj, 15, jacobians[2], jacobians[3]);
    }
    return true;
  }

 private:
  const WindowProblem& P_;
  const WindowState& sj_;
};

// Zero-velocity factor on the speed/bias block [v, bg, ba].
class ZeroVelocityCost final : public ceres::SizedCostFunction<3, 9> {
 public:
  explicit ZeroVelocityCost(double sigma) : inv_sigma_(1.0 / sigma) {}
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    for (int i = 0; i < 3; ++i) residuals[i] = params[0][i] * inv_sigma_;
    if (jacobians && jacobians[0]) {
      Eigen::Map<Eigen::Matrix<double, 3, 9, Eigen::RowMajor>> J(jacobians[0]);
      J.setZero();
      J.leftCols<3>().diagonal().setConstant(inv_sigma_);
    }
    return true;
  }

 private:
  double inv_sigma_;
};

// Map prior of a landmark: (l - prior) / sigma (window_problem.hpp).
class LandmarkPriorCost final : public ceres::SizedCostFunction<3, 3> {
 public:
  explicit LandmarkPriorCost(const WindowLandmark& L) : L_(L) {}
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    Eigen::Map<Eigen::Vector3d> r(residuals);
    r = landmark_prior_residual(L_, Eigen::Vector3d(params[0][0], params[0][1], params[0][2]));
    if (jacobians && jacobians[0]) {
      Eigen::Map<Eigen::Matrix<double, 3, 3, Eigen::RowMajor>> J(jacobians[0]);
      J.setIdentity();
      J /= L_.prior_sigma_m;
    }
    return true;
  }

 private:
  const WindowLandmark& L_;
};

// Hold prior on the speed/bias block of a vision-only state (window_problem.hpp).
class HoldCost final : public ceres::SizedCostFunction<9, 9> {
 public:
  HoldCost(const WindowProblem& P, const WindowState& st) : P_(P), st_(st) {}
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    NavState x;
    x.v_WB = Eigen::Vector3d(params[0][0], params[0][1], params[0][2]);
    x.bg_rps = Eigen::Vector3d(params[0][3], params[0][4], params[0][5]);
    x.ba_mps2 = Eigen::Vector3d(params[0][6], params[0][7], params[0][8]);
    Eigen::Map<Vector9d> res(residuals);
    res = hold_residual(P_, st_, x);
    if (jacobians && jacobians[0]) {
      Eigen::Map<Eigen::Matrix<double, 9, 9, Eigen::RowMajor>> J(jacobians[0]);
      J.setZero();
      J.diagonal() = hold_weights(P_);
    }
    return true;
  }

 private:
  const WindowProblem& P_;
  const WindowState& st_;
};

// A residual on one pose block alone (gauge, map pose factor): f(x, J*)
// returns the kRows residual and d r / d[dp, dphi] from window_problem.hpp.
template <int kRows, class F>
class PoseBlockCost final : public ceres::SizedCostFunction<kRows, 7> {
 public:
  explicit PoseBlockCost(F f) : f_(std::move(f)) {}
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    Eigen::Matrix<double, kRows, 6> J;
    Eigen::Map<Eigen::Matrix<double, kRows, 1>> res(residuals);
    res = f_(to_nav(params[0], nullptr), jacobians ? &J : nullptr);
    if (jacobians && jacobians[0]) {
      Eigen::Map<Eigen::Matrix<double, kRows, 7, Eigen::RowMajor>> Jm(jacobians[0]);
      Jm.setZero();
      Jm.template leftCols<6>() = J;
    }
    return true;
  }

 private:
  F f_;
};

template <int kRows, class F>
ceres::CostFunction* pose_block_cost(F f) {
  return new PoseBlockCost<kRows, F>(std::move(f));
}

// Marginalisation prior 1/2 |e + J (x [-] x0)|^2 over the prior's states,
// parameters (pose, speed/bias) per state.
// (and t_d - td0 last, one more parameter block, when the prior holds t_d).
class PriorCost final : public ceres::CostFunction {
 public:
  PriorCost(Eigen::VectorXd e, Eigen::MatrixXd J, std::vector<NavState> x0, bool with_td, double td0_s)
      : e_(std::move(e)), J_(std::move(J)), x0_(std::move(x0)), with_td_(with_td), td0_s_(td0_s) {
    set_num_residuals(static_cast<int>(e_.size()));
    for (std::size_t k = 0; k < x0_.size(); ++k) {
      mutable_parameter_block_sizes()->push_back(7);
      mutable_parameter_block_sizes()->push_back(9);
    }
    if (with_td_) mutable_parameter_block_sizes()->push_back(1);
  }
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    const int k_n = static_cast<int>(x0_.size());
    const int r = static_cast<int>(e_.size());
    Eigen::VectorXd dx(kDim * k_n + (with_td_ ? 1 : 0));
    std::vector<Eigen::Matrix3d> Jr(k_n);
    for (int k = 0; k < k_n; ++k) {
      dx.segment<kDim>(kDim * k) = state_minus(to_nav(params[2 * k], params[2 * k + 1]), x0_[k], &Jr[k]);
    }
    if (with_td_) dx(kDim * k_n) = params[2 * k_n][0] - td0_s_;
    Eigen::Map<Eigen::VectorXd>(residuals, r) = e_ + J_ * dx;
    if (jacobians) {
      for (int k = 0; k < k_n; ++k) {
        Eigen::MatrixXd Jk = J_.middleCols(kDim * k, kDim);
        Jk.middleCols(3, 3) = (Jk.middleCols(3, 3) * Jr[k]).eval();
        split_jacobian(Jk, r, jacobians[2 * k], jacobians[2 * k + 1]);
      }
      if (with_td_ && jacobians[2 * k_n])
        Eigen::Map<Eigen::VectorXd>(jacobians[2 * k_n], r) = J_.col(kDim * k_n);
    }
    return true;
  }

 private:
  Eigen::VectorXd e_;
  Eigen::MatrixXd J_;
  std::vector<NavState> x0_;
  bool with_td_;
  double td0_s_;
};

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
      problem.AddResidualBlock(new TimeOffsetPriorCost(P), nullptr, &td_s);
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
          problem.AddResidualBlock(new VisualCost(P, P.obs_of(s)[L.obs_idx[j]]), loss, pose[s].data(),
                                   lm[a].data(), &td_s);
        } else {
          problem.AddResidualBlock(new VisualCost(P, P.obs_of(s)[L.obs_idx[j]]), loss, pose[s].data(),
                                   lm[a].data());
        }
        ++n_residual_blocks;
      }
      if (L.has_prior) {
        problem.AddResidualBlock(new LandmarkPriorCost(L), loss, lm[a].data());
        ++n_residual_blocks;
      }
    }
    for (int k = 0; k < P.n_states; ++k) {
      const int j = P.order[k];
      const WindowState& sj = P.states[j];
      if (!sj.has_imu) continue;
      const int i = sj.imu_prev;
      problem.AddResidualBlock(new ImuCost(P, sj), nullptr, pose[i].data(), sb[i].data(), pose[j].data(),
                               sb[j].data());
      ++n_residual_blocks;
    }
    for (int k = 0; k < P.n_states; ++k) {
      const int s = P.order[k];
      if (!P.states[s].zero_velocity) continue;
      problem.AddResidualBlock(new ZeroVelocityCost(P.opt.zero_velocity_sigma_mps), nullptr, sb[s].data());
      ++n_residual_blocks;
    }
    for (int k = 0; k < P.n_states; ++k) {
      const int s = P.order[k];
      if (!P.states[s].has_pose_prior) continue;
      const WindowState& st = P.states[s];
      problem.AddResidualBlock(
          pose_block_cost<6>([&st](const NavState& x, Matrix6d* J) { return pose_prior_residual(st, x, J); }),
          nullptr, pose[s].data());
      ++n_residual_blocks;
    }
    for (int k = 0; k < P.n_states; ++k) {
      const int s = P.order[k];
      if (!P.states[s].hold) continue;
      problem.AddResidualBlock(new HoldCost(P, P.states[s]), nullptr, sb[s].data());
      ++n_residual_blocks;
    }
    if (P.gauge_rotation_active()) {
      problem.AddResidualBlock(pose_block_cost<3>([&P](const NavState& x, Eigen::Matrix<double, 3, 6>* J) {
                                 return gauge_rotation_residual(P, x, J);
                               }),
                               nullptr, pose[P.gauge_slot].data());
      ++n_residual_blocks;
    }
    if (P.gauge_active()) {
      problem.AddResidualBlock(pose_block_cost<4>([&P](const NavState& x, Eigen::Matrix<double, 4, 6>* J) {
                                 return gauge_residual(P, x, J);
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
    problem.AddResidualBlock(new PriorCost(e, J, x0, with_td, P.td0_s), nullptr, blocks);
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

#include "kestrel/core/window_optimizer.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>
#include <sstream>
#include <stdexcept>

#include "kestrel/core/ceres_window.hpp"
#include "kestrel/core/levenberg_marquardt.hpp"
#include "kestrel/core/so3.hpp"
#include "kestrel/rt/mailbox.hpp"

namespace kestrel::core {
namespace {

constexpr int kD = kWindowStateDim;
using Matrix63d = Eigen::Matrix<double, 6, 3>;

double elapsed_ms(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

uint32_t hash_id(uint32_t id) { return id * 2654435761u; }

// The newest pose covariance as it crosses from the optimizer thread to the
// tracking side: plain data for the seqlock mailbox.
struct CovarianceSnapshot {
  double cov[36];  // column-major 6x6
  int64_t t_ns;
  bool valid;
};

}  // namespace

WindowOptions WindowOptions::embedded() {
  WindowOptions o;
  o.S = 2;
  o.N = 3;
  return o;
}

std::string WindowOptions::validate() const {
  std::ostringstream e;
  if (S < 1) e << "S must be >= 1 (got " << S << "); ";
  if (N < 1) e << "N must be >= 1 (got " << N << "); ";
  if (S + N > kWindowMaxStates) e << "S + N must be <= " << kWindowMaxStates << " (got " << S + N << "); ";
  if (max_landmarks < 1) e << "max_landmarks must be >= 1; ";
  if (max_obs_per_frame < 1 || max_obs_per_frame > 32767) e << "max_obs_per_frame must be in [1, 32767]; ";
  if (max_iterations < 1) e << "max_iterations must be >= 1; ";
  if (!(time_budget_ms > 0.0)) e << "time_budget_ms must be > 0; ";
  if (!std::isfinite(huber_px)) e << "huber_px must be finite; ";
  if (!(depth_sigma_coeff_per_m > 0.0)) e << "depth_sigma_coeff_per_m must be > 0; ";
  if (!(pixel_sigma > 0.0)) e << "pixel_sigma must be > 0; ";
  if (acc_bias_model == AccBiasModel::kBoundedRandomWalk && !(acc_bias_tau_s > 0.0))
    e << "acc_bias_tau_s must be > 0 for the bounded random walk; ";
  if (!(imu.gyro_random_walk_rad_s2_sqrthz > 0.0) || !(imu.acc_random_walk_mps3_sqrthz > 0.0))
    e << "imu random walks (gyro_random_walk_rad_s2_sqrthz, acc_random_walk_mps3_sqrthz) must be > 0; ";
  if (!(prior_gyro_bias_sigma_rps > 0.0) || !(prior_acc_bias_sigma_mps2 > 0.0))
    e << "bias prior sigmas must be > 0; ";
  if (!(gauge_sigma > 0.0)) e << "gauge_sigma must be > 0; ";
  if (!(zero_velocity_sigma_mps > 0.0)) e << "zero_velocity_sigma_mps must be > 0; ";
  if (!(time_offset_prior_sigma_ms > 0.0)) e << "time_offset_prior_sigma_ms must be > 0; ";
  if (!(hold_velocity_sigma_mps > 0.0) || !(hold_gyro_bias_sigma_rps > 0.0) ||
      !(hold_acc_bias_sigma_mps2 > 0.0)) {
    e << "hold sigmas (hold_velocity_sigma_mps, hold_gyro_bias_sigma_rps, hold_acc_bias_sigma_mps2) must be "
         "> 0; ";
  }
  return e.str();
}

const char* to_string(WindowOptimizer::Status s) {
  switch (s) {
    case WindowOptimizer::Status::kConverged:
      return "converged";
    case WindowOptimizer::Status::kMaxIterations:
      return "max_iterations";
    case WindowOptimizer::Status::kTimeBudget:
      return "time_budget";
    case WindowOptimizer::Status::kNoProgress:
      return "no_progress";
    case WindowOptimizer::Status::kEmpty:
      return "empty";
    case WindowOptimizer::Status::kFailed:
      return "failed";
  }
  return "?";
}

// Everything the solver and the marginalisation touch per call, sized once.
struct WindowOptimizer::Workspace {
  // Landmark id -> index: open addressing, linear probing, backward-shift deletion.
  std::vector<uint32_t> map_key;
  std::vector<int32_t> map_val;  // -1: empty
  uint32_t map_mask = 0;
  std::vector<int32_t> free_lms;

  // Solver.
  int pos_of_slot[kWindowMaxStates] = {};
  std::vector<int32_t> active;  // active landmark indices
  int n_active = 0;
  Eigen::MatrixXd H_lin, H_red;  // camera part (landmark-free) / reduced system
  Eigen::VectorXd b_lin, b_red, dx, diag_c;
  std::vector<Eigen::Matrix3d> V, Vinv;
  std::vector<Eigen::Vector3d> w, dl, diag_l;
  std::vector<Matrix63d> W;            // per observation (slot-major like problem.obs)
  std::vector<Eigen::RowVector3d> Wt;  // per landmark: its coupling with t_d, sum over its observations
  std::vector<Eigen::Vector3d> cand_l;
  NavState cand_x[kWindowMaxStates];
  Eigen::Matrix3d prior_Jrot[kWindowMaxStates];
  Vector15d prior_dx[kWindowMaxStates];

  // Marginalisation.
  Eigen::MatrixXd Hm;
  Eigen::VectorXd gm;
  Eigen::Matrix<double, Eigen::Dynamic, 15, 0, kWindowMaxDim, 15> T;
  Eigen::MatrixXd Hc;
  // Built in place at the window's size: assigning a size-constructed solver
  // copies its uninitialised status field (UBSan flags it).
  std::unique_ptr<Eigen::LDLT<Eigen::MatrixXd>> ldlt;
  Eigen::VectorXd xm;
  std::vector<int32_t> marg_lms;
  std::vector<uint8_t> lm_mark;

  // The newest pose covariance: whether H_red holds a valid factor of an
  // n x n system, and the last one computed.
  bool factor_ok = false;
  int factor_n = 0;
  rt::Mailbox<CovarianceSnapshot> covariance;
  // Drift from before the window: the gauge pins the oldest state, so the
  // window's covariance is relative to it. Each time the gauge moves to the
  // next state, that state's covariance relative to the old gauge (computed
  // at the solve before) is compounded into the gauge's own: position in W
  // and yaw about W z (roll and pitch are observable through gravity).
  Eigen::Matrix3d drift_pos = Eigen::Matrix3d::Zero();
  double drift_yaw_var = 0.0;
  int64_t gauge_t_ns = -1;
  Eigen::Vector3d gauge_p = Eigen::Vector3d::Zero();
  int64_t next_gauge_t_ns = -1;  // order[1] at the last solve, with its relative covariance
  Eigen::Matrix3d next_pos_cov = Eigen::Matrix3d::Zero();
  double next_yaw_var = 0.0;
};

WindowOptimizer::WindowOptimizer(const PinholeK& K, const Eigen::Isometry3d& T_BC,
                                 const WindowOptions& options)
    : problem_(std::make_unique<WindowProblem>()), ws_(std::make_unique<Workspace>()) {
  const std::string err = options.validate();
  if (!err.empty()) throw std::invalid_argument("WindowOptions: " + err);
  WindowProblem& P = *problem_;
  P.opt = options;
  P.bias_noise = options.imu;
  P.bias_noise.acc_bias_tau_s = options.acc_bias_model == WindowOptions::AccBiasModel::kBoundedRandomWalk
                                    ? options.acc_bias_tau_s
                                    : 0.0;
  P.K = K;
  P.R_CB = T_BC.linear().transpose();
  P.p_CB = -P.R_CB * T_BC.translation();
  P.max_states = options.S + options.N;
  P.states.resize(P.max_states);
  P.obs.resize(static_cast<std::size_t>(P.max_states) * options.max_obs_per_frame);
  P.lms.resize(options.max_landmarks);
  const int D = kD * P.max_states + 1;  // + t_d
  P.prior_H = Eigen::MatrixXd::Zero(D, D);
  P.prior_g = Eigen::VectorXd::Zero(D);

  Workspace& ws = *ws_;
  uint32_t cap = 16;
  while (cap < 2u * static_cast<uint32_t>(options.max_landmarks)) cap <<= 1;
  ws.map_key.assign(cap, 0);
  ws.map_val.assign(cap, -1);
  ws.map_mask = cap - 1;
  ws.free_lms.reserve(options.max_landmarks);
  for (int i = options.max_landmarks - 1; i >= 0; --i) ws.free_lms.push_back(i);
  ws.active.resize(options.max_landmarks);
  ws.H_lin = Eigen::MatrixXd::Zero(D, D);
  ws.H_red = Eigen::MatrixXd::Zero(D, D);
  ws.b_lin = Eigen::VectorXd::Zero(D);
  ws.b_red = Eigen::VectorXd::Zero(D);
  ws.dx = Eigen::VectorXd::Zero(D);
  ws.diag_c = Eigen::VectorXd::Zero(D);
  ws.V.resize(options.max_landmarks);
  ws.Vinv.resize(options.max_landmarks);
  ws.w.resize(options.max_landmarks);
  ws.dl.resize(options.max_landmarks);
  ws.diag_l.resize(options.max_landmarks);
  ws.cand_l.resize(options.max_landmarks);
  ws.W.resize(P.obs.size());
  ws.Wt.resize(options.max_landmarks);
  ws.Hm = Eigen::MatrixXd::Zero(D, D);
  ws.gm = Eigen::VectorXd::Zero(D);
  ws.T.resize(D, 15);
  ws.Hc = Eigen::MatrixXd::Zero(D, D);
  ws.ldlt = std::make_unique<Eigen::LDLT<Eigen::MatrixXd>>(D);
  ws.xm = Eigen::VectorXd::Zero(D);
  ws.marg_lms.resize(options.max_obs_per_frame);
  ws.lm_mark.assign(options.max_landmarks, 0);
}

WindowOptimizer::~WindowOptimizer() = default;

void WindowOptimizer::reset() {
  WindowProblem& P = *problem_;
  Workspace& ws = *ws_;
  for (WindowState& st : P.states) {
    st.used = false;
    st.keyframe = false;
    st.zero_velocity = false;
    st.has_pose_prior = false;
    st.hold = false;
    st.has_imu = false;
    st.imu_prev = -1;
    st.n_obs = 0;
    st.in_prior = false;
  }
  for (WindowObs& o : P.obs) o = WindowObs{};
  for (WindowLandmark& L : P.lms) L = WindowLandmark{};
  P.n_states = 0;
  P.gauge_slot = -1;
  P.prior_H.setZero();
  P.prior_g.setZero();
  P.prior_c = 0.0;
  P.prior_active = false;
  P.td_in_prior = false;  // td_s itself is a calibration: it survives the restart
  std::fill(ws.map_key.begin(), ws.map_key.end(), 0u);
  std::fill(ws.map_val.begin(), ws.map_val.end(), -1);
  ws.free_lms.clear();  // capacity stays: the refill below does not allocate
  for (int i = P.opt.max_landmarks - 1; i >= 0; --i) ws.free_lms.push_back(i);
}

// ---- landmarks -----------------------------------------------------------------

int WindowOptimizer::find_or_create_landmark(uint32_t id) {
  Workspace& ws = *ws_;
  uint32_t h = hash_id(id) & ws.map_mask;
  while (ws.map_val[h] >= 0) {
    if (ws.map_key[h] == id) return ws.map_val[h];
    h = (h + 1) & ws.map_mask;
  }
  if (ws.free_lms.empty()) return -1;
  const int lm = ws.free_lms.back();
  ws.free_lms.pop_back();
  ws.map_key[h] = id;
  ws.map_val[h] = lm;
  WindowLandmark& L = problem_->lms[lm];
  L = WindowLandmark{};
  L.used = true;
  L.id = id;
  return lm;
}

void WindowOptimizer::free_landmark(int lm) {
  Workspace& ws = *ws_;
  WindowProblem& P = *problem_;
  WindowLandmark& L = P.lms[lm];
  for (int k = 0; k < L.n_obs; ++k) P.obs_of(L.obs_slot[k])[L.obs_idx[k]].lm = -1;
  // Backward-shift deletion keeps every probe chain unbroken without tombstones.
  uint32_t i = hash_id(L.id) & ws.map_mask;
  while (!(ws.map_val[i] == lm)) i = (i + 1) & ws.map_mask;
  uint32_t j = i;
  for (;;) {
    ws.map_val[i] = -1;
    for (;;) {
      j = (j + 1) & ws.map_mask;
      if (ws.map_val[j] < 0) goto done;
      const uint32_t home = hash_id(ws.map_key[j]) & ws.map_mask;
      // Move j back to i unless its home lies cyclically in (i, j].
      const bool in_range = i <= j ? (home > i && home <= j) : (home > i || home <= j);
      if (!in_range) break;
    }
    ws.map_key[i] = ws.map_key[j];
    ws.map_val[i] = ws.map_val[j];
    i = j;
  }
done:
  L = WindowLandmark{};
  ws.free_lms.push_back(lm);
}

int WindowOptimizer::num_landmarks() const {
  int n = 0;
  for (const WindowLandmark& L : problem_->lms) n += L.used && L.active();
  return n;
}

int WindowOptimizer::prior_dimension() const {
  if (!problem_->prior_active) return 0;
  int n = 0;
  for (int k = 0; k < problem_->n_states; ++k) n += problem_->states[problem_->order[k]].in_prior ? kD : 0;
  return n + (problem_->td_in_prior ? 1 : 0);
}

// ---- frames --------------------------------------------------------------------

void WindowOptimizer::reset_gauge() {
  WindowProblem& P = *problem_;
  if (P.n_states == 0) {
    P.gauge_slot = -1;
    return;
  }
  const int s = P.order[0];
  if (P.gauge_slot == s) return;
  P.gauge_slot = s;
  P.gauge_p = P.states[s].x.p_WB;
  P.gauge_yaw = yaw_of(P.states[s].x.q_WB);
  P.gauge_q = P.states[s].x.q_WB.normalized();
}

bool WindowOptimizer::add_frame(const WindowFrameInput& in) {
  WindowProblem& P = *problem_;
  if (P.n_states > 0) {
    if (in.imu_from_prev == nullptr && !in.vision_only) return false;
    if (in.t_ns <= P.states[P.newest_slot()].x.t_ns) return false;
  }
  // Which state leaves: the frame dropping out of the S most recent is
  // removed unless it is a keyframe; beyond N keyframes the oldest goes.
  const int S = P.opt.S, n = P.n_states;
  if (n >= S) {
    const int c = P.order[n - S];
    if (!P.states[c].keyframe) {
      marginalize_or_drop(c);
    } else if (n - S + 1 > P.opt.N) {
      marginalize_or_drop(P.order[0]);
    }
  }
  if (P.n_states >= P.max_states) marginalize_or_drop(P.order[0]);  // defensive: cannot happen

  if (P.estimate_td() && in.td_meas_sigma_s > 0.0 && std::isfinite(in.td_meas_s) &&
      std::isfinite(in.td_meas_sigma_s)) {
    // The newest measurement stands until the next; the first one also
    // starts t_d there, which the prior alone would take many solves to reach.
    if (!(P.td_meas_sigma_s > 0.0)) P.td_s = in.td_meas_s;
    P.td_meas_s = in.td_meas_s;
    P.td_meas_sigma_s = in.td_meas_sigma_s;
  }
  if (P.estimate_td() && P.td_meas_sigma_s > 0.0 && P.td_in_prior) {
    // With a measurement, t_d leaves the marginalisation prior (conditioned
    // on, not marginalised): what marginalised states said of t_d was
    // linearised where t_d was first guessed, along a direction vision cannot
    // tell from the poses, and it held t_d there against any evidence - the
    // reason the state alone never moved (docs/optimizer.md). The measurement
    // carries the evidence now.
    const int T = P.td_index();
    P.prior_H.row(T).setZero();
    P.prior_H.col(T).setZero();
    P.prior_g(T) = 0.0;
    P.td_in_prior = false;
  }
  int slot = 0;
  while (P.states[slot].used) ++slot;
  WindowState& st = P.states[slot];
  st.used = true;
  st.keyframe = in.keyframe;
  st.zero_velocity = in.stationary;
  st.has_pose_prior = in.has_pose_prior && in.prior_sigma_p_m > 0.0 && in.prior_sigma_rad > 0.0 &&
                      in.prior_p_WB.allFinite() && in.prior_q_WB.coeffs().allFinite();
  if (st.has_pose_prior) {
    st.prior_p_WB = in.prior_p_WB;
    st.prior_q_WB = in.prior_q_WB.normalized();
    st.prior_sigma_p_m = in.prior_sigma_p_m;
    st.prior_sigma_rad = in.prior_sigma_rad;
  }
  st.x = in.guess;
  st.x.t_ns = in.t_ns;
  st.x.q_WB.normalize();
  st.n_obs = 0;
  st.in_prior = false;
  st.hold = in.vision_only;
  st.hold_x = st.x;
  st.has_imu = P.n_states > 0 && !in.vision_only;
  st.imu_prev = st.has_imu ? P.newest_slot() : -1;
  if (st.has_imu) {
    st.pim = *in.imu_from_prev;
    st.imu_sqrt_info = st.pim.sqrt_information();
    const Matrix6d C = bias_covariance(st.pim.dt_total(), P.bias_noise);
    for (int i = 0; i < 6; ++i) st.bias_sqrt_info(i) = 1.0 / std::sqrt(std::max(C(i, i), 1e-300));
  }
  const bool first = P.n_states == 0 && !P.prior_active;
  P.order[P.n_states++] = slot;
  if (first) {
    // Start-up speed/bias prior (OKVIS): only the biases, the velocity is
    // left to the IMU and the views.
    const int o = kD * slot;
    const double ig = 1.0 / (P.opt.prior_gyro_bias_sigma_rps * P.opt.prior_gyro_bias_sigma_rps);
    const double ia = 1.0 / (P.opt.prior_acc_bias_sigma_mps2 * P.opt.prior_acc_bias_sigma_mps2);
    for (int i = 0; i < 3; ++i) {
      P.prior_H(o + 9 + i, o + 9 + i) = ig;
      P.prior_H(o + 12 + i, o + 12 + i) = ia;
    }
    st.in_prior = true;
    st.x0 = st.x;
    P.prior_active = true;
  }
  reset_gauge();
  add_observations(slot, in);
  return true;
}

void WindowOptimizer::add_observations(int slot, const WindowFrameInput& in) {
  WindowProblem& P = *problem_;
  WindowState& st = P.states[slot];
  WindowObs* obs = P.obs_of(slot);
  const Eigen::Matrix3d R_WB = st.x.q_WB.toRotationMatrix();
  for (int k = 0; k < in.n_obs; ++k) {
    const WindowObservation& o = in.obs[k];
    if (!o.uv.allFinite() || !std::isfinite(o.depth_m) || o.depth_m < 0.0) {
      ++counters_.obs_skipped_invalid;
      continue;
    }
    if (st.n_obs >= P.opt.max_obs_per_frame) {
      counters_.obs_skipped_budget += in.n_obs - k;
      break;
    }
    const int lm = find_or_create_landmark(o.landmark_id);
    if (lm < 0) {
      ++counters_.obs_skipped_budget;
      continue;
    }
    WindowLandmark& L = P.lms[lm];
    bool dup = false;
    for (int j = 0; j < L.n_obs; ++j) dup |= L.obs_slot[j] == slot;
    if (dup || L.n_obs >= kWindowMaxStates) {
      ++counters_.obs_skipped_invalid;
      continue;
    }
    if (P.opt.use_map_points && o.map_sigma_m > 0.0f && o.map_p_W.allFinite()) {
      // The newest position the map gave wins; it also places a landmark not yet placed.
      L.has_prior = true;
      L.prior_p_W = o.map_p_W;
      L.prior_sigma_m = static_cast<double>(o.map_sigma_m);
      if (!L.initialised) {
        L.p_W = o.map_p_W;
        L.initialised = true;
      }
    }
    WindowObs& w = obs[st.n_obs];
    w.lm = lm;
    w.uv = o.uv;
    w.depth_m = P.opt.use_depth ? o.depth_m : 0.0;
    w.sigma_px = o.sigma_px > 0.0f ? static_cast<double>(o.sigma_px) : P.opt.pixel_sigma;
    w.sigma_depth_m = std::max(1e-3, P.opt.depth_sigma_coeff_per_m * o.depth_m * o.depth_m);
    w.uv_vel_pxps = in.uv_vel_pxps != nullptr && in.uv_vel_pxps[k].allFinite() ? in.uv_vel_pxps[k]
                                                                               : Eigen::Vector2d::Zero();
    w.depth_vel_mps =
        in.depth_vel_mps != nullptr && std::isfinite(in.depth_vel_mps[k]) ? in.depth_vel_mps[k] : 0.0;
    const Eigen::Vector3d ray_C((o.uv.x() - P.K.cx) / P.K.fx, (o.uv.y() - P.K.cy) / P.K.fy, 1.0);
    if (!L.initialised && o.depth_m > 0.0) {
      const Eigen::Vector3d p_B = P.R_CB.transpose() * (ray_C * o.depth_m - P.p_CB);
      L.p_W = R_WB * p_B + st.x.p_WB;
      L.initialised = true;
      ++counters_.landmarks_from_depth;
    } else if (!L.initialised && L.n_obs > 0) {
      // Midpoint triangulation with the first view, at the current estimates.
      const WindowState& s0 = P.states[L.obs_slot[0]];
      const WindowObs& o0 = P.obs_of(L.obs_slot[0])[L.obs_idx[0]];
      const Eigen::Matrix3d R0 = s0.x.q_WB.toRotationMatrix();
      const Eigen::Matrix3d R_BC = P.R_CB.transpose();
      const Eigen::Vector3d c0 = s0.x.p_WB + R0 * (-R_BC * P.p_CB);
      const Eigen::Vector3d c1 = st.x.p_WB + R_WB * (-R_BC * P.p_CB);
      const Eigen::Vector3d d0 =
          (R0 * R_BC * Eigen::Vector3d((o0.uv.x() - P.K.cx) / P.K.fx, (o0.uv.y() - P.K.cy) / P.K.fy, 1.0))
              .normalized();
      const Eigen::Vector3d d1 = (R_WB * R_BC * ray_C).normalized();
      const double b = d0.dot(d1);
      const double den = 1.0 - b * b;
      if (den > 3e-4) {  // parallax above ~1 degree
        const Eigen::Vector3d c = c1 - c0;
        const double t0 = (c.dot(d0) - b * c.dot(d1)) / den;
        const double t1 = (b * c.dot(d0) - c.dot(d1)) / den;
        if (t0 > 0.05 && t1 > 0.05) {
          L.p_W = 0.5 * (c0 + t0 * d0 + c1 + t1 * d1);
          L.initialised = true;
          ++counters_.landmarks_triangulated;
        }
      }
    }
    L.obs_slot[L.n_obs] = static_cast<int8_t>(slot);
    L.obs_idx[L.n_obs] = static_cast<int16_t>(st.n_obs);
    ++L.n_obs;
    if (w.depth_m > 0.0) ++L.n_depth;
    ++st.n_obs;
  }
}

void WindowOptimizer::remove_state(int slot) {
  WindowProblem& P = *problem_;
  WindowState& st = P.states[slot];
  WindowObs* obs = P.obs_of(slot);
  for (int k = 0; k < st.n_obs; ++k) {
    const int lm = obs[k].lm;
    if (lm < 0) continue;
    WindowLandmark& L = P.lms[lm];
    for (int j = 0; j < L.n_obs; ++j) {
      if (L.obs_slot[j] != slot) continue;
      if (obs[k].depth_m > 0.0) --L.n_depth;
      --L.n_obs;
      L.obs_slot[j] = L.obs_slot[L.n_obs];
      L.obs_idx[j] = L.obs_idx[L.n_obs];
      break;
    }
    obs[k].lm = -1;
    if (L.n_obs == 0) free_landmark(lm);
  }
  st.n_obs = 0;
  for (int k = 0; k < P.n_states; ++k) {
    WindowState& o = P.states[P.order[k]];
    if (o.has_imu && o.imu_prev == slot) {
      o.has_imu = false;
      o.imu_prev = -1;
    }
  }
  int k = 0;
  while (P.order[k] != slot) ++k;
  for (; k + 1 < P.n_states; ++k) P.order[k] = P.order[k + 1];
  --P.n_states;
  // The prior rows of this slot were eliminated (or discarded) by the caller.
  const int o = kD * slot;
  P.prior_H.middleRows(o, kD).setZero();
  P.prior_H.middleCols(o, kD).setZero();
  P.prior_g.segment(o, kD).setZero();
  st.used = false;
  st.in_prior = false;
  st.has_imu = false;
  bool any = P.td_in_prior;
  for (int j = 0; j < P.n_states; ++j) any |= P.states[P.order[j]].in_prior;
  if (!any) {
    P.prior_active = false;
    P.prior_c = 0.0;
  }
  if (P.gauge_slot == slot) P.gauge_slot = -1;
  reset_gauge();
}

void WindowOptimizer::marginalize_or_drop(int m) {
  WindowProblem& P = *problem_;
  Workspace& ws = *ws_;
  if (!P.opt.marginalize) {
    ++counters_.drops;
    remove_state(m);
    return;
  }
  ++counters_.marginalizations;
  auto lin = [&](int s) -> const NavState& { return P.states[s].in_prior ? P.states[s].x0 : P.states[s].x; };
  const double td_lin = P.td_in_prior ? P.td0_s : P.td_s;
  const bool with_td = P.estimate_td();
  const int T = P.td_index();
  bool td_touched = false;
  bool touched[kWindowMaxStates] = {};
  touched[m] = true;

  ws.Hm = P.prior_H;
  ws.gm = P.prior_g;
  double c = P.prior_active ? P.prior_c : 0.0;

  // IMU + bias factors into and out of m, at the first estimates.
  auto add_imu = [&](int j) {
    const WindowState& sj = P.states[j];
    const int i = sj.imu_prev;
    Matrix15d Ji, Jj;
    const Vector15d r = imu_bias_residual(P, sj, lin(i), lin(j), &Ji, &Jj);
    ws.Hm.block<kD, kD>(kD * i, kD * i) += Ji.transpose() * Ji;
    ws.Hm.block<kD, kD>(kD * i, kD * j) += Ji.transpose() * Jj;
    ws.Hm.block<kD, kD>(kD * j, kD * i) += Jj.transpose() * Ji;
    ws.Hm.block<kD, kD>(kD * j, kD * j) += Jj.transpose() * Jj;
    ws.gm.segment<kD>(kD * i) += Ji.transpose() * r;
    ws.gm.segment<kD>(kD * j) += Jj.transpose() * r;
    c += 0.5 * r.squaredNorm();
    touched[i] = touched[j] = true;
  };
  if (P.states[m].has_imu) add_imu(m);
  // The map pose factor goes into the prior with its state: the window keeps
  // what the map said after the state is gone.
  if (P.states[m].has_pose_prior) {
    Matrix6d J;
    const Vector6d r = pose_prior_residual(P.states[m], lin(m), &J);
    ws.Hm.block<6, 6>(kD * m, kD * m) += J.transpose() * J;
    ws.gm.segment<6>(kD * m) += J.transpose() * r;
    c += 0.5 * r.squaredNorm();
  }
  if (P.states[m].hold) {
    const Vector9d w = hold_weights(P);
    const Vector9d r = hold_residual(P, P.states[m], lin(m));
    ws.Hm.block<9, 9>(kD * m + 6, kD * m + 6).diagonal() += w.cwiseProduct(w);
    ws.gm.segment<9>(kD * m + 6) += w.cwiseProduct(r);
    c += 0.5 * r.squaredNorm();
  }
  for (int k = 0; k < P.n_states; ++k) {
    const int j = P.order[k];
    if (P.states[j].has_imu && P.states[j].imu_prev == m) add_imu(j);
  }

  // Keyframe: landmarks it sees that the temporal window no longer tracks
  // are marginalised with it (OKVIS); for the others its observations are
  // dropped, which keeps the landmarks out of the prior.
  int n_marg = 0;
  if (P.states[m].keyframe) {
    const int n = P.n_states, S = P.opt.S;
    const WindowObs* obs = P.obs_of(m);
    for (int k = 0; k < P.states[m].n_obs; ++k) {
      const int lm = obs[k].lm;
      if (lm < 0) continue;
      const WindowLandmark& L = P.lms[lm];
      if (!L.active() || L.n_obs < 2) continue;
      bool recent = false;
      for (int j = 0; j < L.n_obs; ++j)
        for (int q = std::max(0, n - S + 1); q < n; ++q) recent |= L.obs_slot[j] == P.order[q];
      if (recent) continue;
      ws.marg_lms[n_marg++] = lm;
      for (int j = 0; j < L.n_obs; ++j) touched[L.obs_slot[j]] = true;
    }
    for (int q = 0; q < n_marg; ++q) {
      const WindowLandmark& L = P.lms[ws.marg_lms[q]];
      Eigen::Matrix3d V = Eigen::Matrix3d::Zero();
      Eigen::Vector3d wl = Eigen::Vector3d::Zero();
      Matrix63d Wk[kWindowMaxStates];
      Eigen::RowVector3d Wt = Eigen::RowVector3d::Zero();  // t_d - landmark coupling
      int ok[kWindowMaxStates] = {};
      for (int j = 0; j < L.n_obs; ++j) {
        const int s = L.obs_slot[j];
        const WindowObs& o = P.obs_of(s)[L.obs_idx[j]];
        Eigen::Vector3d r, Jt;
        Matrix36d Jp;
        Eigen::Matrix3d Jl;
        const int rows = visual_residual(P, lin(s), L.p_W, o, td_lin, &r, &Jp, &Jl, &Jt);
        if (rows == 0) continue;
        ok[j] = 1;
        double rho1 = 1.0;
        c += 0.5 * huber_rho(r.squaredNorm(), P.opt.huber_px, &rho1);
        Jp *= std::sqrt(rho1);
        Jl *= std::sqrt(rho1);
        Jt *= std::sqrt(rho1);
        r *= std::sqrt(rho1);
        ws.Hm.block<6, 6>(kD * s, kD * s) += Jp.transpose() * Jp;
        ws.gm.segment<6>(kD * s) += Jp.transpose() * r;
        Wk[j] = Jp.transpose() * Jl;
        V += Jl.transpose() * Jl;
        wl += Jl.transpose() * r;
        if (with_td) {
          ws.Hm.block<6, 1>(kD * s, T) += Jp.transpose() * Jt;
          ws.Hm.block<1, 6>(T, kD * s) += Jt.transpose() * Jp;
          ws.Hm(T, T) += Jt.squaredNorm();
          ws.gm(T) += Jt.dot(r);
          Wt += Jt.transpose() * Jl;
          td_touched = true;
        }
      }
      if (L.has_prior) {
        // The map's word on the point goes into the prior with it.
        const Eigen::Vector3d r = landmark_prior_residual(L, L.p_W);
        double rho1 = 1.0;
        c += 0.5 * huber_rho(r.squaredNorm(), P.opt.huber_px, &rho1);
        const double w = rho1 / L.prior_sigma_m;
        V.diagonal().array() += w / L.prior_sigma_m;
        wl += w * r;
      }
      const Eigen::Matrix3d Vi = V.inverse();
      c -= 0.5 * wl.dot(Vi * wl);
      for (int a = 0; a < L.n_obs; ++a) {
        if (!ok[a]) continue;
        const int sa = L.obs_slot[a];
        const Matrix63d WV = Wk[a] * Vi;
        ws.gm.segment<6>(kD * sa) -= WV * wl;
        for (int b = 0; b < L.n_obs; ++b) {
          if (!ok[b]) continue;
          ws.Hm.block<6, 6>(kD * sa, kD * L.obs_slot[b]) -= WV * Wk[b].transpose();
        }
        if (with_td) {
          const Eigen::Matrix<double, 6, 1> h = WV * Wt.transpose();
          ws.Hm.block<6, 1>(kD * sa, T) -= h;
          ws.Hm.block<1, 6>(T, kD * sa) -= h.transpose();
        }
      }
      if (with_td) {
        ws.gm(T) -= Wt * (Vi * wl);
        ws.Hm(T, T) -= Wt * Vi * Wt.transpose();
      }
    }
  }

  // States newly tied to the prior get their linearisation point now.
  for (int k = 0; k < P.n_states; ++k) {
    const int s = P.order[k];
    if (touched[s] && !P.states[s].in_prior) {
      P.states[s].in_prior = true;
      P.states[s].x0 = P.states[s].x;
    }
  }
  if (td_touched && !P.td_in_prior) {
    P.td_in_prior = true;
    P.td0_s = P.td_s;
  }

  // Schur complement of m (pseudo-inverse: m may be weakly constrained).
  const int om = kD * m;
  const Matrix15d Hmm = 0.5 * (ws.Hm.block<kD, kD>(om, om) + ws.Hm.block<kD, kD>(om, om).transpose());
  Eigen::SelfAdjointEigenSolver<Matrix15d> em(Hmm);
  const double emax = std::max(em.eigenvalues().maxCoeff(), 1e-300);
  Eigen::Matrix<double, 15, 1> inv = Eigen::Matrix<double, 15, 1>::Zero();
  for (int i = 0; i < 15; ++i)
    if (em.eigenvalues()(i) > 1e-12 * emax) inv(i) = 1.0 / em.eigenvalues()(i);
  const Matrix15d Hmm_pinv = em.eigenvectors() * inv.asDiagonal() * em.eigenvectors().transpose();
  const Vector15d g_m = ws.gm.segment<kD>(om);
  c -= 0.5 * g_m.dot(Hmm_pinv * g_m);
  ws.T.noalias() = ws.Hm.middleCols<kD>(om) * Hmm_pinv;
  ws.Hm.noalias() -= ws.T * ws.Hm.middleRows<kD>(om);
  ws.gm.noalias() -= ws.T * g_m;
  ws.Hm.middleRows<kD>(om).setZero();
  ws.Hm.middleCols<kD>(om).setZero();
  ws.gm.segment<kD>(om).setZero();

  // The prior keeps H and g as they are: our solver works on them directly.
  // Ceres needs the equivalent residual 1/2 |e + J dx|^2 and factors H itself
  // (ceres_window.cpp), dropping the numerically non-positive directions; the
  // constant 1/2 g' H^+ g it implies comes from a pivoting LDLT here, whose
  // solve treats vanishing pivots as zero (a pseudo-inverse on the range of H).
  // An eigen-decomposition would do both but allocates (Householder temporary).
  ws.Hc = 0.5 * (ws.Hm + ws.Hm.transpose());
  P.prior_H = ws.Hc;
  P.prior_g = ws.gm;
  ws.ldlt->compute(ws.Hc);
  ws.xm = ws.ldlt->solve(ws.gm);
  P.prior_c = ws.xm.allFinite() ? 0.5 * ws.gm.dot(ws.xm) : 0.0;
  (void)c;  // the irreducible part of the old cost: constant, not kept (see docs)
  P.prior_active = P.prior_H.cwiseAbs().maxCoeff() > 0.0;
  P.states[m].in_prior = false;
  for (int q = 0; q < n_marg; ++q) free_landmark(ws.marg_lms[q]);
  remove_state(m);
  for (int k = 0; k < P.n_states; ++k) {
    // A state whose prior rows all vanished (nothing tied it) leaves the prior.
    const int s = P.order[k];
    if (P.states[s].in_prior && P.prior_H.block<kD, kD>(kD * s, kD * s).cwiseAbs().maxCoeff() == 0.0)
      P.states[s].in_prior = false;
  }
  if (P.td_in_prior && P.prior_H(T, T) == 0.0) P.td_in_prior = false;
}

// ---- cost and solver ---------------------------------------------------------------

namespace {

// Cost of the whole problem with states xs (indexed by slot) and landmark positions ls.
// td_s: the time offset (P.td_s unless a step is being tried).
double problem_cost(const WindowProblem& P, const NavState* xs, const Eigen::Vector3d* ls,
                    const int32_t* active, int n_active, Vector15d* dx_scratch, double td_s) {
  double cost = 0.0;
  for (int a = 0; a < n_active; ++a) {
    const WindowLandmark& L = P.lms[active[a]];
    for (int j = 0; j < L.n_obs; ++j) {
      const int s = L.obs_slot[j];
      Eigen::Vector3d r;
      if (visual_residual(P, xs[s], ls[active[a]], P.obs_of(s)[L.obs_idx[j]], td_s, &r) == 0) continue;
      cost += 0.5 * huber_rho(r.squaredNorm(), P.opt.huber_px, nullptr);
    }
    if (L.has_prior) {
      cost +=
          0.5 * huber_rho(landmark_prior_residual(L, ls[active[a]]).squaredNorm(), P.opt.huber_px, nullptr);
    }
  }
  for (int k = 0; k < P.n_states; ++k) {
    const int s = P.order[k];
    const WindowState& st = P.states[s];
    if (st.has_imu) cost += 0.5 * imu_bias_residual(P, st, xs[st.imu_prev], xs[s]).squaredNorm();
    if (st.zero_velocity) cost += 0.5 * (xs[s].v_WB / P.opt.zero_velocity_sigma_mps).squaredNorm();
    if (st.has_pose_prior) cost += 0.5 * pose_prior_residual(st, xs[s]).squaredNorm();
    if (st.hold) cost += 0.5 * hold_residual(P, st, xs[s]).squaredNorm();
  }
  if (P.gauge_active()) cost += 0.5 * gauge_residual(P, xs[P.gauge_slot]).squaredNorm();
  if (P.estimate_td()) {
    const double r = time_offset_prior_residual(P, td_s);
    cost += 0.5 * r * r;
  }
  if (P.gauge_rotation_active()) cost += 0.5 * gauge_rotation_residual(P, xs[P.gauge_slot]).squaredNorm();
  if (P.prior_active) {
    double pc = P.prior_c;
    for (int k = 0; k < P.n_states; ++k) {
      const int s = P.order[k];
      if (P.states[s].in_prior) dx_scratch[s] = state_minus(xs[s], P.states[s].x0);
    }
    for (int a = 0; a < P.n_states; ++a) {
      const int s = P.order[a];
      if (!P.states[s].in_prior) continue;
      pc += P.prior_g.segment<kD>(kD * s).dot(dx_scratch[s]);
      for (int b = 0; b < P.n_states; ++b) {
        const int t = P.order[b];
        if (!P.states[t].in_prior) continue;
        pc += 0.5 * dx_scratch[s].dot(P.prior_H.block<kD, kD>(kD * s, kD * t) * dx_scratch[t]);
      }
    }
    if (P.td_in_prior) {
      const int T = P.td_index();
      const double dt = td_s - P.td0_s;
      pc += P.prior_g(T) * dt + 0.5 * P.prior_H(T, T) * dt * dt;
      for (int a = 0; a < P.n_states; ++a) {
        const int s = P.order[a];
        if (P.states[s].in_prior) pc += dt * P.prior_H.block<1, kD>(T, kD * s).dot(dx_scratch[s]);
      }
    }
    cost += pc;
  }
  return cost;
}

}  // namespace

double WindowOptimizer::evaluate_cost() const {
  const WindowProblem& P = *problem_;
  Workspace& ws = *ws_;
  int n_active = 0;
  for (int i = 0; i < static_cast<int>(P.lms.size()); ++i)
    if (P.lms[i].used && P.lms[i].active()) ws.active[n_active++] = i;
  NavState xs[kWindowMaxStates];
  for (int k = 0; k < P.n_states; ++k) xs[P.order[k]] = P.states[P.order[k]].x;
  for (int a = 0; a < n_active; ++a) ws.cand_l[ws.active[a]] = P.lms[ws.active[a]].p_W;
  return problem_cost(P, xs, ws.cand_l.data(), ws.active.data(), n_active, ws.prior_dx, P.td_s);
}

WindowOptimizer::Result WindowOptimizer::optimize() {
  {
    WindowProblem& P = *problem_;
    int n_map = 0;
    for (const WindowLandmark& L : P.lms) n_map += L.used && L.has_prior && L.active();
    P.map_anchored = P.opt.use_map_points && n_map >= P.opt.map_anchor_min_landmarks;
  }
  if (problem_->opt.solver == WindowOptions::Solver::kCeres) {
    ws_->factor_ok = false;  // Ceres leaves no factor here: the covariance is not known
    const Result r = solve_window_ceres(*problem_);
    publish_newest_covariance();
    return r;
  }
  return optimize_ours();
}

// The window as the problem of the one Levenberg-Marquardt loop
// (levenberg_marquardt.hpp). The unknowns are the states in time order, then
// t_d (when estimated); the active landmarks are Schur-eliminated in solve()
// and recovered by back-substitution.
struct WindowOptimizer::LmProblem {
  LmProblem(WindowProblem& problem, Workspace& workspace)
      : P(problem),
        ws(workspace),
        n(kD * P.n_states),
        with_td(P.estimate_td()),
        nt(n + (with_td ? 1 : 0)),
        T(P.td_index()),
        Hl(ws.H_lin.topLeftCorner(nt, nt)),
        bl(ws.b_lin.head(nt)) {}

  void linearize();
  bool solve(double lambda, lm::Step* step);
  double try_step();
  void accept();
  void reject() {}

  WindowProblem& P;
  Workspace& ws;
  const int n;
  const bool with_td;
  const int nt;
  const int T;
  Eigen::Block<Eigen::MatrixXd> Hl;
  Eigen::VectorBlock<Eigen::VectorXd> bl;
  double td_cand = 0;

 private:
  void linearize_visual();
  void linearize_states();
  void linearize_prior();
};

// Visual terms: pose blocks into H_lin, landmark blocks kept for the Schur complement.
void WindowOptimizer::LmProblem::linearize_visual() {
  for (int a = 0; a < ws.n_active; ++a) {
    const int lm = ws.active[a];
    const WindowLandmark& L = P.lms[lm];
    Eigen::Matrix3d V = Eigen::Matrix3d::Zero();
    Eigen::Vector3d wv = Eigen::Vector3d::Zero();
    Eigen::RowVector3d Wt = Eigen::RowVector3d::Zero();
    for (int j = 0; j < L.n_obs; ++j) {
      const int s = L.obs_slot[j];
      const int oi = s * P.opt.max_obs_per_frame + L.obs_idx[j];
      Eigen::Vector3d r, Jt;
      Matrix36d Jp;
      Eigen::Matrix3d Jl;
      if (visual_residual(P, P.states[s].x, L.p_W, P.obs[oi], P.td_s, &r, &Jp, &Jl, &Jt) == 0) {
        ws.W[oi].setZero();
        continue;
      }
      double rho1 = 1.0;
      huber_rho(r.squaredNorm(), P.opt.huber_px, &rho1);
      const int o = kD * ws.pos_of_slot[s];
      const Eigen::Matrix<double, 6, 3> JpT = rho1 * Jp.transpose();
      Hl.block<6, 6>(o, o).noalias() += JpT * Jp;
      bl.segment<6>(o).noalias() += JpT * r;
      ws.W[oi].noalias() = JpT * Jl;
      V.noalias() += rho1 * Jl.transpose() * Jl;
      wv.noalias() += rho1 * Jl.transpose() * r;
      if (with_td) {
        const Eigen::Matrix<double, 6, 1> h = JpT * Jt;
        Hl.block<6, 1>(o, n) += h;
        Hl.block<1, 6>(n, o) += h.transpose();
        Hl(n, n) += rho1 * Jt.squaredNorm();
        bl(n) += rho1 * Jt.dot(r);
        Wt.noalias() += rho1 * Jt.transpose() * Jl;
      }
    }
    if (L.has_prior) {
      const Eigen::Vector3d r = landmark_prior_residual(L, L.p_W);
      double rho1 = 1.0;
      huber_rho(r.squaredNorm(), P.opt.huber_px, &rho1);
      const double w = rho1 / L.prior_sigma_m;
      V.diagonal().array() += w / L.prior_sigma_m;
      wv.noalias() += w * r;
    }
    ws.V[lm] = V;
    ws.w[lm] = wv;
    ws.Wt[lm] = Wt;
    ws.diag_l[lm] = V.diagonal().cwiseMax(1e-6);
  }
}

// The factors on states alone: IMU + bias, zero velocity, map poses, holds,
// the gauges and the time-offset prior.
void WindowOptimizer::LmProblem::linearize_states() {
  for (int k = 0; k < P.n_states; ++k) {
    const int j = P.order[k];
    const WindowState& sj = P.states[j];
    if (!sj.has_imu) continue;
    const int i = sj.imu_prev;
    Matrix15d Ji, Jj;
    const Vector15d r = imu_bias_residual(P, sj, P.states[i].x, sj.x, &Ji, &Jj);
    const int oi = kD * ws.pos_of_slot[i], oj = kD * k;
    Hl.block<kD, kD>(oi, oi).noalias() += Ji.transpose() * Ji;
    Hl.block<kD, kD>(oi, oj).noalias() += Ji.transpose() * Jj;
    Hl.block<kD, kD>(oj, oi).noalias() += Jj.transpose() * Ji;
    Hl.block<kD, kD>(oj, oj).noalias() += Jj.transpose() * Jj;
    bl.segment<kD>(oi).noalias() += Ji.transpose() * r;
    bl.segment<kD>(oj).noalias() += Jj.transpose() * r;
  }
  // Zero velocity: r = v / sigma, d r / d dv = I / sigma.
  for (int k = 0; k < P.n_states; ++k) {
    const int s = P.order[k];
    if (!P.states[s].zero_velocity) continue;
    const double w = 1.0 / (P.opt.zero_velocity_sigma_mps * P.opt.zero_velocity_sigma_mps);
    const int o = kD * ws.pos_of_slot[s] + 6;
    Hl.block<3, 3>(o, o).diagonal().array() += w;
    bl.segment<3>(o).noalias() += w * P.states[s].x.v_WB;
  }
  for (int k = 0; k < P.n_states; ++k) {
    const int s = P.order[k];
    if (!P.states[s].has_pose_prior) continue;
    Matrix6d J;
    const Vector6d r = pose_prior_residual(P.states[s], P.states[s].x, &J);
    const int o = kD * ws.pos_of_slot[s];
    Hl.block<6, 6>(o, o).noalias() += J.transpose() * J;
    bl.segment<6>(o).noalias() += J.transpose() * r;
  }
  // Hold priors of vision-only states: r = w (x - x_hold) on [v, bg, ba].
  for (int k = 0; k < P.n_states; ++k) {
    const WindowState& st = P.states[P.order[k]];
    if (!st.hold) continue;
    const Vector9d w = hold_weights(P);
    const int o = kD * k + 6;
    Hl.block<9, 9>(o, o).diagonal() += w.cwiseProduct(w);
    bl.segment<9>(o).noalias() += w.cwiseProduct(hold_residual(P, st, st.x));
  }
  if (P.gauge_rotation_active()) {
    Eigen::Matrix<double, 3, 6> Jg;
    const Eigen::Vector3d r = gauge_rotation_residual(P, P.states[P.gauge_slot].x, &Jg);
    const int o = kD * ws.pos_of_slot[P.gauge_slot];
    Hl.block<6, 6>(o, o).noalias() += Jg.transpose() * Jg;
    bl.segment<6>(o).noalias() += Jg.transpose() * r;
  }
  if (P.gauge_active()) {
    Eigen::Matrix<double, 4, 6> Jg;
    const Eigen::Vector4d r = gauge_residual(P, P.states[P.gauge_slot].x, &Jg);
    const int o = kD * ws.pos_of_slot[P.gauge_slot];
    Hl.block<6, 6>(o, o).noalias() += Jg.transpose() * Jg;
    bl.segment<6>(o).noalias() += Jg.transpose() * r;
  }
  if (with_td) {
    double J = 0.0;
    const double r = time_offset_prior_residual(P, P.td_s, &J);
    Hl(n, n) += J * J;
    bl(n) += J * r;
  }
}

// Marginalisation prior, chained through d(x [-] x0)/dx (t_d: linear).
void WindowOptimizer::LmProblem::linearize_prior() {
  if (!P.prior_active) return;
  const bool td_prior = with_td && P.td_in_prior;
  const double dtd = P.td_s - P.td0_s;
  for (int k = 0; k < P.n_states; ++k) {
    const int s = P.order[k];
    if (P.states[s].in_prior) ws.prior_dx[s] = state_minus(P.states[s].x, P.states[s].x0, &ws.prior_Jrot[s]);
  }
  for (int a = 0; a < P.n_states; ++a) {
    const int s = P.order[a];
    if (!P.states[s].in_prior) continue;
    Vector15d g = P.prior_g.segment<kD>(kD * s);
    for (int b = 0; b < P.n_states; ++b) {
      const int t = P.order[b];
      if (!P.states[t].in_prior) continue;
      Matrix15d Hst = P.prior_H.block<kD, kD>(kD * s, kD * t);
      g.noalias() += Hst * ws.prior_dx[t];
      Hst.middleRows<3>(3) = (ws.prior_Jrot[s].transpose() * Hst.middleRows<3>(3)).eval();
      Hst.middleCols<3>(3) = (Hst.middleCols<3>(3) * ws.prior_Jrot[t]).eval();
      Hl.block<kD, kD>(kD * a, kD * b) += Hst;
    }
    if (td_prior) {
      Vector15d h = P.prior_H.block<kD, 1>(kD * s, T);
      g.noalias() += h * dtd;
      h.segment<3>(3) = (ws.prior_Jrot[s].transpose() * h.segment<3>(3)).eval();
      Hl.block<kD, 1>(kD * a, n) += h;
      Hl.block<1, kD>(n, kD * a) += h.transpose();
    }
    g.segment<3>(3) = (ws.prior_Jrot[s].transpose() * g.segment<3>(3)).eval();
    bl.segment<kD>(kD * a) += g;
  }
  if (td_prior) {
    double g = P.prior_g(T) + P.prior_H(T, T) * dtd;
    for (int b = 0; b < P.n_states; ++b) {
      const int t = P.order[b];
      if (P.states[t].in_prior) g += P.prior_H.block<1, kD>(T, kD * t).dot(ws.prior_dx[t]);
    }
    Hl(n, n) += P.prior_H(T, T);
    bl(n) += g;
  }
}

void WindowOptimizer::LmProblem::linearize() {
  Hl.setZero();
  bl.setZero();
  linearize_visual();
  linearize_states();
  linearize_prior();
  for (int i = 0; i < nt; ++i) ws.diag_c(i) = std::clamp(Hl(i, i), 1e-6, 1e32);
}

// Damped Schur complement H_red = H_cc + lambda D - sum_l W V^-1 W', its
// Cholesky factor (kept for the covariance), the states' step, and the
// landmarks' by back-substitution.
bool WindowOptimizer::LmProblem::solve(double lambda, lm::Step* step) {
  auto Hr = ws.H_red.topLeftCorner(nt, nt);
  auto br = ws.b_red.head(nt);
  Hr = Hl;
  br = bl;
  Hr.diagonal() += lambda * ws.diag_c.head(nt);
  for (int a = 0; a < ws.n_active; ++a) {
    const int lm = ws.active[a];
    const WindowLandmark& L = P.lms[lm];
    Eigen::Matrix3d Vd = ws.V[lm];
    Vd.diagonal() += lambda * ws.diag_l[lm];
    ws.Vinv[lm] = Vd.inverse();
    for (int j = 0; j < L.n_obs; ++j) {
      const int oj = L.obs_slot[j] * P.opt.max_obs_per_frame + L.obs_idx[j];
      const int pj = kD * ws.pos_of_slot[L.obs_slot[j]];
      const Matrix63d WV = ws.W[oj] * ws.Vinv[lm];
      br.segment<6>(pj).noalias() -= WV * ws.w[lm];
      for (int q = 0; q < L.n_obs; ++q) {
        const int oq = L.obs_slot[q] * P.opt.max_obs_per_frame + L.obs_idx[q];
        const int pq = kD * ws.pos_of_slot[L.obs_slot[q]];
        Hr.block<6, 6>(pj, pq).noalias() -= WV * ws.W[oq].transpose();
      }
      if (with_td) {
        const Eigen::Matrix<double, 6, 1> h = WV * ws.Wt[lm].transpose();
        Hr.block<6, 1>(pj, n) -= h;
        Hr.block<1, 6>(n, pj) -= h.transpose();
      }
    }
    if (with_td) {
      const Eigen::RowVector3d WtV = ws.Wt[lm] * ws.Vinv[lm];
      Hr(n, n) -= WtV.dot(ws.Wt[lm]);
      br(n) -= WtV.dot(ws.w[lm]);
    }
  }
  Eigen::Ref<Eigen::MatrixXd> Hr_ref(Hr);
  Eigen::LLT<Eigen::Ref<Eigen::MatrixXd>> llt(Hr_ref);
  ws.factor_ok = llt.info() == Eigen::Success;
  ws.factor_n = nt;
  if (!ws.factor_ok) return false;
  auto dx = ws.dx.head(nt);
  dx = -br;
  llt.solveInPlace(dx);
  // Back-substitution: dl = V^-1 (-w - sum W' dx), and the model decrease.
  double pred = 0.0;
  pred += 0.5 * (lambda * dx.dot(ws.diag_c.head(nt).cwiseProduct(dx)) - bl.dot(dx));
  double max_step = dx.cwiseAbs().maxCoeff();
  for (int a = 0; a < ws.n_active; ++a) {
    const int lm = ws.active[a];
    const WindowLandmark& L = P.lms[lm];
    Eigen::Vector3d rhs = -ws.w[lm];
    for (int j = 0; j < L.n_obs; ++j) {
      const int oj = L.obs_slot[j] * P.opt.max_obs_per_frame + L.obs_idx[j];
      rhs.noalias() -= ws.W[oj].transpose() * dx.segment<6>(kD * ws.pos_of_slot[L.obs_slot[j]]);
    }
    if (with_td) rhs.noalias() -= ws.Wt[lm].transpose() * dx(n);
    const Eigen::Vector3d d = ws.Vinv[lm] * rhs;
    ws.dl[lm] = d;
    pred += 0.5 * (lambda * d.dot(ws.diag_l[lm].cwiseProduct(d)) - ws.w[lm].dot(d));
    max_step = std::max(max_step, d.cwiseAbs().maxCoeff());
  }
  step->predicted_decrease = pred;
  step->negligible = max_step < P.opt.step_tolerance;
  return true;
}

double WindowOptimizer::LmProblem::try_step() {
  auto dx = ws.dx.head(nt);
  for (int a = 0; a < ws.n_active; ++a)
    ws.cand_l[ws.active[a]] = P.lms[ws.active[a]].p_W + ws.dl[ws.active[a]];
  for (int k = 0; k < P.n_states; ++k) {
    const int s = P.order[k];
    ws.cand_x[s] = state_plus(P.states[s].x, dx.segment<kD>(kD * k));
  }
  td_cand = with_td ? P.td_s + dx(n) : P.td_s;
  return problem_cost(P, ws.cand_x, ws.cand_l.data(), ws.active.data(), ws.n_active, ws.prior_dx, td_cand);
}

void WindowOptimizer::LmProblem::accept() {
  for (int k = 0; k < P.n_states; ++k) P.states[P.order[k]].x = ws.cand_x[P.order[k]];
  P.td_s = td_cand;
  for (int a = 0; a < ws.n_active; ++a) P.lms[ws.active[a]].p_W = ws.cand_l[ws.active[a]];
}

WindowOptimizer::Result WindowOptimizer::optimize_ours() {
  const auto t0 = std::chrono::steady_clock::now();
  WindowProblem& P = *problem_;
  Workspace& ws = *ws_;
  Result res;
  ws.factor_ok = false;
  if (P.n_states == 0) {
    res.status = Status::kEmpty;
    publish_newest_covariance();
    return res;
  }
  for (int k = 0; k < P.n_states; ++k) ws.pos_of_slot[P.order[k]] = k;
  ws.n_active = 0;
  int n_vis = 0;
  for (int i = 0; i < static_cast<int>(P.lms.size()); ++i) {
    if (P.lms[i].used && P.lms[i].active()) {
      ws.active[ws.n_active++] = i;
      n_vis += P.lms[i].n_obs + (P.lms[i].has_prior ? 1 : 0);
    }
  }
  int n_states_factors = 0;
  for (int k = 0; k < P.n_states; ++k) {
    const WindowState& st = P.states[P.order[k]];
    n_states_factors += st.has_imu + st.zero_velocity + st.has_pose_prior + st.hold;
  }
  const bool with_td = P.estimate_td();
  res.landmarks = ws.n_active;
  res.residuals = n_vis + n_states_factors + (P.gauge_active() ? 1 : 0) +
                  (P.gauge_rotation_active() ? 1 : 0) + (P.prior_active ? 1 : 0) + (with_td ? 1 : 0);

  for (int k = 0; k < P.n_states; ++k) ws.cand_x[P.order[k]] = P.states[P.order[k]].x;
  for (int a = 0; a < ws.n_active; ++a) ws.cand_l[ws.active[a]] = P.lms[ws.active[a]].p_W;
  const double cost =
      problem_cost(P, ws.cand_x, ws.cand_l.data(), ws.active.data(), ws.n_active, ws.prior_dx, P.td_s);
  res.cost_initial = cost;

  // The rules this solver was tuned with (docs/optimizer.md): any decrease is
  // taken; a step that changes no unknown by step_tolerance, or the cost by
  // function_tolerance, ends the solve once tried.
  lm::Rules rules;
  rules.max_iterations = P.opt.max_iterations;
  rules.time_budget_ms = P.opt.time_budget_ms;
  rules.function_tolerance = P.opt.function_tolerance;
  LmProblem problem(P, ws);
  const lm::Outcome out = lm::minimize(problem, cost, rules, t0);
  res.iterations = out.iterations;
  switch (out.stop) {
    case lm::Stop::kConverged:
      res.status = Status::kConverged;
      break;
    case lm::Stop::kMaxIterations:
      res.status = Status::kMaxIterations;
      break;
    case lm::Stop::kTimeBudget:
      res.status = Status::kTimeBudget;
      break;
    case lm::Stop::kNoProgress:
      res.status = Status::kNoProgress;
      break;
  }
  res.cost_final = out.cost;
  res.ok = std::isfinite(out.cost) && res.status != Status::kFailed && res.status != Status::kNoProgress;
  if (res.status == Status::kNoProgress) res.ok = out.cost <= res.cost_initial;
  res.solve_ms = elapsed_ms(t0);
  publish_newest_covariance();
  return res;
}

const NavState& WindowOptimizer::latest() const {
  static const NavState kNone{};
  const int s = problem_->newest_slot();
  return s >= 0 ? problem_->states[s].x : kNone;
}

bool WindowOptimizer::state_of(int64_t t_ns, NavState* out) const {
  for (int k = 0; k < problem_->n_states; ++k) {
    const WindowState& st = problem_->states[problem_->order[k]];
    if (st.x.t_ns == t_ns) {
      if (out) *out = st.x;
      return true;
    }
  }
  return false;
}

namespace {

// Marginal [dp, dphi] covariance of the state at block k of a system whose
// Cholesky factor L (lower triangle of H, n x n) is given: Y = L[o:, o:]^-1
// [I6; 0], cov = Y'Y. Column by column on a fixed-capacity buffer: no heap.
Eigen::Matrix<double, 6, 6> marginal_pose(const Eigen::MatrixXd& H, int n, int k) {
  const int o = kD * k, m = n - o;
  Eigen::Matrix<double, Eigen::Dynamic, 6, 0, kWindowMaxDim, 6> Y(m, 6);
  Y.setZero();
  const auto L = H.block(o, o, m, m).triangularView<Eigen::Lower>();
  for (int j = 0; j < 6; ++j) {
    Y(j, j) = 1.0;
    auto y = Y.col(j);
    L.solveInPlace(y);
  }
  return Y.transpose() * Y;
}

}  // namespace

void WindowOptimizer::publish_newest_covariance() {
  const WindowProblem& P = *problem_;
  Workspace& ws = *ws_;
  CovarianceSnapshot c{};
  const int s = P.newest_slot();
  // The factor belongs to this window only if nothing was added since and the
  // newest state is the system's last block (time order: it always is).
  if (ws.factor_ok && s >= 0 && ws.factor_n == kD * P.n_states + (P.estimate_td() ? 1 : 0) &&
      ws.pos_of_slot[s] == P.n_states - 1) {
    const Eigen::Vector3d ez = Eigen::Vector3d::UnitZ();
    // A map pose factor in the window replaces the gauge: the window is then
    // anchored to the map (its factors carry their own sigma), and the drift
    // chain starts again from there once the gauge returns.
    if (!P.gauge_active()) {
      ws.drift_pos.setZero();
      ws.drift_yaw_var = 0.0;
      ws.gauge_t_ns = -1;
    }
    // The gauge moved since the last solve: compound the new gauge's relative covariance.
    const NavState& g = P.states[P.order[0]].x;
    if (P.gauge_active() && g.t_ns != ws.gauge_t_ns) {
      if (ws.gauge_t_ns >= 0 && g.t_ns == ws.next_gauge_t_ns) {
        const Eigen::Vector3d lever = ez.cross(g.p_WB - ws.gauge_p);
        ws.drift_pos += ws.next_pos_cov + ws.drift_yaw_var * lever * lever.transpose();
        ws.drift_yaw_var += ws.next_yaw_var;
      }
      ws.gauge_t_ns = g.t_ns;
      ws.gauge_p = g.p_WB;
    }
    ws.next_gauge_t_ns = -1;
    if (P.gauge_active() && P.n_states >= 2) {
      const Eigen::Matrix<double, 6, 6> c1 = marginal_pose(ws.H_red, ws.factor_n, 1);
      const Eigen::Vector3d yaw_B = P.states[P.order[1]].x.q_WB.conjugate() * ez;  // W z in B
      ws.next_pos_cov = c1.topLeftCorner<3, 3>();
      ws.next_yaw_var = yaw_B.dot(c1.bottomRightCorner<3, 3>() * yaw_B);
      ws.next_gauge_t_ns = P.states[P.order[1]].x.t_ns;
    }
    // The newest state relative to the gauge, then the gauge's own drift:
    // its position error shifts the newest, its yaw error turns it about W z.
    const NavState& x = P.states[s].x;
    Eigen::Matrix<double, 6, 6> cov = marginal_pose(ws.H_red, ws.factor_n, P.n_states - 1);
    cov.topLeftCorner<3, 3>() += ws.drift_pos;
    Eigen::Matrix<double, 6, 1> J;
    J.head<3>() = ez.cross(x.p_WB - ws.gauge_p);  // drift_yaw_var is 0 while the map anchors the window
    J.tail<3>() = x.q_WB.conjugate() * ez;
    cov.noalias() += ws.drift_yaw_var * J * J.transpose();
    if (cov.allFinite()) {
      Eigen::Map<Eigen::Matrix<double, 6, 6>>(c.cov) = 0.5 * (cov + cov.transpose());
      c.t_ns = x.t_ns;
      c.valid = true;
    }
  }
  ws.covariance.publish(c);
}

PoseCovariance WindowOptimizer::newest_pose_covariance() const {
  PoseCovariance out;
  CovarianceSnapshot c{};
  if (!ws_->covariance.read(c) || !c.valid) return out;
  out.cov = Eigen::Map<const Eigen::Matrix<double, 6, 6>>(c.cov);
  out.t_ns = c.t_ns;
  out.valid = true;
  return out;
}

}  // namespace kestrel::core

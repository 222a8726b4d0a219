// Sliding-window visual-inertial optimiser (paper 000 eq. 4-10): reprojection
// (+ RGB-D depth) and IMU preintegration terms over the S most recent frames
// and N keyframes, 4-DoF gauge, marginalisation into a linear prior
// (Leutenegger et al., IJRR 2015 "OKVIS" where paper 000 is vague; IMU terms
// after Forster et al., TRO 2017). docs/optimizer.md has the cost, the
// parametrisation, the solver and the measured figures.
//
// Two solvers on the same problem (window_problem.hpp): ours (Levenberg-
// Marquardt, Schur complement on landmarks, dense Cholesky on the reduced
// camera system, preallocated: optimize() makes no heap allocation) and Ceres
// (ceres_window.hpp; allocates, kept as a reference and a selectable fallback).
//
// Threading: single-threaded object; call add_frame/optimize from one thread.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <memory>
#include <string>

#include "kestrel/core/estimator.hpp"
#include "kestrel/core/imu_propagator.hpp"
#include "kestrel/core/motion_estimation.hpp"
#include "kestrel/core/preintegration.hpp"
#include "kestrel/core/window_options.hpp"
#include "kestrel/core/window_problem.hpp"

namespace kestrel::core {

class WindowOptimizer {
 public:
  enum class Status : uint8_t { kConverged, kMaxIterations, kTimeBudget, kNoProgress, kEmpty, kFailed };
  struct Result {
    bool ok = false;  // the states were updated (or already optimal)
    Status status = Status::kEmpty;
    int iterations = 0;
    double cost_initial = 0, cost_final = 0;  // 0.5 * sum rho(|whitened r|^2) + priors
    double solve_ms = 0;
    int landmarks = 0;  // in the problem
    int residuals = 0;  // residual blocks (visual + IMU + priors)
  };
  struct Counters {
    uint64_t obs_skipped_budget = 0;   // no free landmark slot / frame full
    uint64_t obs_skipped_invalid = 0;  // non-finite, depth beyond range, duplicate id in a frame
    uint64_t landmarks_triangulated = 0;
    uint64_t landmarks_from_depth = 0;
    uint64_t marginalizations = 0;
    uint64_t drops = 0;
  };

  // The pinhole part of the rig's colour camera (observations come undistorted).
  static PinholeK pinhole_of(const Rig& rig) {
    return PinholeK{rig.rgb.fx, rig.rgb.fy, rig.rgb.cx, rig.rgb.cy};
  }

  // Allocates everything. Throws std::invalid_argument when options.validate() fails.
  WindowOptimizer(const PinholeK& K, const Eigen::Isometry3d& T_BC, const WindowOptions& options);
  ~WindowOptimizer();
  WindowOptimizer(const WindowOptimizer&) = delete;
  WindowOptimizer& operator=(const WindowOptimizer&) = delete;

  // Marginalises (or drops) the state that leaves the window, then inserts the
  // frame. A frame without imu_from_prev (other than the first) is rejected
  // (returns false): the window's states must form an IMU chain.
  bool add_frame(const WindowFrameInput& in);
  Result optimize();
  // Empties the window (states, landmarks, prior, gauge) for a
  // re-initialisation; keeps every buffer, so no heap allocation.
  void reset();

  const NavState& latest() const;
  bool state_of(int64_t t_ns, NavState* out) const;

  // Marginal covariance of the newest state's pose [dp (W), dphi (B)] (the
  // order and frames of PoseCovariance) from the last solve of our solver: the
  // inverse of the reduced camera system (landmarks Schur-eliminated) it last
  // Cholesky-factored, H_red = L L'. The newest state is last in the system,
  // so its block is Y'Y with Y = L_nn^-1 [I6; 0] over the trailing 15x15
  // factor: 6 triangular solves, fixed capacity, no heap. That is the
  // Gauss-Newton covariance at that linearisation, with that factorisation's
  // Levenberg-Marquardt damping (lambda D: negligible once converged; it can
  // only make the figure smaller), and relative to the window's gauge (the
  // oldest state's position and yaw are pinned). Drift from before the window
  // is added: each time the gauge moves on, the new gauge's covariance
  // relative to the old one (position, and yaw about W z with its lever arm)
  // is compounded into a running gauge covariance (first order; correlations
  // between moves are ignored). While a map pose factor is in the window it
  // replaces the gauge: the covariance is then relative to the map factors
  // (their sigmas), and the drift chain restarts. valid = false after a Ceres solve or a failed
  // factorisation. Computed at the end of each optimize(); this read is a
  // seqlock copy, safe from the tracking thread while the optimizer runs.
  PoseCovariance newest_pose_covariance() const;

  // For tests and benchmarks.
  int num_states() const { return problem_->n_states; }
  int num_landmarks() const;     // initialised landmarks in the problem
  int prior_dimension() const;   // rows of the marginalisation prior in use (0: none)
  double evaluate_cost() const;  // cost at the current estimates
  const Counters& counters() const { return counters_; }
  const WindowOptions& options() const { return problem_->opt; }
  WindowProblem& problem() { return *problem_; }
  const WindowProblem& problem() const { return *problem_; }
  // Our solver regardless of options().solver (for the cross-check).
  Result optimize_ours();

 private:
  struct Workspace;
  struct LmProblem;  // the window as levenberg_marquardt.hpp's problem
  void marginalize_or_drop(int slot);
  void remove_state(int slot);
  void add_observations(int slot, const WindowFrameInput& in);
  int find_or_create_landmark(uint32_t id);
  void free_landmark(int lm);
  void reset_gauge();
  void publish_newest_covariance();

  std::unique_ptr<WindowProblem> problem_;
  std::unique_ptr<Workspace> ws_;
  Counters counters_;
};

const char* to_string(WindowOptimizer::Status s);

}  // namespace kestrel::core

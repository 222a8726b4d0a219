// Outlier rejection for frame-to-frame translation given the IMU rotation:
// LONSC (paper 000, Algorithm 1, "Longest Successive Consistency") and, for
// comparison and as a fallback, a 2-point RANSAC with the same minimal solver
// and the same consistency test.
//
// Both classes size every buffer once at construction (capacity = most
// correspondences per call) and never allocate in estimate(). Results that
// are arrays (inlier mask, inlier indices) live in the estimator and stay
// valid until its next estimate() call.
//
// LONSC depends on the ORDER of the correspondences: a run is a stretch of
// consecutive ones consistent with one motion. CorrespondenceOrderer builds
// the permutation; docs/lonsc.md explains why kByMatchCost is the default.
#pragma once

#include <cstddef>
#include <cstdint>
#include <iosfwd>
#include <memory>

#include "kestrel/core/motion_estimation.hpp"

namespace kestrel::core {

enum class CorrespondenceOrder : uint8_t {
  kAsGiven,      // matcher order (for a FAST/raster detector: roughly image rows)
  kByMatchCost,  // ascending match_cost: most reliable matches first
  kHilbert,      // along a Hilbert curve over u_cur: neighbours in the image are neighbours in the run
  kShuffled,     // random permutation from a seed (the control)
};
const char* to_string(CorrespondenceOrder o);

// Builds permutations into caller memory using preallocated scratch.
class CorrespondenceOrderer {
 public:
  explicit CorrespondenceOrderer(std::size_t capacity);
  ~CorrespondenceOrderer();
  CorrespondenceOrderer(const CorrespondenceOrderer&) = delete;
  CorrespondenceOrderer& operator=(const CorrespondenceOrderer&) = delete;

  // Writes min(n, capacity) indices into order_out; returns how many.
  // image_w/h bound the Hilbert grid (pixels outside are clamped);
  // seed is used by kShuffled only. Ties break by index (deterministic).
  std::size_t order(CorrespondenceOrder mode, const Correspondence2D3D* c, std::size_t n, uint32_t* order_out,
                    double image_w = 640, double image_h = 480, uint64_t seed = 1) const;
  std::size_t capacity() const { return capacity_; }

 private:
  static constexpr uint32_t kCountingSortRange = 1024;  // integral costs below this use a counting sort
  std::size_t capacity_;
  std::unique_ptr<uint64_t[]> keys_;
  std::unique_ptr<uint32_t[]> counts_;
};

// Common result of LonscEstimator and TwoPointRansac.
struct MotionEstimate {
  MotionStatus status = MotionStatus::kTooFewCorrespondences;
  Eigen::Vector3d t = Eigen::Vector3d::Zero();  // p_cur = R p_prev + t, R as passed in [m]
  std::size_t num_inliers = 0;
  std::size_t num_used = 0;   // correspondences looked at (min(n, capacity))
  std::size_t truncated = 0;  // n - capacity when the caller passed more than capacity
  // LONSC: longest run; the run whose t_hat was used (the longest unless
  // candidate_runs > 1 found a better-supported one) and where it starts
  // (position in the walk, i.e. the order without unusable entries).
  int longest_run = 0;
  int chosen_run = 0;
  int chosen_run_begin = -1;
  int candidates_evaluated = 0;
  int model_estimates = 0;  // minimal (2-point) solves: LONSC run breaks, RANSAC hypotheses
  int iterations = 0;       // LONSC: consistency tests in the run pass; RANSAC: hypotheses drawn
  double inlier_rms_px = 0;
  bool ok() const { return status == MotionStatus::kOk; }
};

struct LonscOptions {
  ConsistencyTest consistency;  // threshold 3 px by default
  // Runs shorter than this are not trusted (status kNoConsistentRun).
  int min_run_length = 3;
  // Paper: after re-estimating T from (c_{i-1}, c_i), CLen = 1 and T is used
  // as is. With verify_seed_pair the pair must itself be consistent with T
  // (4 equations, 3 unknowns: one degree of redundancy); a consistent pair
  // starts a run of 2, an inconsistent one leaves no model, so the next
  // correspondence seeds a new pair at once. Off = paper-literal.
  bool verify_seed_pair = true;
  // Paper: the model T of a run stays the 2-point solution it started from.
  // With grow_model, every correspondence that joins the run is added to the
  // run's normal equations and T is re-solved (closed-form 3x3, ~20 ns), so
  // the run is tested against the least-squares t of all its members.
  // Off = paper-literal.
  bool grow_model = true;
  // Paper: t_hat from the single longest run. With K > 1 the K longest runs
  // (at most 8) each propose t_hat and the largest consensus wins: costs K
  // passes of consistency tests (fewer: it stops at the first candidate that
  // more than half of the correspondences support), defeats a moving object
  // that happens to give the longest run. 1 = paper-literal.
  int candidate_runs = 3;
  // Minimal-pair degeneracy: pixels closer than this leave t_z unobservable.
  double min_pair_separation_px = 5.0;
  // Paper eq. 3 (plain) or depth-normalised weights (ML, see motion_estimation.hpp).
  bool weighted_least_squares = true;
  // Extra "collect inliers with the current t, re-solve" passes after the
  // paper's final least squares (0 = paper-literal).
  int refine_passes = 1;
  std::size_t min_inliers = 6;

  // Algorithm 1 as the paper prints it: the run's model is the 2-point T that
  // started it, a new pair is trusted unchecked and starts a run of 1, the
  // single longest run gives t_hat, plain least squares (eq. 3), no extra
  // passes, and a run of 2 is a run. The config's `frontend.lonsc_variant:
  // paper` selects it (docs/lonsc.md measures both).
  static LonscOptions paper();
};

struct RansacOptions {
  ConsistencyTest consistency;
  double confidence = 0.99;
  int max_iterations = 500;
  uint64_t seed = 0x5eed5eedULL;
  bool reseed_each_call = true;  // same input -> same output (replay determinism)
  double min_pair_separation_px = 5.0;
  bool weighted_least_squares = true;
  int refine_passes = 1;
  std::size_t min_inliers = 6;
};

std::ostream& operator<<(std::ostream& os, const LonscOptions& o);
std::ostream& operator<<(std::ostream& os, const RansacOptions& o);

// Shared fixed-capacity workspace for both estimators.
class MotionWorkspace {
 public:
  explicit MotionWorkspace(std::size_t capacity);
  ~MotionWorkspace();
  MotionWorkspace(const MotionWorkspace&) = delete;
  MotionWorkspace& operator=(const MotionWorkspace&) = delete;

  std::size_t capacity() const { return capacity_; }
  // Last call's results, valid until the next estimate().
  const uint8_t* inlier_mask() const { return mask_.get(); }         // [num_used], by correspondence index
  const uint32_t* inlier_indices() const { return inliers_.get(); }  // [num_inliers], ascending

  // Optional 6-DoF step after estimate(): Gauss-Newton on the inliers of `est`
  // starting from (R, t) (usually the IMU R and est->t), then the inlier set
  // (mask, indices, est->num_inliers) is re-collected with the refined pose.
  // R_prior (the IMU rotation) is used when opt.rotation_prior_sigma_rad > 0.
  PoseRefineResult refine_pose(Eigen::Matrix3d* R, Eigen::Vector3d* t, const PinholeK& K,
                               const Correspondence2D3D* c, std::size_t n, MotionEstimate* est,
                               const ConsistencyTest& test, const PoseRefineOptions& opt = {},
                               const Eigen::Matrix3d* R_prior = nullptr);

 protected:
  // Collects the inliers of t into mask_/inliers_; returns their count.
  std::size_t collect_inliers(const Eigen::Vector3d& t, const PinholeK& K, const Correspondence2D3D* c,
                              std::size_t n, const ConsistencyTest& test, double* rms_px);
  // Least squares on c[idx[0..k)] given the R of precompute(). Weighted: depth
  // weights from t_ref, or from a plain first solve when t_ref is null.
  MotionStatus solve_on(const uint32_t* idx, std::size_t k, const PinholeK& K, const Correspondence2D3D* c,
                        bool weighted, const Eigen::Vector3d* t_ref, Eigen::Vector3d* t) const;
  // Minimal solve on correspondences i, j. False when degenerate.
  bool solve_pair(std::size_t i, std::size_t j, const PinholeK& K, const Correspondence2D3D* c,
                  double min_sep_px, Eigen::Vector3d* t) const;
  // Common tail: Phi from t_hat, least squares on Phi, optional re-collection
  // passes. precollected: mask_/inliers_ already hold Phi of t_hat (its size).
  static constexpr std::size_t kNotCollected = ~std::size_t{0};
  void finish(const Eigen::Vector3d& t_hat, const PinholeK& K, const Correspondence2D3D* c, std::size_t n,
              const ConsistencyTest& test, bool weighted, int refine_passes, std::size_t min_inliers,
              MotionEstimate* out, std::size_t precollected = kNotCollected);
  void precompute(const Eigen::Matrix3d& R, const Correspondence2D3D* c, std::size_t n);

  std::size_t capacity_;
  std::unique_ptr<Eigen::Vector3d[]> Rp_;  // R * p_prev per correspondence
  std::unique_ptr<uint8_t[]> usable_;
  std::unique_ptr<uint8_t[]> mask_;
  std::unique_ptr<uint32_t[]> inliers_;
  std::unique_ptr<uint32_t[]> run_;  // indices of the longest run
};

class LonscEstimator : public MotionWorkspace {
 public:
  explicit LonscEstimator(std::size_t capacity, const LonscOptions& opt = {});
  const LonscOptions& options() const { return opt_; }
  void set_options(const LonscOptions& opt) { opt_ = opt; }

  // R: rotation from the IMU (p_cur = R p_prev + t). order: permutation of
  // [0, n) to walk (null = as given); entries >= n are skipped. t_init: the
  // paper's initial T (0 there); a velocity prediction works too.
  MotionEstimate estimate(const Eigen::Matrix3d& R, const PinholeK& K, const Correspondence2D3D* c,
                          std::size_t n, const uint32_t* order = nullptr,
                          const Eigen::Vector3d& t_init = Eigen::Vector3d::Zero());

 private:
  LonscOptions opt_;
};

class TwoPointRansac : public MotionWorkspace {
 public:
  explicit TwoPointRansac(std::size_t capacity, const RansacOptions& opt = {});
  const RansacOptions& options() const { return opt_; }
  void set_options(const RansacOptions& opt);

  MotionEstimate estimate(const Eigen::Matrix3d& R, const PinholeK& K, const Correspondence2D3D* c,
                          std::size_t n);

 private:
  uint64_t next_random();
  RansacOptions opt_;
  uint64_t rng_state_;
};

}  // namespace kestrel::core

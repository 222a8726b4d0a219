// 6-DoF frame-to-keyframe motion without an IMU rotation (RGB-D tracking;
// docs/real-imagery.md). Every correspondence pairs a keyframe point with a
// pixel of the current frame (Correspondence2D3D); where the current pixel
// has a depth too, the pair is a 3D-3D one and three of them fix the motion
// (a closed-form rigid fit, Horn/Kabsch: SVD of the 3x3 cross-covariance).
//
// Two ways to find the consistent set:
//  - LONSC's idea carried over to the 3-point model (lonsc.hpp): walk the
//    correspondences in order (most reliable match first), seed a model from
//    three consecutive 3D-3D pairs, let it grow while the next pairs agree
//    (re-fitted on the run's members as it grows), start a new seed where
//    the run breaks; the longest runs propose the motion and the one with
//    the largest consensus wins.
//  - RANSAC over random triples, the reference (adaptive stopping).
// Consistency: the reprojection test of motion_estimation.hpp and, for pairs
// with a current depth, the 3D distance within depth_tol_rel * z + depth_tol_m.
//
// Buffers are sized once at construction; estimate_*() never allocate.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <memory>

#include "kestrel/core/motion_estimation.hpp"

namespace kestrel::core {

struct RigidOptions {
  ConsistencyTest consistency;        // reprojection bound, 3 px by default
  double depth_tol_rel = 0.04;        // 3D distance bound, share of the current depth...
  double depth_tol_m = 0.02;          // ...plus this (depth noise and registration error)
  int min_run_length = 5;             // LONSC: shorter runs are not trusted
  int candidate_runs = 3;             // LONSC: longest runs that each propose a motion, at most 8
  double min_sample_spread_m = 0.05;  // a triple whose points are closer than this is degenerate
  std::size_t min_inliers = 8;
  // RANSAC.
  double confidence = 0.99;
  int max_iterations = 300;
  uint64_t seed = 0x5eed0003ULL;  // re-seeded every call: same input, same output
};

enum class RigidMethod : uint8_t { kLonsc = 0, kRansac = 1 };
const char* to_string(RigidMethod m);

struct RigidEstimate {
  MotionStatus status = MotionStatus::kTooFewCorrespondences;
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();  // p_cur = R p_prev + t
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
  std::size_t num_inliers = 0;
  std::size_t num_3d = 0;   // correspondences with a current depth
  int model_estimates = 0;  // rigid fits (seeds, growth re-fits, hypotheses): a 3x3 SVD each
  // Pairs tested against a model: the cost that scales with the matches (a
  // RANSAC hypothesis tests all of them, a LONSC growth step one).
  std::size_t consistency_checks = 0;
  int hypotheses = 0;   // models whose consensus was counted
  int longest_run = 0;  // LONSC
  double inlier_rms_px = 0;
  bool ok() const { return status == MotionStatus::kOk; }
};

class RigidConsensus {
 public:
  explicit RigidConsensus(std::size_t capacity, const RigidOptions& opt = {});
  ~RigidConsensus();
  RigidConsensus(const RigidConsensus&) = delete;
  RigidConsensus& operator=(const RigidConsensus&) = delete;

  const RigidOptions& options() const { return opt_; }
  void set_options(const RigidOptions& o) { opt_ = o; }
  std::size_t capacity() const { return capacity_; }

  // q_cur[i]: the current frame's point of c[i] (camera frame, from its
  // depth) where has_q[i] != 0. order: the walk (null = as given; LONSC
  // only). At most capacity() correspondences are looked at.
  RigidEstimate estimate(RigidMethod method, const PinholeK& K, const Correspondence2D3D* c,
                         const Eigen::Vector3d* q_cur, const uint8_t* has_q, std::size_t n,
                         const uint32_t* order = nullptr);
  // The last estimate's inliers, ascending; valid until the next call.
  const uint32_t* inlier_indices() const { return inliers_.get(); }

 private:
  bool consistent(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const PinholeK& K, std::size_t i) const;
  std::size_t consensus(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const PinholeK& K, std::size_t n,
                        bool collect, double* rms_px);
  void walk_lonsc(const PinholeK& K, std::size_t n, const uint32_t* order, RigidEstimate* out);
  void run_ransac(const PinholeK& K, std::size_t n, RigidEstimate* out);

  std::size_t capacity_;
  RigidOptions opt_;
  const Correspondence2D3D* c_ = nullptr;
  const Eigen::Vector3d* q_ = nullptr;
  const uint8_t* has_q_ = nullptr;
  std::unique_ptr<uint32_t[]> usable3d_;  // indices of 3D-3D pairs in walk order
  std::unique_ptr<uint32_t[]> inliers_;
  uint64_t rng_ = 0;
  mutable std::size_t checks_ = 0;  // consistency_checks of the current estimate
};

// Closed-form rigid fit q = R p + t of n >= 3 pairs (Horn/Kabsch); false when
// the points are (nearly) collinear or coincide.
bool fit_rigid(const Eigen::Vector3d* p, const Eigen::Vector3d* q, const uint32_t* idx, std::size_t n,
               Eigen::Matrix3d* R, Eigen::Vector3d* t);

}  // namespace kestrel::core

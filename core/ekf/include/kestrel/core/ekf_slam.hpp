// EKF visual-inertial SLAM on SE(3) (paper 003, made fast): the `ekf`
// backend for boards too small for the keyframe-window optimizer.
//
// State: the body (IMU) pose T_WB in SE(3) [+ v_WB, gyro and accelerometer
// biases in IMU mode] and a bounded active set of world landmarks m_W, with ONE
// joint covariance (paper 003's combined update, without its split into a
// pose part and a map part). Error state, in this order:
//   velocity mode: [rho, theta] (6)              T_WB = T_hat exp([rho; theta]^)
//   IMU mode:      [rho, theta, dv, dbg, dba] (15)
//   then 3 per active landmark (additive, world frame).
//
// Fixed memory: every matrix is allocated in the constructor for the landmark
// capacity; predict / propagate / update never touch the heap (tests/ekf proves
// it with a malloc counter). Per-step cost is bounded by the capacity.
// No explicit inverse anywhere: the Kalman gain comes from a Cholesky
// factorisation of the innovation covariance, processed in chunks of
// landmarks (sequential updates, each linearised at the current mean).
// Details and derivations: docs/ekf.md.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/core/ekf_geometry.hpp"

namespace kestrel::core {

enum class EkfMotionModel : uint8_t {
  kVelocity = 0,  // paper 003: measured body twist (v_B, w_B) as the input
  kImu = 1,       // accelerometer + gyro input, biases in the state
};

struct EkfSlamOptions {
  EkfMotionModel motion = EkfMotionModel::kVelocity;
  int landmark_capacity = 256;      // active landmarks held in the filter (memory ~ (3C)^2 doubles)
  int max_observations = 1024;      // per update call; more are counted and ignored
  int update_chunk_landmarks = 32;  // landmarks per sequential Cholesky update (<= 32)

  double pixel_sigma_px = 1.0;      // std of each of uL, vL, uR, vR
  double gate_chi2 = 13.28;         // Mahalanobis gate on the 4 stereo rows (chi2, 4 dof, 99 %)
  double mono_gate_chi2 = 9.21;     // the same gate on a pixel without depth (chi2, 2 dof, 99 %)
  double min_depth_m = 0.5;         // points closer than this are neither used nor initialised
  double max_init_depth_m = 60.0;   // far points triangulate badly: not initialised
  int max_missed_frames = 0;        // an active landmark unobserved for more frames is frozen into the map
  int max_consecutive_rejects = 2;  // a landmark gated out this often in a row is dropped as an outlier

  // Velocity mode: std of the measured twist, per component (W = dt^2 diag).
  double vel_sigma_mps = 0.3;
  double gyro_vel_sigma_rps = 0.02;

  // IMU mode: continuous-time densities (Kalibr convention) and gravity.
  double gyro_noise_density = 1.7e-4;  // rad/s/sqrt(Hz)
  double acc_noise_density = 2.0e-3;   // m/s^2/sqrt(Hz)
  double gyro_random_walk = 2.0e-5;    // rad/s^2/sqrt(Hz)
  double acc_random_walk = 3.0e-3;     // m/s^3/sqrt(Hz)
  double gravity_mps2 = 9.81;          // W has gravity along -z

  // > 0: the observations are RGB-D pixels with depth as virtual stereo
  // (virtual_stereo()): u, v and the virtual disparity d = fx b / depth are
  // independent with stds pixel_sigma_px, pixel_sigma_px and this, so
  // R = [[s2, 0, s2], [0, s2, 0], [s2, 0, s2 + sd2]] in [uL, v, uR] (vL = vR
  // are one measurement, not two). With a depth noise sigma_z = k z^2 the
  // disparity noise is fx b k whatever the depth. 0: a real stereo pair.
  double rgbd_disparity_sigma_px = 0.0;

  // New tracks take the free slots spread over the image: with more
  // candidates than slots, a cell of this grid over [0, image_width_px) x
  // [0, image_height_px) (in uL, vL) with fewer landmarks seen this frame is
  // served first. Landmarks bunched in one corner constrain the pose far
  // worse than as many spread out. 0 columns: the front end's order.
  int spread_grid_cols = 0;
  int spread_grid_rows = 0;
  double image_width_px = 0.0;
  double image_height_px = 0.0;

  // Throws std::invalid_argument naming the field.
  void validate() const;
  // Every effective setting, one per line.
  std::string describe() const;
};

// One stereo (or virtual-stereo) observation of a landmark, paper 003's
// z = [uL, vL, uR, vR] in pixels. `id` is the front end's track id.
struct StereoObservation {
  uint32_t id = 0;
  double uL = 0.0, vL = 0.0, uR = 0.0, vR = 0.0;
  // The point is known already (a bundle-adjusted map point, in W, with an
  // isotropic 1-sigma): a new landmark starts there, independent of the
  // pose, instead of from this observation. 0: unknown.
  double prior_sigma_m = 0.0;
  Eigen::Vector3d prior_p_W = Eigen::Vector3d::Zero();
  // false: only (uL, vL) was measured, a pixel without depth (beyond the
  // sensor's range, a hole in the depth image). It updates a landmark already
  // in the filter with its 2 rows, and starts a new one only at a known
  // point (prior_sigma_m > 0): one pixel does not place a point.
  bool has_depth = true;
};

// A pixel without depth (StereoObservation::has_depth false).
StereoObservation pixel_only(uint32_t id, double u, double v);

// An RGB-D pixel with registered depth as a virtual stereo observation:
// uR = u - fx * b / depth (docs/ekf.md, "RGB-D").
StereoObservation virtual_stereo(uint32_t id, double u, double v, double depth_m, double fx,
                                 double baseline_m);

// A landmark that left the filter: its last estimate and marginal covariance.
struct FrozenLandmark {
  uint32_t id = 0;
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  uint32_t observations = 0;
};

struct EkfUpdateStats {
  int observations = 0;        // given to update()
  int used = 0;                // in the Kalman update
  int used_without_depth = 0;  // of those, 2-row updates from a pixel without depth
  int gated = 0;               // rejected by the chi2 gate
  int initialised = 0;         // new landmarks
  int not_initialised = 0;     // new tracks not taken (bad disparity, too far, capacity full)
  int frozen = 0;              // left the filter into the map
  int dropped = 0;             // removed as outliers
  int chunks = 0;              // sequential Cholesky updates
  // Normalised innovation squared of the first chunk, linearised at the
  // prior (before any of this update's corrections), and its degrees of
  // freedom (3 per observation, 2 without depth): about nis_dof when the filter's predicted
  // uncertainty matches its actual errors.
  double nis = 0.0;
  int nis_dof = 0;
  // The pose correction the whole update made, xi = log(T_prior^-1 T_post),
  // against the covariance it should have, P_prior - P_post (pose block):
  // about 6 in a consistent filter, larger when the prediction was worse
  // than the propagated covariance claimed. 0 without an update.
  double pose_nis = 0.0;
};

struct EkfCounters {
  uint64_t predictions = 0;
  uint64_t updates = 0;
  uint64_t observations_used = 0;
  uint64_t observations_used_without_depth = 0;  // of those, pixels without depth (2 rows)
  uint64_t observations_gated = 0;
  uint64_t observations_ignored = 0;  // beyond max_observations, or duplicates in one call
  uint64_t landmarks_initialised = 0;
  uint64_t landmarks_from_prior = 0;  // of those, started at a known point (StereoObservation::prior_sigma_m)
  uint64_t landmarks_frozen = 0;
  uint64_t landmarks_dropped = 0;
  uint64_t capacity_full = 0;      // new tracks not taken because the active set was full
  uint64_t frozen_lost = 0;        // frozen landmarks lost because the caller did not drain them
  uint64_t cholesky_failures = 0;  // chunks skipped because S was not positive definite
};

class EkfSlam {
 public:
  EkfSlam(const EkfSlamOptions& options, const ekf::StereoCamera& camera);

  // Sets the state and clears every landmark. Pose covariance is given in the
  // [rho, theta] right-perturbation convention; in IMU mode velocity and bias
  // stds are set separately.
  void reset(const ekf::Pose& T_WB, const ekf::Mat6& P_pose);
  void reset_imu(const ekf::Pose& T_WB, const Eigen::Vector3d& v_WB, const Eigen::Vector3d& bg,
                 const Eigen::Vector3d& ba, const ekf::Mat6& P_pose, double v_sigma, double bg_sigma,
                 double ba_sigma);

  // Velocity mode: T <- T exp(dt [v; w]^), covariance through Ad(exp(-dt u^)).
  void predict_velocity(const Eigen::Vector3d& v_B_mps, const Eigen::Vector3d& w_B_rps, double dt_s);
  // IMU mode: one strapdown step with the sample held over dt.
  void propagate_imu(const Eigen::Vector3d& gyro_rps, const Eigen::Vector3d& acc_mps2, double dt_s);

  // Every IMU noise density is multiplied by k from the next propagation on
  // (EkfEstimator's imu_noise_inflation); 1 at construction.
  void set_imu_noise_scale(double k) { imu_noise_k2_ = k * k; }
  double imu_noise_scale() const { return std::sqrt(imu_noise_k2_); }

  // Updates with the landmarks already in the filter, freezes those no longer
  // seen, then initialises new tracks from their first observation.
  EkfUpdateStats update(const StereoObservation* obs, int count);

  // A direct measurement of the body pose, T_meas = T_WB exp(n), n ~ N(0, R)
  // in the filter's [rho, theta] order (e.g. a PnP on mapped points). Gated
  // at gate_chi2 (6 dof); false when refused or not positive definite.
  // Corrects pose, velocity, biases and every active landmark through their
  // correlations. Allocation-free.
  bool update_pose(const ekf::Pose& T_meas, const ekf::Mat6& R, double gate_chi2, double* nis = nullptr);

  // Moves every active landmark into the frozen buffer (end of a run).
  void freeze_all();

  // Landmarks that left the filter since the last clear_frozen(). The buffer
  // holds 2 x landmark_capacity entries; drain it after every update() (what
  // does not fit is counted in frozen_lost).
  int frozen_count() const { return frozen_count_; }
  const FrozenLandmark& frozen(int i) const { return frozen_[static_cast<size_t>(i)]; }
  void clear_frozen() { frozen_count_ = 0; }

  const ekf::Pose& pose() const { return T_WB_; }
  const Eigen::Vector3d& v_WB() const { return v_WB_; }
  const Eigen::Vector3d& gyro_bias() const { return bg_; }
  const Eigen::Vector3d& acc_bias() const { return ba_; }
  // Marginal covariance of the pose error [rho, theta] (call after update()
  // for the cross terms to be current; the pose block itself always is).
  ekf::Mat6 pose_covariance() const { return P_.topLeftCorner<6, 6>(); }
  // Full error-state covariance block of the active state (dim x dim).
  Eigen::Block<const Eigen::MatrixXd> covariance() const { return P_.topLeftCorner(dim(), dim()); }

  int dim() const { return dx_ + 3 * num_active_; }
  int pose_dim() const { return dx_; }
  int num_active() const { return num_active_; }
  uint32_t active_id(int slot) const { return lm_id_[static_cast<size_t>(slot)]; }
  Eigen::Vector3d active_position(int slot) const { return lm_p_.col(slot); }

  const EkfSlamOptions& options() const { return opt_; }
  const ekf::StereoCamera& camera() const { return cam_; }
  const EkfCounters& counters() const { return counters_; }

 private:
  using Mat15 = Eigen::Matrix<double, 15, 15>;
  void flush_cross_covariance();
  void propagate_pose_block(const Mat15& Phi, const Mat15& Qd);
  void remove_slot(int slot, bool to_map);
  bool initialise_landmark(const StereoObservation& o);
  void apply_correction(int n);
  int find_slot(uint32_t id) const;
  bool gate(int slot, const StereoObservation& o) const;
  void update_chunk(const int* slots, int count, EkfUpdateStats& stats);
  void symmetric_downdate(int n, int m);

  EkfSlamOptions opt_;
  ekf::StereoCamera cam_;
  int dx_ = 6;                 // error dimension of the non-landmark part
  int cap_ = 0;                // landmark capacity
  int nmax_ = 0;               // dx_ + 3 cap_
  int chunk_ = 32;             // landmarks per sequential update
  Eigen::Matrix3d R_;          // noise of the compressed measurement [uL, v, uR]
  double s2_ = 1.0;            // pixel variance
  double imu_noise_k2_ = 1.0;  // IMU noise variance scale (set_imu_noise_scale)

  // Mean.
  ekf::Pose T_WB_;
  Eigen::Vector3d v_WB_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d bg_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d ba_ = Eigen::Vector3d::Zero();
  Eigen::Matrix3Xd lm_p_;  // 3 x cap; active landmarks live in slots [0, num_active_)
  std::vector<uint32_t> lm_id_;
  std::vector<int> lm_missed_, lm_rejects_, lm_obs_count_, lm_this_obs_, lm_gate_;
  int num_active_ = 0;

  // Covariance (nmax x nmax; the active part is the top-left dim() x dim()).
  // The cross terms pose x landmarks lag behind the pose block: the
  // transitions since the last update are accumulated in Phi_acc_ and applied
  // once, when an update needs them (flush_cross_covariance).
  Eigen::MatrixXd P_;
  Mat15 Phi_acc_ = Mat15::Identity();
  bool phi_pending_ = false;

  // Workspace, allocated once.
  Eigen::MatrixXd pose_tmp_;  // 15 x 15
  ekf::Mat6 P_pose_prior_;
  Eigen::MatrixXd cross_tmp_;  // 15 x nmax
  Eigen::MatrixXd U_;          // nmax x 3 chunk: P H^T, then P H^T L^-T
  Eigen::MatrixXd S_;          // 3 chunk square: innovation covariance, then its Cholesky factor
  Eigen::VectorXd nu_;         // 3 chunk
  Eigen::VectorXd dx_vec_;     // nmax
  std::vector<Eigen::Matrix<double, 3, 6>> Hp_;
  std::vector<Eigen::Matrix3d> Hm_;
  std::vector<int> rows_, row0_;  // per observation of a chunk: 3 (with depth) or 2 rows, from row row0
  std::vector<int> obs_slot_, slot_list_, upd_slots_;
  std::vector<int> cell_count_;  // spread_grid_cols x rows: landmarks seen this frame per cell
  int cell_of(const StereoObservation& o) const;
  void initialise_new_tracks(const StereoObservation* obs, int count, EkfUpdateStats& st);
  const StereoObservation* obs_cache_ = nullptr;  // the observations of the update in progress
  std::vector<FrozenLandmark> frozen_;
  int frozen_count_ = 0;

  EkfCounters counters_;
};

const char* motion_model_name(EkfMotionModel m);

}  // namespace kestrel::core

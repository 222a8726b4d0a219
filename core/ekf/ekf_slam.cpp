#include "kestrel/core/ekf_slam.hpp"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

namespace kestrel::core {

using ekf::Mat3;
using ekf::Mat6;
using ekf::Pose;
using ekf::skew;
using ekf::Vec3;
using ekf::Vec6;

namespace {

// Eigen's GEMM takes its packing buffers from the stack (alloca) when each is
// at most EIGEN_STACK_ALLOCATION_LIMIT (128 KiB = 16384 doubles), and from the
// heap above that. Every dynamic product here is cut into panels of at most
// kPanel rows/columns with a depth of at most 3 * kMaxChunk, so the buffers
// (depth x panel) always stay on the stack: the update never allocates.
constexpr int kMaxChunk = 32;
constexpr int kPanel = 128;
static_assert(3 * kMaxChunk * kPanel <= 16384,
              "GEMM packing buffers must fit Eigen's stack allocation limit");

constexpr int kPoseDim = 6;

}  // namespace

const char* motion_model_name(EkfMotionModel m) {
  switch (m) {
    case EkfMotionModel::kVelocity:
      return "velocity";
    case EkfMotionModel::kImu:
      return "imu";
  }
  return "?";
}

void EkfSlamOptions::validate() const {
  auto fail = [](const std::string& field, const std::string& why) {
    throw std::invalid_argument("ekf option '" + field + "': " + why);
  };
  if (landmark_capacity < 1 || landmark_capacity > 4096) fail("landmark_capacity", "must be in [1, 4096]");
  if (max_observations < 1) fail("max_observations", "must be >= 1");
  if (update_chunk_landmarks < 1 || update_chunk_landmarks > kMaxChunk)
    fail("update_chunk_landmarks", "must be in [1, 32]");
  if (!(pixel_sigma_px > 0.0)) fail("pixel_sigma_px", "must be > 0");
  if (!(gate_chi2 > 0.0)) fail("gate_chi2", "must be > 0");
  if (!(mono_gate_chi2 > 0.0)) fail("mono_gate_chi2", "must be > 0");
  if (!(min_depth_m > 0.0)) fail("min_depth_m", "must be > 0");
  if (!(max_init_depth_m > min_depth_m)) fail("max_init_depth_m", "must be > min_depth_m");
  if (max_missed_frames < 0) fail("max_missed_frames", "must be >= 0");
  if (max_consecutive_rejects < 1) fail("max_consecutive_rejects", "must be >= 1");
  if (!(vel_sigma_mps >= 0.0) || !(gyro_vel_sigma_rps >= 0.0))
    fail("vel_sigma_mps/gyro_vel_sigma_rps", "must be >= 0");
  if (!(gyro_noise_density >= 0.0) || !(acc_noise_density >= 0.0) || !(gyro_random_walk >= 0.0) ||
      !(acc_random_walk >= 0.0))
    fail("imu noise", "densities must be >= 0");
  if (!(gravity_mps2 > 0.0)) fail("gravity_mps2", "must be > 0");
  if (!(rgbd_disparity_sigma_px >= 0.0)) fail("rgbd_disparity_sigma_px", "must be >= 0");
  if (spread_grid_cols < 0 || spread_grid_cols > 32 || spread_grid_rows < 0 || spread_grid_rows > 32)
    fail("spread_grid_cols/rows", "must be in [0, 32]");
  if (spread_grid_cols > 0 && !(spread_grid_rows > 0 && image_width_px > 0.0 && image_height_px > 0.0))
    fail("spread_grid_rows/image_width_px/image_height_px", "must be > 0 with spread_grid_cols > 0");
}

std::string EkfSlamOptions::describe() const {
  std::ostringstream s;
  s << "motion_model: " << motion_model_name(motion) << "\n"
    << "landmark_capacity: " << landmark_capacity << "\n"
    << "spread_grid: " << spread_grid_cols << " x " << spread_grid_rows << "\n"
    << "max_observations: " << max_observations << "\n"
    << "update_chunk_landmarks: " << update_chunk_landmarks << "\n"
    << "pixel_sigma_px: " << pixel_sigma_px << "\n"
    << "gate_chi2: " << gate_chi2 << "\n"
    << "mono_gate_chi2: " << mono_gate_chi2 << "\n"
    << "min_depth_m: " << min_depth_m << "\n"
    << "max_init_depth_m: " << max_init_depth_m << "\n"
    << "max_missed_frames: " << max_missed_frames << "\n"
    << "max_consecutive_rejects: " << max_consecutive_rejects << "\n";
  if (rgbd_disparity_sigma_px > 0.0) s << "rgbd_disparity_sigma_px: " << rgbd_disparity_sigma_px << "\n";
  if (motion == EkfMotionModel::kVelocity) {
    s << "vel_sigma_mps: " << vel_sigma_mps << "\n"
      << "gyro_vel_sigma_rps: " << gyro_vel_sigma_rps << "\n";
  } else {
    s << "gyro_noise_density: " << gyro_noise_density << "\n"
      << "acc_noise_density: " << acc_noise_density << "\n"
      << "gyro_random_walk: " << gyro_random_walk << "\n"
      << "acc_random_walk: " << acc_random_walk << "\n"
      << "gravity_mps2: " << gravity_mps2 << "\n";
  }
  return s.str();
}

StereoObservation virtual_stereo(uint32_t id, double u, double v, double depth_m, double fx,
                                 double baseline_m) {
  StereoObservation o;
  o.id = id;
  o.uL = u;
  o.vL = v;
  o.uR = u - fx * baseline_m / depth_m;
  o.vR = v;
  return o;
}

StereoObservation pixel_only(uint32_t id, double u, double v) {
  StereoObservation o;
  o.id = id;
  o.uL = o.uR = u;
  o.vL = o.vR = v;
  o.has_depth = false;
  return o;
}

EkfSlam::EkfSlam(const EkfSlamOptions& options, const ekf::StereoCamera& camera)
    : opt_(options), cam_(camera) {
  opt_.validate();
  if (!(cam_.fsu > 0.0) || !(cam_.fsv > 0.0) || !(cam_.baseline_m > 0.0))
    throw std::invalid_argument("ekf camera: fsu, fsv and baseline_m must be > 0");
  dx_ = opt_.motion == EkfMotionModel::kImu ? 15 : 6;
  cap_ = opt_.landmark_capacity;
  nmax_ = dx_ + 3 * cap_;
  chunk_ = opt_.update_chunk_landmarks;
  const double s2 = opt_.pixel_sigma_px * opt_.pixel_sigma_px;
  s2_ = s2;
  R_.setZero();
  if (opt_.rgbd_disparity_sigma_px > 0.0) {
    // Virtual stereo: u, v and the disparity d are measured independently
    // and uR = u - d, so uR carries u's error too (docs/ekf.md, "RGB-D").
    const double d2 = opt_.rgbd_disparity_sigma_px * opt_.rgbd_disparity_sigma_px;
    R_ << s2, 0, s2, 0, s2, 0, s2, 0, s2 + d2;
  } else {
    R_.diagonal() = Vec3(s2, 0.5 * s2, s2);  // the v row is the mean of vL and vR
  }

  lm_p_.setZero(3, cap_);
  const auto cap = static_cast<size_t>(cap_);
  lm_id_.assign(cap, 0);
  lm_missed_.assign(cap, 0);
  lm_rejects_.assign(cap, 0);
  lm_obs_count_.assign(cap, 0);
  lm_this_obs_.assign(cap, -1);
  lm_gate_.assign(cap, 0);
  P_.setZero(nmax_, nmax_);
  pose_tmp_.setZero(15, 15);
  cross_tmp_.setZero(15, nmax_);
  // update_pose needs 6 columns whatever the chunk size.
  const int work_cols = std::max(3 * chunk_, 6);
  U_.setZero(nmax_, work_cols);
  S_.setZero(work_cols, work_cols);
  nu_.setZero(work_cols);
  dx_vec_.setZero(nmax_);
  Hp_.resize(static_cast<size_t>(chunk_));
  Hm_.resize(static_cast<size_t>(chunk_));
  rows_.assign(static_cast<size_t>(chunk_), 3);
  row0_.assign(static_cast<size_t>(chunk_), 0);
  obs_slot_.assign(static_cast<size_t>(opt_.max_observations), -1);
  cell_count_.assign(static_cast<size_t>(std::max(1, opt_.spread_grid_cols * opt_.spread_grid_rows)), 0);
  upd_slots_.assign(cap, 0);
  slot_list_.assign(cap, 0);
  frozen_.resize(2 * cap);
  reset(Pose(), Mat6::Identity() * 1e-12);
}

void EkfSlam::reset(const Pose& T_WB, const Mat6& P_pose) {
  reset_imu(T_WB, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), P_pose, 1.0, 0.01, 0.1);
}

void EkfSlam::reset_imu(const Pose& T_WB, const Vec3& v_WB, const Vec3& bg, const Vec3& ba,
                        const Mat6& P_pose, double v_sigma, double bg_sigma, double ba_sigma) {
  T_WB_ = T_WB;
  v_WB_ = v_WB;
  bg_ = bg;
  ba_ = ba;
  num_active_ = 0;
  P_.setZero();
  P_.topLeftCorner<6, 6>() = 0.5 * (P_pose + P_pose.transpose());
  if (dx_ == 15) {
    P_.block<3, 3>(6, 6) = Mat3::Identity() * v_sigma * v_sigma;
    P_.block<3, 3>(9, 9) = Mat3::Identity() * bg_sigma * bg_sigma;
    P_.block<3, 3>(12, 12) = Mat3::Identity() * ba_sigma * ba_sigma;
  }
  Phi_acc_.setIdentity();
  phi_pending_ = false;
  frozen_count_ = 0;
}

// ---- prediction ----------------------------------------------------------------

void EkfSlam::propagate_pose_block(const Mat15& Phi, const Mat15& Qd) {
  const int d = dx_;
  auto Pxx = P_.topLeftCorner(d, d);
  pose_tmp_.topLeftCorner(d, d).noalias() = Phi.topLeftCorner(d, d) * Pxx;
  Pxx.noalias() = pose_tmp_.topLeftCorner(d, d) * Phi.topLeftCorner(d, d).transpose();
  Pxx += Qd.topLeftCorner(d, d);
  for (int c = 0; c < d; ++c)
    for (int r = c + 1; r < d; ++r) Pxx(c, r) = Pxx(r, c) = 0.5 * (Pxx(r, c) + Pxx(c, r));
  if (num_active_ > 0) {
    const Mat15 acc = Phi * Phi_acc_;
    Phi_acc_ = acc;
    phi_pending_ = true;
  }
  ++counters_.predictions;
}

void EkfSlam::predict_velocity(const Vec3& v_B_mps, const Vec3& w_B_rps, double dt_s) {
  if (!(dt_s > 0.0) || !v_B_mps.allFinite() || !w_B_rps.allFinite()) return;
  Vec6 xi;
  xi << v_B_mps * dt_s, w_B_rps * dt_s;
  const Pose step = ekf::se3_exp(xi);
  T_WB_ = T_WB_ * step;
  // delta+ = exp(-dt u^) delta + w: the error transforms by the adjoint of the
  // inverse step (paper 003, section III.C).
  Mat15 Phi = Mat15::Identity();
  Phi.topLeftCorner<6, 6>() = ekf::se3_adjoint(step.inverse());
  Mat15 Qd = Mat15::Zero();
  const double sv = opt_.vel_sigma_mps * dt_s, sw = opt_.gyro_vel_sigma_rps * dt_s;
  Qd.diagonal().segment<3>(0).setConstant(sv * sv);
  Qd.diagonal().segment<3>(3).setConstant(sw * sw);
  propagate_pose_block(Phi, Qd);
}

void EkfSlam::propagate_imu(const Vec3& gyro_rps, const Vec3& acc_mps2, double dt_s) {
  if (dx_ != 15 || !(dt_s > 0.0) || !gyro_rps.allFinite() || !acc_mps2.allFinite()) return;
  ekf::ImuNominal x{T_WB_, v_WB_, bg_, ba_};
  Mat15 Phi;
  Eigen::Matrix<double, 15, 12> G;
  ekf::imu_step(x, gyro_rps, acc_mps2, dt_s, opt_.gravity_mps2, &Phi, &G);
  T_WB_ = x.T_WB;
  v_WB_ = x.v_WB;
  // Discrete noise: white densities over dt (variance density / dt per
  // sample), bias random walks.
  Eigen::Matrix<double, 12, 1> qn;
  qn << Vec3::Constant(opt_.gyro_noise_density * opt_.gyro_noise_density / dt_s),
      Vec3::Constant(opt_.acc_noise_density * opt_.acc_noise_density / dt_s),
      Vec3::Constant(opt_.gyro_random_walk * opt_.gyro_random_walk / dt_s),
      Vec3::Constant(opt_.acc_random_walk * opt_.acc_random_walk / dt_s);
  qn *= imu_noise_k2_;
  const Mat15 Qd = G * qn.asDiagonal() * G.transpose();
  propagate_pose_block(Phi, Qd);
}

void EkfSlam::flush_cross_covariance() {
  if (!phi_pending_) return;
  phi_pending_ = false;
  const int d = dx_, nl = 3 * num_active_;
  if (nl > 0) {
    auto Pxl = P_.block(0, d, d, nl);
    for (int c0 = 0; c0 < nl; c0 += kPanel) {
      const int cb = std::min(kPanel, nl - c0);
      cross_tmp_.block(0, c0, d, cb).noalias() = Phi_acc_.topLeftCorner(d, d) * Pxl.middleCols(c0, cb);
    }
    Pxl = cross_tmp_.topLeftCorner(d, nl);
    P_.block(d, 0, nl, d) = Pxl.transpose();
  }
  Phi_acc_.setIdentity();
}

// ---- landmark management -------------------------------------------------------

int EkfSlam::find_slot(uint32_t id) const {
  // Linear search: the active set is small and bounded, and a scan of a few
  // hundred integers is cheaper than keeping a hash table in step.
  for (int s = 0; s < num_active_; ++s)
    if (lm_id_[static_cast<size_t>(s)] == id) return s;
  return -1;
}

void EkfSlam::remove_slot(int slot, bool to_map) {
  const auto s = static_cast<size_t>(slot);
  const int n = dim();
  const int a = dx_ + 3 * slot;
  if (to_map) {
    if (frozen_count_ < static_cast<int>(frozen_.size())) {
      FrozenLandmark& f = frozen_[static_cast<size_t>(frozen_count_++)];
      f.id = lm_id_[s];
      f.p_W = lm_p_.col(slot);
      f.cov = P_.block<3, 3>(a, a);
      f.observations = static_cast<uint32_t>(lm_obs_count_[s]);
    } else {
      ++counters_.frozen_lost;
    }
  }
  // Dropping a landmark's rows and columns is its exact marginalisation. The
  // last slot moves into the hole so the active state stays contiguous.
  const int last = num_active_ - 1;
  if (slot != last) {
    const int b = dx_ + 3 * last;
    const auto l = static_cast<size_t>(last);
    lm_p_.col(slot) = lm_p_.col(last);
    lm_id_[s] = lm_id_[l];
    lm_missed_[s] = lm_missed_[l];
    lm_rejects_[s] = lm_rejects_[l];
    lm_obs_count_[s] = lm_obs_count_[l];
    lm_this_obs_[s] = lm_this_obs_[l];
    lm_gate_[s] = lm_gate_[l];
    P_.block(0, a, n, 3) = P_.block(0, b, n, 3);
    P_.block(a, 0, 3, n) = P_.block(b, 0, 3, n);
  }
  --num_active_;
}

bool EkfSlam::initialise_landmark(const StereoObservation& o) {
  Vec3 p_C;
  Mat3 J_z;
  if (o.has_depth) {
    const ekf::StereoMeas z(o.uL, 0.5 * (o.vL + o.vR), o.uR);
    const double s2 = opt_.pixel_sigma_px * opt_.pixel_sigma_px;
    // vL - vR is pure noise for a rectified pair: a large one is a bad match.
    if ((o.vL - o.vR) * (o.vL - o.vR) > 2.0 * s2 * 6.63) return false;
    if (!ekf::stereo_triangulate(cam_, z, p_C, &J_z)) return false;
    if (!(p_C.z() >= opt_.min_depth_m && p_C.z() <= opt_.max_init_depth_m)) return false;
  } else {
    // One pixel does not place a point; a known one it may bring in, if the
    // map's position is in front of the camera.
    ekf::StereoMeas zh;
    if (!(o.prior_sigma_m > 0.0) || !ekf::stereo_project(cam_, T_WB_, o.prior_p_W, opt_.min_depth_m, zh))
      return false;
  }
  if (num_active_ >= cap_) {
    ++counters_.capacity_full;
    return false;
  }
  const int n = dim();
  const int slot = num_active_;
  if (o.prior_sigma_m > 0.0) {
    // A point the map knows: its position and sigma, uncorrelated with the
    // state (the window's map-point prior, as a filter takes it). The
    // observation that brought it was checked above like any new track's.
    lm_p_.col(slot) = o.prior_p_W;
    P_.block(n, 0, 3, n).setZero();
    P_.block(0, n, n, 3).setZero();
    P_.block<3, 3>(n, n) = Mat3::Identity() * (o.prior_sigma_m * o.prior_sigma_m);
    ++counters_.landmarks_from_prior;
  } else {
    const Pose T_BC = cam_.T_CB.inverse();
    const Vec3 p_B = T_BC * p_C;
    // m(xi, z) = T_WB exp(xi^) T_BC p_C(z): Jacobians for the correlated
    // initialisation (the new landmark inherits the pose uncertainty).
    Eigen::Matrix<double, 3, 6> Jx;
    Jx.leftCols<3>() = T_WB_.R;
    Jx.rightCols<3>() = -T_WB_.R * skew(p_B);
    const Mat3 Jz = T_WB_.R * T_BC.R * J_z;
    lm_p_.col(slot) = T_WB_ * p_B;
    // Row block: P(m, :) = Jx P(pose, :).
    cross_tmp_.topLeftCorner(3, n).noalias() = Jx * P_.topLeftCorner(kPoseDim, n);
    P_.block(n, 0, 3, n) = cross_tmp_.topLeftCorner(3, n);
    P_.block(0, n, n, 3) = cross_tmp_.topLeftCorner(3, n).transpose();
    const Mat3 Pmm = Jx * P_.topLeftCorner<6, 6>() * Jx.transpose() + Jz * R_ * Jz.transpose();
    P_.block<3, 3>(n, n) = 0.5 * (Pmm + Pmm.transpose());
  }
  const auto s = static_cast<size_t>(slot);
  lm_id_[s] = o.id;
  lm_missed_[s] = 0;
  lm_rejects_[s] = 0;
  lm_obs_count_[s] = 1;
  lm_this_obs_[s] = -1;
  lm_gate_[s] = 0;
  ++num_active_;
  ++counters_.landmarks_initialised;
  return true;
}

void EkfSlam::freeze_all() {
  flush_cross_covariance();
  while (num_active_ > 0) {
    remove_slot(num_active_ - 1, true);
    ++counters_.landmarks_frozen;
  }
}

// ---- update --------------------------------------------------------------------

bool EkfSlam::gate(int slot, const StereoObservation& o) const {
  ekf::StereoMeas zh;
  Eigen::Matrix<double, 3, 6> Hp;
  Mat3 Hm;
  if (!ekf::stereo_project(cam_, T_WB_, lm_p_.col(slot), opt_.min_depth_m, zh, &Hp, &Hm)) return false;
  const int a = dx_ + 3 * slot;
  Eigen::Matrix<double, 9, 9> Ps;
  Ps.topLeftCorner<6, 6>() = P_.topLeftCorner<6, 6>();
  Ps.topRightCorner<6, 3>() = P_.block<6, 3>(0, a);
  Ps.bottomLeftCorner<3, 6>() = P_.block<3, 6>(a, 0);
  Ps.bottomRightCorner<3, 3>() = P_.block<3, 3>(a, a);
  Eigen::Matrix<double, 3, 9> H;
  H << Hp, Hm;
  Mat3 S = H * Ps * H.transpose();
  if (!o.has_depth) {
    // The pixel's two rows, each with the pixel noise (vL alone, not the
    // mean of a pair).
    const Eigen::Matrix2d S2 = S.topLeftCorner<2, 2>() + s2_ * Eigen::Matrix2d::Identity();
    const Eigen::Vector2d nu2(o.uL - zh(0), o.vL - zh(1));
    const Eigen::LLT<Eigen::Matrix2d> llt2(S2);
    if (llt2.info() != Eigen::Success) return false;
    return nu2.dot(llt2.solve(nu2)) <= opt_.mono_gate_chi2;
  }
  S += R_;
  const Vec3 nu(o.uL - zh(0), 0.5 * (o.vL + o.vR) - zh(1), o.uR - zh(2));
  const Eigen::LLT<Mat3> llt(S);
  if (llt.info() != Eigen::Success) return false;
  const double dv = o.vL - o.vR;
  const double d2 = nu.dot(llt.solve(nu)) + dv * dv / (2.0 * s2_);
  return d2 <= opt_.gate_chi2;
}

void EkfSlam::symmetric_downdate(int n, int m) {
  // P -= W W^T over the lower panels, mirrored into the upper ones.
  for (int j0 = 0; j0 < n; j0 += kPanel) {
    const int jb = std::min(kPanel, n - j0);
    for (int i0 = j0; i0 < n; i0 += kPanel) {
      const int ib = std::min(kPanel, n - i0);
      P_.block(i0, j0, ib, jb).noalias() -= U_.block(i0, 0, ib, m) * U_.block(j0, 0, jb, m).transpose();
      if (i0 != j0) P_.block(j0, i0, jb, ib) = P_.block(i0, j0, ib, jb).transpose();
    }
    for (int c = 0; c < jb; ++c) {
      for (int r = c + 1; r < jb; ++r) {
        const double v = 0.5 * (P_(j0 + r, j0 + c) + P_(j0 + c, j0 + r));
        P_(j0 + r, j0 + c) = v;
        P_(j0 + c, j0 + r) = v;
      }
    }
  }
}

void EkfSlam::apply_correction(int n) {
  const Vec6 xi = dx_vec_.head<6>();
  T_WB_ = T_WB_ * ekf::se3_exp(xi);
  if (dx_ == 15) {
    v_WB_ += dx_vec_.segment<3>(6);
    bg_ += dx_vec_.segment<3>(9);
    ba_ += dx_vec_.segment<3>(12);
  }
  for (int s = 0; 3 * s + dx_ < n; ++s) lm_p_.col(s) += dx_vec_.segment<3>(dx_ + 3 * s);
}

bool EkfSlam::update_pose(const Pose& T_meas, const ekf::Mat6& R, double gate_chi2, double* nis) {
  flush_cross_covariance();
  const int n = dim();
  // r = log(T_hat^-1 T_meas) = xi + n to first order: H = [I6 0].
  const Vec6 r = ekf::se3_log(T_WB_.inverse() * T_meas);
  ekf::Mat6 S6 = P_.topLeftCorner<6, 6>() + R;
  S6 = (0.5 * (S6 + S6.transpose())).eval();  // fixed size: no heap temporary
  Eigen::Ref<Eigen::MatrixXd> S(S_.topLeftCorner(6, 6));
  S = S6;
  Eigen::LLT<Eigen::Ref<Eigen::MatrixXd>> llt(S);
  if (llt.info() != Eigen::Success) {
    ++counters_.cholesky_failures;
    return false;
  }
  nu_.head<6>() = r;
  llt.matrixL().solveInPlace(nu_.head(6));
  const double d2 = nu_.head<6>().squaredNorm();
  if (nis != nullptr) *nis = d2;
  if (!(d2 <= gate_chi2)) return false;
  // U = P H^T = the pose columns; W = U L^-T; dx = W L^-1 r; P -= W W^T.
  U_.topLeftCorner(n, 6) = P_.leftCols<6>().topRows(n);
  for (int r0 = 0; r0 < n; r0 += kPanel) {
    const int rb = std::min(kPanel, n - r0);
    llt.matrixU().solveInPlace<Eigen::OnTheRight>(U_.block(r0, 0, rb, 6));
  }
  dx_vec_.head(n).noalias() = U_.topLeftCorner(n, 6) * nu_.head(6);
  symmetric_downdate(n, 6);
  apply_correction(n);
  return true;
}

namespace {

// The chunk's products for one observation of R rows (3 with depth, 2
// without), at fixed size so that nothing is sized at run time.
template <int R>
void chunk_gain_columns(const Eigen::MatrixXd& P, int n, int a, const Eigen::Matrix<double, 3, 6>& Hp,
                        const Mat3& Hm, Eigen::MatrixXd& U, int c) {
  auto Ui = U.middleCols<R>(c).topRows(n);
  Ui.noalias() = P.leftCols<6>().topRows(n) * Hp.topRows<R>().transpose();
  Ui.noalias() += P.middleCols<3>(a).topRows(n) * Hm.topRows<R>().transpose();
}

template <int R>
void chunk_innovation_rows(const Eigen::MatrixXd& U, int m, int a, const Eigen::Matrix<double, 3, 6>& Hp,
                           const Mat3& Hm, Eigen::MatrixXd& S, int r) {
  auto Si = S.middleRows<R>(r).leftCols(m);
  Si.noalias() = Hp.topRows<R>() * U.topRows<6>().leftCols(m);
  Si.noalias() += Hm.topRows<R>() * U.middleRows<3>(a).leftCols(m);
}

}  // namespace

void EkfSlam::update_chunk(const int* slots, int count, EkfUpdateStats& stats) {
  const int n = dim();
  // Linearise every observation of the chunk at the current mean: 3 rows
  // [uL, v, uR] with depth, the first 2 without.
  int k = 0, m = 0, k_mono = 0;
  for (int i = 0; i < count; ++i) {
    const int slot = slots[i];
    const auto ki = static_cast<size_t>(k);
    ekf::StereoMeas zh;
    if (!ekf::stereo_project(cam_, T_WB_, lm_p_.col(slot), opt_.min_depth_m, zh, &Hp_[ki], &Hm_[ki]))
      continue;
    const int oi = lm_this_obs_[static_cast<size_t>(slot)];
    const StereoObservation& ob = obs_cache_[static_cast<size_t>(oi)];
    row0_[ki] = m;
    if (ob.has_depth) {
      nu_.segment<3>(m) = Vec3(ob.uL - zh(0), 0.5 * (ob.vL + ob.vR) - zh(1), ob.uR - zh(2));
      rows_[ki] = 3;
    } else {
      nu_.segment<2>(m) = Eigen::Vector2d(ob.uL - zh(0), ob.vL - zh(1));
      rows_[ki] = 2;
      ++k_mono;
    }
    m += rows_[ki];
    upd_slots_[ki] = slot;  // compacted in place: slots[] is read ahead of k
    ++k;
  }
  if (k == 0) return;
  // U = P H^T, using the sparsity of H (pose columns + one landmark).
  for (int i = 0; i < k; ++i) {
    const auto ii = static_cast<size_t>(i);
    const int a = dx_ + 3 * upd_slots_[ii];
    if (rows_[ii] == 3) {
      chunk_gain_columns<3>(P_, n, a, Hp_[ii], Hm_[ii], U_, row0_[ii]);
    } else {
      chunk_gain_columns<2>(P_, n, a, Hp_[ii], Hm_[ii], U_, row0_[ii]);
    }
  }
  // S = H P H^T + R.
  for (int i = 0; i < k; ++i) {
    const auto ii = static_cast<size_t>(i);
    const int a = dx_ + 3 * upd_slots_[ii];
    const int r = row0_[ii];
    if (rows_[ii] == 3) {
      chunk_innovation_rows<3>(U_, m, a, Hp_[ii], Hm_[ii], S_, r);
      S_.block<3, 3>(r, r) += R_;
    } else {
      // A pixel alone: u and v each with the pixel noise (vL, not a pair's mean).
      chunk_innovation_rows<2>(U_, m, a, Hp_[ii], Hm_[ii], S_, r);
      S_(r, r) += s2_;
      S_(r + 1, r + 1) += s2_;
    }
  }
  // S = L L^T in place; K = U S^-1 is never formed: W = U L^-T gives both the
  // correction W (L^-1 nu) and the covariance downdate W W^T.
  Eigen::Ref<Eigen::MatrixXd> S_ref(S_.topLeftCorner(m, m));
  Eigen::LLT<Eigen::Ref<Eigen::MatrixXd>> llt(S_ref);
  if (llt.info() != Eigen::Success) {
    ++counters_.cholesky_failures;
    return;
  }
  for (int r0 = 0; r0 < n; r0 += kPanel) {
    const int rb = std::min(kPanel, n - r0);
    llt.matrixU().solveInPlace<Eigen::OnTheRight>(U_.block(r0, 0, rb, m));
  }
  llt.matrixL().solveInPlace(nu_.head(m));
  if (stats.chunks == 0) {
    stats.nis = nu_.head(m).squaredNorm();
    stats.nis_dof = m;
  }
  dx_vec_.head(n).noalias() = U_.topLeftCorner(n, m) * nu_.head(m);
  symmetric_downdate(n, m);
  apply_correction(n);
  stats.used += k;
  stats.used_without_depth += k_mono;
  ++stats.chunks;
}

EkfUpdateStats EkfSlam::update(const StereoObservation* obs, int count) {
  EkfUpdateStats st;
  st.observations = count;
  ++counters_.updates;
  if (count > opt_.max_observations) {
    counters_.observations_ignored += static_cast<uint64_t>(count - opt_.max_observations);
    count = opt_.max_observations;
  }
  if (count < 0) count = 0;
  obs_cache_ = obs;
  flush_cross_covariance();

  // Associate by id; an id given twice in one call keeps its first observation.
  for (int s = 0; s < num_active_; ++s) lm_this_obs_[static_cast<size_t>(s)] = -1;
  for (int i = 0; i < count; ++i) {
    const int s = find_slot(obs[i].id);
    obs_slot_[static_cast<size_t>(i)] = s;
    if (s < 0) continue;
    if (lm_this_obs_[static_cast<size_t>(s)] >= 0) {
      ++counters_.observations_ignored;
      obs_slot_[static_cast<size_t>(i)] = -2;
      continue;
    }
    lm_this_obs_[static_cast<size_t>(s)] = i;
  }
  // Landmarks not seen for too long leave the filter into the map.
  for (int s = num_active_ - 1; s >= 0; --s) {
    const auto ss = static_cast<size_t>(s);
    if (lm_this_obs_[ss] >= 0) {
      lm_missed_[ss] = 0;
      continue;
    }
    if (++lm_missed_[ss] > opt_.max_missed_frames) {
      remove_slot(s, true);
      ++st.frozen;
      ++counters_.landmarks_frozen;
    }
  }
  // Chi2 gate at the prior; repeat offenders are dropped, not mapped.
  for (int s = num_active_ - 1; s >= 0; --s) {
    const auto ss = static_cast<size_t>(s);
    const int oi = lm_this_obs_[ss];
    lm_gate_[ss] = 0;
    if (oi < 0) continue;
    if (gate(s, obs[oi])) {
      lm_gate_[ss] = 1;
      lm_rejects_[ss] = 0;
      ++lm_obs_count_[ss];
      continue;
    }
    ++st.gated;
    ++counters_.observations_gated;
    if (++lm_rejects_[ss] >= opt_.max_consecutive_rejects) {
      remove_slot(s, false);
      ++st.dropped;
      ++counters_.landmarks_dropped;
    }
  }
  // Sequential Cholesky updates over chunks of landmarks. slot_list_ holds the
  // accepted slots; update_chunk compacts into upd_slots_ (a separate array).
  int nacc = 0;
  for (int s = 0; s < num_active_; ++s)
    if (lm_gate_[static_cast<size_t>(s)] == 1) slot_list_[static_cast<size_t>(nacc++)] = s;
  const Pose T_prior = T_WB_;
  P_pose_prior_ = P_.topLeftCorner<6, 6>();
  for (int c0 = 0; c0 < nacc; c0 += chunk_) {
    update_chunk(slot_list_.data() + c0, std::min(chunk_, nacc - c0), st);
  }
  if (st.used >= 2) {  // one landmark's 3 rows leave P_prior - P_post rank-deficient
    const Vec6 xi = ekf::se3_log(T_prior.inverse() * T_WB_);
    const ekf::Mat6 D = P_pose_prior_ - P_.topLeftCorner<6, 6>();
    const Eigen::LDLT<ekf::Mat6> ldlt(0.5 * (D + D.transpose()));
    if (ldlt.info() == Eigen::Success && ldlt.isPositive()) st.pose_nis = xi.dot(ldlt.solve(xi));
  }
  counters_.observations_used += static_cast<uint64_t>(st.used);
  counters_.observations_used_without_depth += static_cast<uint64_t>(st.used_without_depth);

  initialise_new_tracks(obs, count, st);
  obs_cache_ = nullptr;
  return st;
}

int EkfSlam::cell_of(const StereoObservation& o) const {
  const int cx = static_cast<int>(std::floor(o.uL * opt_.spread_grid_cols / opt_.image_width_px));
  const int cy = static_cast<int>(std::floor(o.vL * opt_.spread_grid_rows / opt_.image_height_px));
  return std::clamp(cy, 0, opt_.spread_grid_rows - 1) * opt_.spread_grid_cols +
         std::clamp(cx, 0, opt_.spread_grid_cols - 1);
}

// New tracks, initialised from the updated pose.
void EkfSlam::initialise_new_tracks(const StereoObservation* obs, int count, EkfUpdateStats& st) {
  auto try_one = [&](int i) {
    obs_slot_[static_cast<size_t>(i)] = -3;  // tried
    if (find_slot(obs[i].id) >= 0) {         // the same new id twice in one call
      ++counters_.observations_ignored;
      return;
    }
    if (initialise_landmark(obs[i])) {
      ++st.initialised;
    } else {
      ++st.not_initialised;
    }
  };
  int n_new = 0;
  for (int i = 0; i < count; ++i) n_new += obs_slot_[static_cast<size_t>(i)] == -1;
  if (opt_.spread_grid_cols > 0 && n_new > cap_ - num_active_) {
    // Round by round, a cell with at most `level` landmarks takes one more,
    // until the slots are full: the emptiest parts of the image first.
    std::fill(cell_count_.begin(), cell_count_.end(), 0);
    for (int s = 0; s < num_active_; ++s) {
      const int oi = lm_this_obs_[static_cast<size_t>(s)];
      if (oi >= 0) ++cell_count_[static_cast<size_t>(cell_of(obs[oi]))];
    }
    // Each round starts at the emptiest cell any candidate is in, so the
    // rounds are bounded by the free slots, not by the fullest cell.
    while (num_active_ < cap_) {
      int level = std::numeric_limits<int>::max();
      for (int i = 0; i < count; ++i) {
        if (obs_slot_[static_cast<size_t>(i)] == -1)
          level = std::min(level, cell_count_[static_cast<size_t>(cell_of(obs[i]))]);
      }
      if (level == std::numeric_limits<int>::max()) break;
      for (int i = 0; i < count && num_active_ < cap_; ++i) {
        if (obs_slot_[static_cast<size_t>(i)] != -1) continue;
        int& c = cell_count_[static_cast<size_t>(cell_of(obs[i]))];
        if (c > level) continue;
        const int before = num_active_;
        try_one(i);
        if (num_active_ > before) ++c;
      }
    }
  }
  // The rest in the front end's order (with no grid: all of them); once the
  // slots are full they are counted as refused for capacity.
  for (int i = 0; i < count; ++i)
    if (obs_slot_[static_cast<size_t>(i)] == -1) try_one(i);
}

}  // namespace kestrel::core

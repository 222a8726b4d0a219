#include "kestrel/core/preintegration.hpp"

#include <Eigen/Cholesky>
#include <cmath>

#include "kestrel/core/so3.hpp"

namespace kestrel::core {
namespace {

using so3::Exp;
using so3::hat;
using so3::Log;

bool finite_positive(double x) { return std::isfinite(x) && x > 0.0; }

// exp(-dt/tau) of the Ornstein-Uhlenbeck accelerometer bias; 1 for a plain
// random walk.
double acc_bias_decay(double dt_s, double tau_s) { return tau_s > 0.0 ? std::exp(-dt_s / tau_s) : 1.0; }

}  // namespace

ImuNoiseParams ImuNoiseParams::from_imu_noise(const ImuNoise& n, double rate_hz) {
  ImuNoiseParams p;
  p.gyro_noise_density_rad_s_sqrthz = n.gyro_noise_density_rad_s_sqrthz;
  p.acc_noise_density_mps2_sqrthz = n.acc_noise_density_mps2_sqrthz;
  p.gyro_random_walk_rad_s2_sqrthz = n.gyro_random_walk_rad_s2_sqrthz;
  p.acc_random_walk_mps3_sqrthz = n.acc_random_walk_mps3_sqrthz;
  p.acc_bias_tau_s = n.acc_bias_tau_s;
  p.rate_hz = rate_hz;
  p = p.scaled(1.0);  // fills the discrete variances
  return p;
}

ImuNoiseParams ImuNoiseParams::scaled(double k) const {
  ImuNoiseParams p = *this;
  p.gyro_noise_density_rad_s_sqrthz *= k;
  p.acc_noise_density_mps2_sqrthz *= k;
  p.gyro_random_walk_rad_s2_sqrthz *= k;
  p.acc_random_walk_mps3_sqrthz *= k;
  const double dt = rate_hz > 0.0 ? 1.0 / rate_hz : 0.0;
  const auto sq = [](double x) { return x * x; };
  p.gyro_var_d = dt > 0.0 ? sq(p.gyro_noise_density_rad_s_sqrthz) / dt : 0.0;
  p.acc_var_d = dt > 0.0 ? sq(p.acc_noise_density_mps2_sqrthz) / dt : 0.0;
  p.gyro_bias_var_d = sq(p.gyro_random_walk_rad_s2_sqrthz) * dt;
  p.acc_bias_var_d = sq(p.acc_random_walk_mps3_sqrthz) * dt;
  return p;
}

bool ImuNoiseParams::valid() const {
  return finite_positive(gyro_noise_density_rad_s_sqrthz) && finite_positive(acc_noise_density_mps2_sqrthz) &&
         finite_positive(gyro_random_walk_rad_s2_sqrthz) && finite_positive(acc_random_walk_mps3_sqrthz) &&
         finite_positive(rate_hz) && std::isfinite(acc_bias_tau_s);
}

PreintegrationParams PreintegrationParams::from_rig(const Rig& rig) {
  PreintegrationParams p;
  p.noise = ImuNoiseParams::from_rig(rig);
  p.gravity_mps2 = rig.gravity_mps2;
  return p;
}

Preintegrated::Preintegrated(const PreintegrationParams& params) : params_(params) {
  reset(Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero(), 0);
}

void Preintegrated::reset(const Eigen::Vector3d& bg_rps, const Eigen::Vector3d& ba_mps2, int64_t t_start_ns) {
  bg_ = bg_rps;
  ba_ = ba_mps2;
  dR_.setIdentity();
  dv_.setZero();
  dp_.setZero();
  cov_.setZero();
  dR_dbg_.setZero();
  dv_dbg_.setZero();
  dv_dba_.setZero();
  dp_dbg_.setZero();
  dp_dba_.setZero();
  dt_s_ = 0.0;
  t_start_ns_ = t_start_ns;
  t_end_ns_ = t_start_ns;
  steps_ = 0;
  rejected_ = 0;
}

bool Preintegrated::integrate(const Eigen::Vector3d& gyro_rps, const Eigen::Vector3d& acc_mps2, double dt) {
  if (!(dt > 0.0) || !std::isfinite(dt) || !gyro_rps.allFinite() || !acc_mps2.allFinite()) {
    ++rejected_;
    return false;
  }
  const Eigen::Vector3d w = gyro_rps - bg_;
  const Eigen::Vector3d a = acc_mps2 - ba_;
  const Eigen::Vector3d phi = w * dt;
  const Eigen::Matrix3d dR_step = Exp(phi);
  const Eigen::Matrix3d Jr = so3::right_jacobian(phi);
  const Eigen::Matrix3d a_hat = hat(a);
  const Eigen::Matrix3d R_a_hat = dR_ * a_hat;  // dR_ik a^
  const double dt2 = dt * dt;

  // Covariance (Forster eq. 62-63), everything taken at step k, before the
  // update:
  //   A = [ dR_step^T          0     0 ]     B_g = [ Jr dt ]   B_a = [ 0           ]
  //       [ -dR a^ dt          I     0 ]           [ 0     ]         [ dR dt       ]
  //       [ -1/2 dR a^ dt^2    I dt  I ]           [ 0     ]         [ 1/2 dR dt^2 ]
  Matrix9d A = Matrix9d::Identity();
  A.block<3, 3>(0, 0) = dR_step.transpose();
  A.block<3, 3>(3, 0) = -R_a_hat * dt;
  A.block<3, 3>(6, 0) = -0.5 * R_a_hat * dt2;
  A.block<3, 3>(6, 3) = Eigen::Matrix3d::Identity() * dt;
  Eigen::Matrix<double, 9, 3> Bg = Eigen::Matrix<double, 9, 3>::Zero();
  Bg.block<3, 3>(0, 0) = Jr * dt;
  Eigen::Matrix<double, 9, 3> Ba = Eigen::Matrix<double, 9, 3>::Zero();
  Ba.block<3, 3>(3, 0) = dR_ * dt;
  Ba.block<3, 3>(6, 0) = 0.5 * dR_ * dt2;
  const double ng = params_.noise.gyro_noise_density_rad_s_sqrthz;
  const double na = params_.noise.acc_noise_density_mps2_sqrthz;
  const double var_gd = ng * ng / dt;  // discrete white noise over this step (Forster eq. 47 ff.)
  const double var_ad = na * na / dt;
  const Matrix9d cov_prop = A * cov_ * A.transpose();
  cov_ = cov_prop;
  cov_.noalias() += var_gd * (Bg * Bg.transpose());
  cov_.noalias() += var_ad * (Ba * Ba.transpose());
  cov_ = 0.5 * (cov_ + cov_.transpose()).eval();

  // Bias Jacobians (Forster Appendix B), also from step-k values; position
  // before velocity before rotation.
  dp_dba_ += dv_dba_ * dt - 0.5 * dR_ * dt2;
  dp_dbg_ += dv_dbg_ * dt - 0.5 * R_a_hat * dR_dbg_ * dt2;
  dv_dba_ -= dR_ * dt;
  dv_dbg_ -= R_a_hat * dR_dbg_ * dt;
  dR_dbg_ = (dR_step.transpose() * dR_dbg_ - Jr * dt).eval();

  // Deltas (Forster eq. 37, Euler).
  dp_ += dv_ * dt + 0.5 * dR_ * a * dt2;
  dv_ += dR_ * a * dt;
  dR_ = (dR_ * dR_step).eval();

  dt_s_ += dt;
  ++steps_;
  return true;
}

bool Preintegrated::integrate_segment(const ImuSample& a, const ImuSample& b, int64_t t0_ns, int64_t t1_ns) {
  const Eigen::Vector3d ga = to_eigen(a.gyro_rps), aa = to_eigen(a.acc_mps2);
  Eigen::Vector3d gyro = ga, acc = aa;
  if (b.t_ns > a.t_ns) {
    if (t0_ns < a.t_ns) t0_ns = a.t_ns;
    if (t1_ns > b.t_ns) t1_ns = b.t_ns;
    if (params_.signal == ImuSignalModel::kLinear) {
      // Mean of the linear signal over [t0, t1] = its value at the centre.
      const double s =
          (0.5 * static_cast<double>(t0_ns + t1_ns - 2 * a.t_ns)) / static_cast<double>(b.t_ns - a.t_ns);
      gyro += s * (to_eigen(b.gyro_rps) - ga);
      acc += s * (to_eigen(b.acc_mps2) - aa);
    }
  }
  if (t1_ns <= t0_ns) {
    ++rejected_;
    return false;
  }
  if (!integrate(gyro, acc, 1e-9 * static_cast<double>(t1_ns - t0_ns))) return false;
  t_end_ns_ = t1_ns;
  return true;
}

Matrix9d Preintegrated::sqrt_information() const {
  const Eigen::LLT<Matrix9d> llt(cov_);
  Matrix9d W = Matrix9d::Identity();
  llt.matrixL().solveInPlace(W);
  return W;
}

PreintegratedDelta Preintegrated::corrected_delta(const Eigen::Vector3d& bg_rps,
                                                  const Eigen::Vector3d& ba_mps2) const {
  const Eigen::Vector3d dbg = bg_rps - bg_;
  const Eigen::Vector3d dba = ba_mps2 - ba_;
  PreintegratedDelta d;
  d.R = dR_ * Exp(dR_dbg_ * dbg);
  d.v = dv_ + dv_dbg_ * dbg + dv_dba_ * dba;
  d.p = dp_ + dp_dbg_ * dbg + dp_dba_ * dba;
  return d;
}

Vector9d imu_residual(const Preintegrated& pim, const NavState& x_i, const NavState& x_j,
                      ImuFactorJacobians* J) {
  const double dt = pim.dt_total();
  const Eigen::Vector3d g = pim.params().gravity_W();
  const Eigen::Matrix3d R_i = x_i.q_WB.toRotationMatrix();
  const Eigen::Matrix3d R_j = x_j.q_WB.toRotationMatrix();
  const Eigen::Matrix3d Rt_i = R_i.transpose();
  const Eigen::Vector3d dbg = x_i.bg_rps - pim.bias_gyro();
  const PreintegratedDelta d = pim.corrected_delta(x_i.bg_rps, x_i.ba_mps2);

  const Eigen::Matrix3d E = d.R.transpose() * Rt_i * R_j;  // Exp(r_R)
  const Eigen::Vector3d dv_W = x_j.v_WB - x_i.v_WB - g * dt;
  const Eigen::Vector3d dp_W = x_j.p_WB - x_i.p_WB - x_i.v_WB * dt - 0.5 * g * dt * dt;
  const Eigen::Vector3d v_Bi = Rt_i * dv_W;
  const Eigen::Vector3d p_Bi = Rt_i * dp_W;

  Vector9d r;
  r.segment<3>(0) = Log(E);
  r.segment<3>(3) = v_Bi - d.v;
  r.segment<3>(6) = p_Bi - d.p;
  if (J == nullptr) return r;

  // Forster eq. 75-79 (Appendix C), but with p and v perturbed in W (so
  // dr/dp_i = -R_i^T, not Forster's -I for p_i <- p_i + R_i dp).
  const Eigen::Matrix3d Jr_inv = so3::right_jacobian_inv(r.segment<3>(0));
  const Eigen::Matrix3d Z = Eigen::Matrix3d::Zero();
  J->phi_i << -Jr_inv * R_j.transpose() * R_i, hat(v_Bi), hat(p_Bi);
  J->p_i << Z, Z, -Rt_i;
  J->v_i << Z, -Rt_i, -Rt_i * dt;
  J->phi_j << Jr_inv, Z, Z;
  J->p_j << Z, Z, Rt_i;
  J->v_j << Z, Rt_i, Z;
  J->bg_i << -Jr_inv * E.transpose() * so3::right_jacobian(pim.dR_dbg() * dbg) * pim.dR_dbg(), -pim.dv_dbg(),
      -pim.dp_dbg();
  J->ba_i << Z, -pim.dv_dba(), -pim.dp_dba();
  return r;
}

NavState predict(const NavState& x_i, const Preintegrated& pim) {
  const double dt = pim.dt_total();
  const Eigen::Vector3d g = pim.params().gravity_W();
  const PreintegratedDelta d = pim.corrected_delta(x_i.bg_rps, x_i.ba_mps2);
  const Eigen::Matrix3d R_i = x_i.q_WB.toRotationMatrix();
  NavState x_j = x_i;
  x_j.t_ns = x_i.t_ns + static_cast<int64_t>(std::llround(dt * 1e9));
  x_j.q_WB = Eigen::Quaterniond(R_i * d.R).normalized();
  x_j.v_WB = x_i.v_WB + g * dt + R_i * d.v;
  x_j.p_WB = x_i.p_WB + x_i.v_WB * dt + 0.5 * g * dt * dt + R_i * d.p;
  x_j.ba_mps2 = acc_bias_decay(dt, pim.params().noise.acc_bias_tau_s) * x_i.ba_mps2;
  return x_j;
}

Vector6d bias_residual(const NavState& x_i, const NavState& x_j, double dt_s, const ImuNoiseParams& noise,
                       BiasFactorJacobians* J) {
  const double a = acc_bias_decay(dt_s, noise.acc_bias_tau_s);
  Vector6d r;
  r.segment<3>(0) = x_j.bg_rps - x_i.bg_rps;
  r.segment<3>(3) = x_j.ba_mps2 - a * x_i.ba_mps2;
  if (J != nullptr) {
    const Eigen::Matrix3d I = Eigen::Matrix3d::Identity();
    const Eigen::Matrix3d Z = Eigen::Matrix3d::Zero();
    J->bg_i << -I, Z;
    J->ba_i << Z, -a * I;
    J->bg_j << I, Z;
    J->ba_j << Z, I;
  }
  return r;
}

Matrix6d bias_covariance(double dt_s, const ImuNoiseParams& noise) {
  const double sg = noise.gyro_random_walk_rad_s2_sqrthz;
  const double sa = noise.acc_random_walk_mps3_sqrthz;
  const double tau = noise.acc_bias_tau_s;
  const double var_a = tau > 0.0 ? sa * sa * 0.5 * tau * (1.0 - std::exp(-2.0 * dt_s / tau)) : sa * sa * dt_s;
  Matrix6d C = Matrix6d::Zero();
  C.diagonal().head<3>().setConstant(sg * sg * dt_s);
  C.diagonal().tail<3>().setConstant(var_a);
  return C;
}

}  // namespace kestrel::core

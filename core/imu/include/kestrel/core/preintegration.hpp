// On-manifold IMU preintegration between two keyframes, its residual (the IMU
// factor) with analytic Jacobians, the bias random-walk factor, and the
// prediction the optimizer uses for initial guesses.
//
// Follows Forster, Carlone, Dellaert, Scaramuzza, "On-Manifold Preintegration
// for Real-Time Visual-Inertial Odometry", TRO 2017 (equation numbers below
// are that paper's); paper 001 restates it in part and paper 000 (eq. 6)
// adds the bounded-random-walk accelerometer bias. Derivations, choices and
// the EuRoC consistency figures: docs/preintegration.md.
//
// Conventions (docs/frames.md): W world with g_W = (0, 0, -g); B body = IMU.
// States are NavState (p_WB, q_WB, v_WB, bg_rps, ba_mps2). Perturbations, for
// every Jacobian here: q_WB <- q_WB * Exp(dphi) (right, in B), p_WB <- p_WB + dp
// (in W), v_WB <- v_WB + dv (in W), b <- b + db. Residual and covariance
// order: [dphi, dv, dp] (rows 0-2 rotation, 3-5 velocity, 6-8 position).
//
// Real-time: fixed-size Eigen only, nothing allocates after construction.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>

#include "kestrel/core/imu_propagator.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::core {

using Vector6d = Eigen::Matrix<double, 6, 1>;
using Vector9d = Eigen::Matrix<double, 9, 1>;
using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Matrix9d = Eigen::Matrix<double, 9, 9>;
using Matrix93d = Eigen::Matrix<double, 9, 3>;
using Matrix63d = Eigen::Matrix<double, 6, 3>;

// IMU noise for preintegration. Continuous-time densities as in the rig
// (Kalibr / EuRoC convention) plus what they become per sample: a white
// noise of density s sampled every dt has variance s^2 / dt (Forster
// eq. 47 ff.: Cov(eta_d) = Cov(eta) / dt); a random walk of density s grows
// by s^2 dt per step.
struct ImuNoiseParams {
  double gyro_noise_density_rad_s_sqrthz = 0;
  double acc_noise_density_mps2_sqrthz = 0;
  double gyro_random_walk_rad_s2_sqrthz = 0;
  double acc_random_walk_mps3_sqrthz = 0;
  // Paper 000 eq. 6: db_a/dt = -b_a / tau + w. <= 0: plain random walk (Forster).
  double acc_bias_tau_s = 0;
  double rate_hz = 0;

  // Per-sample (discrete) variances at the nominal rate, per axis. The
  // integrator uses s^2 / dt with the actual dt, so a split sample interval
  // at a keyframe gets the right (larger) per-step variance.
  double gyro_var_d = 0;       // [rad^2/s^2]
  double acc_var_d = 0;        // [m^2/s^4]
  double gyro_bias_var_d = 0;  // [rad^2/s^2] per sample step
  double acc_bias_var_d = 0;   // [m^2/s^4] per sample step

  static ImuNoiseParams from_imu_noise(const ImuNoise& n, double rate_hz);
  static ImuNoiseParams from_rig(const Rig& rig) { return from_imu_noise(rig.imu, rig.imu_rate_hz); }
  // Every density scaled by k (sigma * k): used for deliberate mis-tuning tests.
  ImuNoiseParams scaled(double k) const;
  // False when a density or the rate is non-positive or non-finite.
  bool valid() const;
};

// How the measured signal is modelled between two samples a, b.
enum class ImuSignalModel : uint8_t {
  // Forster: sample a held over [t_a, t_b) (zero-order hold). Needs no
  // sample after the keyframe time.
  kZeroOrderHold = 0,
  // Linear between samples; a segment [t0, t1] uses the signal's mean, the
  // interpolated value at (t0 + t1)/2 (for a full interval: (a + b)/2).
  // Centres the measurement on the interval instead of lagging by dt/2.
  kLinear = 1,
};

struct PreintegrationParams {
  ImuNoiseParams noise;
  double gravity_mps2 = 9.81;  // EuRoC's convention; 9.80665 is standard gravity
  ImuSignalModel signal = ImuSignalModel::kLinear;

  static PreintegrationParams from_rig(const Rig& rig);
  Eigen::Vector3d gravity_W() const { return {0.0, 0.0, -gravity_mps2}; }
};

// Bias-corrected preintegrated measurement (Forster eq. 44).
struct PreintegratedDelta {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();  // dR_ij
  Eigen::Vector3d v = Eigen::Vector3d::Zero();      // dv_ij [m/s], in B_i
  Eigen::Vector3d p = Eigen::Vector3d::Zero();      // dp_ij [m], in B_i
};

class Preintegrated {
 public:
  explicit Preintegrated(const PreintegrationParams& params = {});

  // Starts a new interval at t_start_ns with the linearisation-point biases.
  void reset(const Eigen::Vector3d& bg_rps, const Eigen::Vector3d& ba_mps2, int64_t t_start_ns = 0);

  // One Forster Euler step (eq. 37-38 deltas, eq. 62-63 covariance,
  // Appendix B bias Jacobians): the raw measurement held for dt_s seconds.
  // Rejects (returns false, counts) non-finite input and dt_s <= 0.
  bool integrate(const Eigen::Vector3d& gyro_rps, const Eigen::Vector3d& acc_mps2, double dt_s);

  // The part [t0_ns, t1_ns] of the interval between consecutive samples a and
  // b (clamped to [a.t_ns, b.t_ns]), under params().signal. This is how a
  // keyframe time that falls between samples is handled: the sample interval
  // is split and each part goes to its own preintegration. Pass a == b to
  // hold one sample (extrapolation) over [t0, t1].
  bool integrate_segment(const ImuSample& a, const ImuSample& b, int64_t t0_ns, int64_t t1_ns);

  // Measurement at the linearisation-point biases.
  const Eigen::Matrix3d& delta_R() const { return dR_; }
  const Eigen::Vector3d& delta_v() const { return dv_; }
  const Eigen::Vector3d& delta_p() const { return dp_; }
  // Cov of [dphi, dv, dp] (Forster eq. 63). Bias uncertainty is not in it:
  // the bias random walk is its own factor (bias_residual below).
  const Matrix9d& covariance() const { return cov_; }
  // Whitening W = L^-1 with covariance = L L^T: ||W r||^2 = r^T Cov^-1 r.
  Matrix9d sqrt_information() const;

  // Bias Jacobians at the linearisation point (Forster Appendix B, eq. 69-70).
  const Eigen::Matrix3d& dR_dbg() const { return dR_dbg_; }
  const Eigen::Matrix3d& dv_dbg() const { return dv_dbg_; }
  const Eigen::Matrix3d& dv_dba() const { return dv_dba_; }
  const Eigen::Matrix3d& dp_dbg() const { return dp_dbg_; }
  const Eigen::Matrix3d& dp_dba() const { return dp_dba_; }

  // First-order bias update without re-integration (Forster eq. 44).
  PreintegratedDelta corrected_delta(const Eigen::Vector3d& bg_rps, const Eigen::Vector3d& ba_mps2) const;

  const Eigen::Vector3d& bias_gyro() const { return bg_; }
  const Eigen::Vector3d& bias_acc() const { return ba_; }
  double dt_total() const { return dt_s_; }  // integrated time [s]
  int64_t t_start_ns() const { return t_start_ns_; }
  int64_t t_end_ns() const { return t_end_ns_; }  // end of the last segment (integrate_segment only)
  int steps() const { return steps_; }
  uint64_t rejected() const { return rejected_; }
  const PreintegrationParams& params() const { return params_; }

 private:
  PreintegrationParams params_;
  Eigen::Vector3d bg_, ba_;
  Eigen::Matrix3d dR_;
  Eigen::Vector3d dv_, dp_;
  Matrix9d cov_;
  Eigen::Matrix3d dR_dbg_, dv_dbg_, dv_dba_, dp_dbg_, dp_dba_;
  double dt_s_ = 0;
  int64_t t_start_ns_ = 0;
  int64_t t_end_ns_ = 0;
  int steps_ = 0;
  uint64_t rejected_ = 0;
};

// What preintegrate_window did with the samples it was given.
struct WindowReport {
  int segments = 0;
  int skipped_unusable = 0;     // NaN / saturated samples bridged over
  int64_t extrapolated_ns = 0;  // span of [t_i, t_j] not bracketed by samples (held from the nearest one)
  bool ok() const { return segments > 0; }
};

// Preintegrates exactly [t_i_ns, t_j_ns] from time-ordered samples: any
// container with size() and operator[] returning ImuSample (std::vector,
// rt::HistoryRing, rt::FixedVector). Sample intervals that straddle t_i or
// t_j are split (integrate_segment). Give it the last sample at or before t_i
// through the first at or after t_j; where they do not bracket the window the
// nearest sample is held and the span is reported. Resets pim first.
template <class Samples>
WindowReport preintegrate_window(Preintegrated& pim, const Samples& samples, int64_t t_i_ns, int64_t t_j_ns,
                                 const Eigen::Vector3d& bg_rps, const Eigen::Vector3d& ba_mps2) {
  WindowReport rep;
  pim.reset(bg_rps, ba_mps2, t_i_ns);
  if (t_j_ns <= t_i_ns) return rep;
  const std::size_t n = samples.size();
  const ImuSample* prev = nullptr;
  int64_t covered_until = t_i_ns;
  for (std::size_t k = 0; k < n; ++k) {
    const ImuSample& s = samples[k];
    if (!imu_sample_usable(s)) {
      ++rep.skipped_unusable;
      continue;
    }
    if (prev == nullptr) {
      if (s.t_ns > t_i_ns) {
        // No sample at or before t_i: hold the first one backwards.
        const int64_t t1 = s.t_ns < t_j_ns ? s.t_ns : t_j_ns;
        if (pim.integrate_segment(s, s, t_i_ns, t1)) ++rep.segments;
        rep.extrapolated_ns += t1 - t_i_ns;
        covered_until = t1;
      }
      prev = &s;
      if (s.t_ns >= t_j_ns) break;
      continue;
    }
    if (s.t_ns <= prev->t_ns) continue;  // out of order / duplicate: the caller's rings count these
    const int64_t t0 = prev->t_ns > covered_until ? prev->t_ns : covered_until;
    const int64_t t1 = s.t_ns < t_j_ns ? s.t_ns : t_j_ns;
    if (t1 > t0) {
      if (pim.integrate_segment(*prev, s, t0, t1)) ++rep.segments;
      covered_until = t1;
    }
    prev = &s;
    if (s.t_ns >= t_j_ns) break;
  }
  if (prev != nullptr && covered_until < t_j_ns) {
    // No sample at or after t_j: hold the last one forwards.
    if (pim.integrate_segment(*prev, *prev, covered_until, t_j_ns)) ++rep.segments;
    rep.extrapolated_ns += t_j_ns - covered_until;
  }
  return rep;
}

// Jacobians of the 9-vector IMU residual w.r.t. each 3-DoF block (see the
// perturbation convention at the top of this file).
struct ImuFactorJacobians {
  Matrix93d phi_i, p_i, v_i, bg_i, ba_i;
  Matrix93d phi_j, p_j, v_j;
};

// Forster eq. 45 with the bias correction of eq. 44 (paper 001, "IMU Factors"):
//   r_R = Log((dR(bg_i))^T R_i^T R_j)
//   r_v = R_i^T (v_j - v_i - g dt) - dv(bg_i, ba_i)
//   r_p = R_i^T (p_j - p_i - v_i dt - 1/2 g dt^2) - dp(bg_i, ba_i)
// dt = pim.dt_total(); the biases are x_i's.
Vector9d imu_residual(const Preintegrated& pim, const NavState& x_i, const NavState& x_j,
                      ImuFactorJacobians* J = nullptr);

// x_j such that imu_residual(pim, x_i, x_j) == 0, with x_i's biases (bg
// carried over, ba decayed by exp(-dt/tau) when tau > 0 so that
// bias_residual is zero too). t_ns advanced by dt_total.
NavState predict(const NavState& x_i, const Preintegrated& pim);

// Bias factor between consecutive keyframes (Forster eq. 48; paper 000 eq. 6
// for the accelerometer): r = [bg_j - bg_i; ba_j - a ba_i], a = exp(-dt/tau)
// (1 with tau <= 0). Rows 0-2 gyro, 3-5 accelerometer.
struct BiasFactorJacobians {
  Matrix63d bg_i, ba_i, bg_j, ba_j;
};
Vector6d bias_residual(const NavState& x_i, const NavState& x_j, double dt_s, const ImuNoiseParams& noise,
                       BiasFactorJacobians* J = nullptr);
// Its covariance: gyro s_bg^2 dt; accelerometer the discrete Ornstein-Uhlenbeck
// variance s_ba^2 tau/2 (1 - exp(-2 dt/tau)) (-> s_ba^2 dt as tau -> inf).
Matrix6d bias_covariance(double dt_s, const ImuNoiseParams& noise);

}  // namespace kestrel::core

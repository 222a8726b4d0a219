#include "kestrel/core/time_offset_calibrator.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

namespace kestrel::core {

std::string TimeOffsetCalibratorOptions::validate() const {
  std::ostringstream e;
  if (!(search_ms > 0.0 && search_ms <= 500.0)) e << "search_ms must be in (0, 500]; ";
  if (!(step_ms > 0.0 && step_ms <= search_ms)) e << "step_ms must be in (0, search_ms]; ";
  if (!(memory_s > 0.0)) e << "memory_s must be > 0; ";
  if (min_intervals < 10) e << "min_intervals must be >= 10; ";
  if (!(max_sigma_ms > 0.0)) e << "max_sigma_ms must be > 0; ";
  if (!(sigma_floor_ms >= 0.0)) e << "sigma_floor_ms must be >= 0; ";
  if (!(gate_rad > 0.0)) e << "gate_rad must be > 0; ";
  if (gyro_capacity < 64) e << "gyro_capacity must be >= 64; ";
  if (!(max_interval_s > 0.0)) e << "max_interval_s must be > 0; ";
  return e.str();
}

TimeOffsetCalibrator::TimeOffsetCalibrator(const TimeOffsetCalibratorOptions& opt,
                                           const Eigen::Matrix3d& R_BC)
    : opt_(opt), R_BC_(R_BC) {
  const std::string err = opt_.validate();
  if (!err.empty()) throw std::invalid_argument("TimeOffsetCalibratorOptions: " + err);
  n_grid_ = 2 * static_cast<int>(std::lround(opt_.search_ms / opt_.step_ms)) + 1;
  gyro_ = std::make_unique<Gyro[]>(static_cast<std::size_t>(opt_.gyro_capacity));
  sdd_ = std::make_unique<double[]>(static_cast<std::size_t>(n_grid_));
  sd_ = std::make_unique<Eigen::Vector3d[]>(static_cast<std::size_t>(n_grid_));
  cost_ = std::make_unique<double[]>(static_cast<std::size_t>(n_grid_));
  d_ = std::make_unique<Eigen::Vector3d[]>(static_cast<std::size_t>(n_grid_));
  reset();
}

TimeOffsetCalibrator::~TimeOffsetCalibrator() = default;

void TimeOffsetCalibrator::reset() {
  g_head_ = g_n_ = 0;
  p_head_ = p_n_ = 0;
  for (int j = 0; j < n_grid_; ++j) {
    sdd_[j] = 0.0;
    sd_[j].setZero();
  }
  stt_ = n_eff_ = 0.0;
  last_t1_ns_ = -1;
  est_ = TimeOffsetEstimate{};
}

namespace {
Eigen::Quaterniond exp_q(const Eigen::Vector3d& phi) {
  const double a = phi.norm();
  if (a < 1e-12) return Eigen::Quaterniond(1.0, 0.5 * phi.x(), 0.5 * phi.y(), 0.5 * phi.z()).normalized();
  return Eigen::Quaterniond(Eigen::AngleAxisd(a, phi / a));
}
Eigen::Vector3d log_q(const Eigen::Quaterniond& q) {
  const Eigen::AngleAxisd aa(q);
  double a = aa.angle();
  if (a > M_PI) a -= 2.0 * M_PI;
  return a * aa.axis();
}
}  // namespace

void TimeOffsetCalibrator::add_gyro(int64_t t_ns, const Eigen::Vector3d& gyro_rps) {
  if (!gyro_rps.allFinite()) return;
  Gyro g{t_ns, gyro_rps, Eigen::Quaterniond::Identity()};
  if (g_n_ > 0) {
    const Gyro& last = gyro_at(g_n_ - 1);
    if (t_ns <= last.t_ns) return;
    // A gap (IMU dropout) would be integrated as a straight line: start over
    // so no interval spans it.
    if (t_ns - last.t_ns > 50'000'000) {
      g_head_ = g_n_ = 0;
    } else {
      g.q = (last.q * exp_q(0.5 * (last.w + gyro_rps) * (1e-9 * static_cast<double>(t_ns - last.t_ns))))
                .normalized();
    }
  }
  if (g_n_ == opt_.gyro_capacity) {
    g_head_ = (g_head_ + 1) % opt_.gyro_capacity;
    --g_n_;
  }
  gyro_[(g_head_ + g_n_) % opt_.gyro_capacity] = g;
  ++g_n_;
  const int64_t search_ns = static_cast<int64_t>(opt_.search_ms * 1e6) + 1;
  while (p_n_ > 0 && pending_[p_head_].t1_ns + search_ns <= t_ns) {
    absorb(pending_[p_head_]);
    p_head_ = (p_head_ + 1) % kPending;
    --p_n_;
  }
}

void TimeOffsetCalibrator::add_camera_rotation(int64_t t0_ns, int64_t t1_ns, const Eigen::Matrix3d& R_C0C1) {
  if (!(t1_ns > t0_ns) || !R_C0C1.allFinite()) return;
  if (1e-9 * static_cast<double>(t1_ns - t0_ns) > opt_.max_interval_s) return;
  if (p_n_ == kPending) {
    ++dropped_;
    return;
  }
  const Eigen::Matrix3d R_B = R_BC_ * R_C0C1 * R_BC_.transpose();
  pending_[(p_head_ + p_n_) % kPending] = Interval{t0_ns, t1_ns, Eigen::Quaterniond(R_B).normalized()};
  ++p_n_;
}

bool TimeOffsetCalibrator::attitude(int64_t t_ns, Eigen::Quaterniond* out) const {
  if (g_n_ < 2 || t_ns < gyro_at(0).t_ns || t_ns > gyro_at(g_n_ - 1).t_ns) return false;
  int lo = 0, hi = g_n_ - 1;  // the last sample at or before t
  while (hi - lo > 1) {
    const int mid = (lo + hi) / 2;
    if (gyro_at(mid).t_ns <= t_ns) {
      lo = mid;
    } else {
      hi = mid;
    }
  }
  const Gyro& a = gyro_at(lo);
  const Gyro& b = gyro_at(std::min(lo + 1, g_n_ - 1));
  const double h = 1e-9 * static_cast<double>(t_ns - a.t_ns);
  const double span = 1e-9 * static_cast<double>(b.t_ns - a.t_ns);
  const Eigen::Vector3d w_t = span > 0.0 ? Eigen::Vector3d(a.w + (b.w - a.w) * (h / span)) : a.w;
  *out = a.q * exp_q(0.5 * (a.w + w_t) * h);
  return true;
}

bool TimeOffsetCalibrator::relative(int64_t a_ns, int64_t b_ns, Eigen::Quaterniond* q_ab) const {
  Eigen::Quaterniond qa, qb;
  if (!attitude(a_ns, &qa) || !attitude(b_ns, &qb)) return false;
  *q_ab = qa.conjugate() * qb;
  return true;
}

void TimeOffsetCalibrator::absorb(const Interval& iv) {
  const int64_t step_ns = static_cast<int64_t>(std::llround(opt_.step_ms * 1e6));
  const int half = (n_grid_ - 1) / 2;
  // d_j = camera rotation - gyro integral shifted by the j-th offset, folded
  // into the sums only once the whole interval passed the gate.
  double best = std::numeric_limits<double>::infinity();
  for (int j = 0; j < n_grid_; ++j) {
    const int64_t tau_ns = static_cast<int64_t>(j - half) * step_ns;
    Eigen::Quaterniond q_gyro;
    if (!relative(iv.t0_ns + tau_ns, iv.t1_ns + tau_ns, &q_gyro)) {
      ++dropped_;
      return;
    }
    // What the gyro's rotation misses of the camera's, as a rotation vector;
    // a small residual gyro bias shows as about dt * bias.
    d_[j] = log_q(q_gyro.conjugate() * iv.q_B0B1);
    best = std::min(best, d_[j].norm());
  }
  if (!(best <= opt_.gate_rad)) {
    ++gated_;
    return;
  }
  const double f =
      last_t1_ns_ >= 0 ? std::exp(-1e-9 * static_cast<double>(iv.t1_ns - last_t1_ns_) / opt_.memory_s) : 1.0;
  last_t1_ns_ = iv.t1_ns;
  const double dt = 1e-9 * static_cast<double>(iv.t1_ns - iv.t0_ns);
  for (int j = 0; j < n_grid_; ++j) {
    const Eigen::Vector3d& d = d_[j];
    sdd_[j] = f * sdd_[j] + d.squaredNorm();
    sd_[j] = f * sd_[j] + dt * d;
  }
  stt_ = f * stt_ + dt * dt;
  n_eff_ = f * n_eff_ + 1.0;
  ++used_;
  solve();
}

void TimeOffsetCalibrator::solve() {
  est_.intervals = n_eff_;
  if (n_eff_ < opt_.min_intervals || !(stt_ > 0.0)) {
    est_.valid = false;
    return;
  }
  int jb = 0;
  for (int j = 0; j < n_grid_; ++j) {
    // The best constant gyro bias for this offset is fitted away.
    cost_[j] = sdd_[j] - sd_[j].squaredNorm() / stt_;
    if (cost_[j] < cost_[jb]) jb = j;
  }
  est_.valid = false;
  est_.sigma_s = 0.0;
  if (jb == 0 || jb == n_grid_ - 1) return;  // the minimum is at the edge: outside the search
  const double cm = cost_[jb - 1], c0 = cost_[jb], cp = cost_[jb + 1];
  const double denom = cm - 2.0 * c0 + cp;
  if (!(denom > 0.0)) return;
  const double step_s = 1e-3 * opt_.step_ms;
  const double frac = 0.5 * (cm - cp) / denom;  // in steps, within [-0.5, 0.5]
  const int half = (n_grid_ - 1) / 2;
  const double td_s = (static_cast<double>(jb - half) + frac) * step_s;
  const double cost_min = std::max(c0 - 0.125 * (cm - cp) * (cm - cp) / denom, 0.0);
  // cost ~ cost_min + curvature/2 (tau - td)^2; the least-squares variance of
  // td is 2 sigma^2 / curvature with sigma^2 the residual variance.
  const double curvature = denom / (step_s * step_s);
  const double dof = std::max(1.0, 3.0 * n_eff_ - 4.0);
  const double sigma_s = std::max(std::sqrt(2.0 * (cost_min / dof) / curvature), 1e-3 * opt_.sigma_floor_ms);
  est_.td_s = td_s;
  est_.residual_rad = std::sqrt(cost_min / dof);
  est_.sigma_s = sigma_s;
  est_.valid = sigma_s <= 1e-3 * opt_.max_sigma_ms;
}

}  // namespace kestrel::core

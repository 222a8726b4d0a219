// Ground-truth files and the cubic B-spline fitted to them.
#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/drivers/text.hpp"
#include "kestrel/tools/sim_trajectory.hpp"

namespace kestrel::tools {
namespace {

namespace text = drivers::text;

std::string where(const std::string& path, size_t line) { return path + ":" + std::to_string(line); }

// Ground-truth stamps: exact, never negative, and no digit below a nanosecond
// silently dropped (a file with finer stamps than the spline can honour is refused).
bool parse_stamp_s(const std::string& s, int64_t& t_ns) {
  int64_t t = 0;
  if (!text::parse_seconds_ns(s, t, text::SecondsSyntax{text::BelowNs::kReject, false}) || t < 0)
    return false;
  t_ns = t;
  return true;
}

// Uniform cubic B-spline basis at u in [0, 1] and its first two derivatives in u.
struct Basis {
  double b[4], db[4], ddb[4];
};

Basis basis(double u) {
  Basis B{};
  const double u2 = u * u, u3 = u2 * u, omu = 1.0 - u;
  B.b[0] = omu * omu * omu / 6.0;
  B.b[1] = (3.0 * u3 - 6.0 * u2 + 4.0) / 6.0;
  B.b[2] = (-3.0 * u3 + 3.0 * u2 + 3.0 * u + 1.0) / 6.0;
  B.b[3] = u3 / 6.0;
  B.db[0] = -0.5 * omu * omu;
  B.db[1] = 0.5 * (3.0 * u2 - 4.0 * u);
  B.db[2] = 0.5 * (-3.0 * u2 + 2.0 * u + 1.0);
  B.db[3] = 0.5 * u2;
  B.ddb[0] = omu;
  B.ddb[1] = 3.0 * u - 2.0;
  B.ddb[2] = -3.0 * u + 1.0;
  B.ddb[3] = u;
  return B;
}

// Segment index and local parameter for time t (s since t0).
void locate(double t, double dt, size_t n_ctrl, size_t& i, double& u) {
  const double s = t / dt;
  const double max_seg = static_cast<double>(n_ctrl - 4);
  double fl = std::floor(s);
  if (fl < 0.0) fl = 0.0;
  if (fl > max_seg) fl = max_seg;
  i = static_cast<size_t>(fl);
  u = std::clamp(s - fl, 0.0, 1.0);
}

}  // namespace

std::vector<GtSample> load_gt_file(const std::string& path) {
  std::vector<std::string> lines;
  const text::LinesRead read = text::read_lines(path, lines);
  if (!read.opened) throw std::runtime_error(path + ": cannot open ground-truth file");
  if (!read) throw std::runtime_error(path + ": read error");
  std::vector<GtSample> out;
  int csv = -1;  // decided by the first data line
  for (size_t k = 0; k < lines.size(); ++k) {
    const size_t line_no = k + 1;
    const std::string line = text::trim(lines[k]);
    if (line.empty() || line[0] == '#') continue;
    if (csv < 0) csv = line.find(',') != std::string::npos ? 1 : 0;
    const auto f = csv == 1 ? text::split(line, ',') : text::split_ws(line);
    if (f.size() < 8) {
      throw std::runtime_error(where(path, line_no) + ": expected 8 fields (" +
                               (csv ? "t_ns,px,py,pz,qw,qx,qy,qz" : "t x y z qx qy qz qw") + "), got " +
                               std::to_string(f.size()));
    }
    GtSample s;
    if (csv) {
      if (!text::parse_i64(f[0], s.t_ns))
        throw std::runtime_error(where(path, line_no) + ": bad timestamp '" + f[0] + "'");
    } else if (!parse_stamp_s(f[0], s.t_ns)) {
      throw std::runtime_error(where(path, line_no) + ": bad timestamp '" + f[0] + "'");
    }
    double v[7];
    for (int j = 0; j < 7; ++j) {
      if (!text::parse_finite_f64(f[1 + j], v[j])) {
        throw std::runtime_error(where(path, line_no) + ": field " + std::to_string(j + 2) +
                                 " is not a number: '" + f[1 + j] + "'");
      }
    }
    s.p_WB = {v[0], v[1], v[2]};
    s.q_WB = csv ? Eigen::Quaterniond(v[3], v[4], v[5], v[6]) : Eigen::Quaterniond(v[6], v[3], v[4], v[5]);
    const double n = s.q_WB.norm();
    if (std::abs(n - 1.0) > 0.05)
      throw std::runtime_error(where(path, line_no) + ": quaternion norm " + std::to_string(n) + " is not 1");
    s.q_WB.normalize();
    if (!out.empty() && s.t_ns <= out.back().t_ns)
      throw std::runtime_error(where(path, line_no) + ": time " + f[0] + " does not increase");
    out.push_back(s);
  }
  if (out.size() < 4) {
    throw std::runtime_error(path + ": needs at least 4 ground-truth samples, found " +
                             std::to_string(out.size()));
  }
  return out;
}

SplineTrajectory SplineTrajectory::fit(const std::vector<GtSample>& samples, const FitOptions& options) {
  if (samples.size() < 4) throw std::invalid_argument("spline fit needs at least 4 samples");
  for (size_t k = 1; k < samples.size(); ++k) {
    if (samples[k].t_ns <= samples[k - 1].t_ns)
      throw std::invalid_argument("spline fit: sample times must increase");
  }

  SplineTrajectory sp;
  sp.t0_ns_ = samples.front().t_ns;
  const size_t M = samples.size();
  std::vector<double> ts(M);
  for (size_t k = 0; k < M; ++k) ts[k] = 1e-9 * static_cast<double>(samples[k].t_ns - sp.t0_ns_);
  sp.duration_s_ = ts.back();
  sp.sample_times_s_ = ts;

  double dt = options.knot_spacing_s;
  if (dt <= 0.0) {
    std::vector<double> d(M - 1);
    for (size_t k = 0; k + 1 < M; ++k) d[k] = ts[k + 1] - ts[k];
    std::nth_element(d.begin(), d.begin() + static_cast<long>(d.size() / 2), d.end());
    dt = d[d.size() / 2];
  }
  sp.dt_ = dt;
  // Segments cover [0, duration]; control point j sits at time (j - 1) dt.
  const size_t N = static_cast<size_t>(std::ceil(sp.duration_s_ / dt - 1e-9)) + 3;
  const size_t n_ctrl = std::max<size_t>(N, 4);

  // Normal equations of the sample residuals plus a second-difference
  // penalty; a tiny one always, so that knots without samples (gaps, the
  // two spare end points) are still determined.
  std::vector<Eigen::Triplet<double>> trip;
  std::vector<size_t> seg(M);
  std::vector<Basis> bas(M);
  for (size_t k = 0; k < M; ++k) {
    double u;
    locate(ts[k], dt, n_ctrl, seg[k], u);
    bas[k] = basis(u);
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        trip.emplace_back(static_cast<int>(seg[k] + a), static_cast<int>(seg[k] + b),
                          bas[k].b[a] * bas[k].b[b]);
      }
    }
  }
  auto add_smoothing = [&](std::vector<Eigen::Triplet<double>>& t, double lambda) {
    const double c[3] = {1.0, -2.0, 1.0};
    for (size_t j = 0; j + 2 < n_ctrl; ++j) {
      for (int a = 0; a < 3; ++a) {
        for (int b = 0; b < 3; ++b)
          t.emplace_back(static_cast<int>(j + a), static_cast<int>(j + b), lambda * c[a] * c[b]);
      }
    }
  };
  const int n = static_cast<int>(n_ctrl);
  auto factor = [&](double lambda) {
    std::vector<Eigen::Triplet<double>> t = trip;
    add_smoothing(t, lambda);
    Eigen::SparseMatrix<double> A(n, n);
    A.setFromTriplets(t.begin(), t.end());
    auto solver = std::make_unique<Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>>();
    solver->compute(A);
    if (solver->info() != Eigen::Success)
      throw std::runtime_error("spline fit: normal equations are singular");
    return solver;
  };
  constexpr double kTinySmoothing = 1e-6;

  // Positions: one linear least-squares solve.
  {
    auto solver = factor(kTinySmoothing + std::max(0.0, options.position_smoothing));
    Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(n, 3);
    for (size_t k = 0; k < M; ++k) {
      for (int a = 0; a < 4; ++a)
        rhs.row(static_cast<long>(seg[k] + a)) += bas[k].b[a] * samples[k].p_WB.transpose();
    }
    const Eigen::MatrixXd c = solver->solve(rhs);
    sp.ctrl_p_.resize(n_ctrl);
    for (size_t j = 0; j < n_ctrl; ++j) sp.ctrl_p_[j] = c.row(static_cast<long>(j)).transpose();
  }

  // Rotations: start from the samples slerped at the control times, then
  // Gauss-Newton on right perturbations of the control rotations, with the
  // linear basis as the (approximate) Jacobian of the cumulative spline.
  {
    sp.ctrl_q_.resize(n_ctrl);
    size_t k = 0;
    for (size_t j = 0; j < n_ctrl; ++j) {
      const double tj = std::clamp((static_cast<double>(j) - 1.0) * dt, 0.0, sp.duration_s_);
      while (k + 2 < M && ts[k + 1] < tj) ++k;
      const double a = std::clamp((tj - ts[k]) / (ts[k + 1] - ts[k]), 0.0, 1.0);
      sp.ctrl_q_[j] = samples[k].q_WB.slerp(a, samples[k + 1].q_WB).normalized();
    }
    auto solver = factor(kTinySmoothing);
    for (int it = 0; it < std::max(0, options.rotation_iterations); ++it) {
      Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(n, 3);
      double max_r = 0.0;
      for (size_t m = 0; m < M; ++m) {
        const Eigen::Vector3d r = so3_log(sp.state(ts[m]).q_WB.conjugate() * samples[m].q_WB);
        max_r = std::max(max_r, r.norm());
        for (int a = 0; a < 4; ++a) rhs.row(static_cast<long>(seg[m] + a)) += bas[m].b[a] * r.transpose();
      }
      if (max_r < 1e-10) break;
      const Eigen::MatrixXd d = solver->solve(rhs);
      for (size_t j = 0; j < n_ctrl; ++j)
        sp.ctrl_q_[j] = (sp.ctrl_q_[j] * so3_exp(d.row(static_cast<long>(j)).transpose())).normalized();
    }
  }

  for (size_t k = 0; k < M; ++k) {
    const TrajectoryState s = sp.state(ts[k]);
    sp.max_pos_residual_m_ = std::max(sp.max_pos_residual_m_, (s.p_WB - samples[k].p_WB).norm());
    sp.max_rot_residual_rad_ =
        std::max(sp.max_rot_residual_rad_, so3_log(s.q_WB.conjugate() * samples[k].q_WB).norm());
  }
  sp.description_ = "spline of " + std::to_string(M) + " samples";
  return sp;
}

SplineTrajectory SplineTrajectory::from_file(const std::string& path, double start_s, double duration_s,
                                             const FitOptions& options) {
  const std::vector<GtSample> all = load_gt_file(path);
  const int64_t t_begin = all.front().t_ns + static_cast<int64_t>(std::llround(std::max(0.0, start_s) * 1e9));
  const int64_t t_end =
      duration_s > 0.0 ? t_begin + static_cast<int64_t>(std::llround(duration_s * 1e9)) : all.back().t_ns;
  std::vector<GtSample> cut;
  for (const GtSample& s : all)
    if (s.t_ns >= t_begin && s.t_ns <= t_end) cut.push_back(s);
  if (cut.size() < 4) {
    const double file_s = 1e-9 * static_cast<double>(all.back().t_ns - all.front().t_ns);
    throw std::invalid_argument(path + ": the span --start " + std::to_string(start_s) + " s --duration " +
                                std::to_string(duration_s) + " s holds " + std::to_string(cut.size()) +
                                " samples (need 4); the file covers " + std::to_string(file_s) + " s");
  }
  SplineTrajectory sp = fit(cut, options);
  sp.description_ = "spline of " + path + " (" + std::to_string(cut.size()) + " samples)";
  return sp;
}

TrajectoryState SplineTrajectory::state(double t) const {
  size_t i;
  double u;
  locate(t, dt_, ctrl_p_.size(), i, u);
  const Basis B = basis(u);
  TrajectoryState s;
  s.t_s = t;
  s.p_WB.setZero();
  s.v_WB.setZero();
  s.a_WB.setZero();
  for (int k = 0; k < 4; ++k) {
    s.p_WB += B.b[k] * ctrl_p_[i + k];
    s.v_WB += (B.db[k] / dt_) * ctrl_p_[i + k];
    s.a_WB += (B.ddb[k] / (dt_ * dt_)) * ctrl_p_[i + k];
  }
  // Cumulative basis: B~_j = sum_{k >= j} b_k.
  const double bc[4] = {1.0, B.b[1] + B.b[2] + B.b[3], B.b[2] + B.b[3], B.b[3]};
  const double dbc[4] = {0.0, (B.db[1] + B.db[2] + B.db[3]) / dt_, (B.db[2] + B.db[3]) / dt_, B.db[3] / dt_};
  Eigen::Quaterniond q = ctrl_q_[i];
  Eigen::Vector3d w = Eigen::Vector3d::Zero();
  for (int j = 1; j <= 3; ++j) {
    const Eigen::Vector3d d = so3_log(ctrl_q_[i + j - 1].conjugate() * ctrl_q_[i + j]);
    const Eigen::Quaterniond A = so3_exp(bc[j] * d);
    q = q * A;
    // Body rate recursion (Sommer et al. 2020): w_j = A_j^T w_{j-1} + dB~_j/dt d_j.
    w = A.conjugate() * w + dbc[j] * d;
  }
  s.q_WB = q.normalized();
  s.w_B = w;
  return s;
}

}  // namespace kestrel::tools

// Association, alignment and metrics. Formulas: docs/evaluation.md.
#include "kestrel/tools/trajectory_eval.hpp"

#include <Eigen/Geometry>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

namespace kestrel::tools {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kRadToDeg = 180.0 / M_PI;

// Rotation angle in [0, pi], robust near 0 and pi (acos is not).
double angle_rad(const Eigen::Quaterniond& q) { return 2.0 * std::atan2(q.vec().norm(), std::fabs(q.w())); }

Stats make_stats(std::vector<double> v) {
  Stats s;
  s.count = static_cast<int>(v.size());
  if (v.empty()) {
    s.rmse = s.mean = s.median = s.std = s.min = s.max = kNaN;
    return s;
  }
  double sum = 0, sum_sq = 0;
  for (double x : v) {
    sum += x;
    sum_sq += x * x;
  }
  const double n = static_cast<double>(v.size());
  s.mean = sum / n;
  s.rmse = std::sqrt(sum_sq / n);
  double var = 0;
  for (double x : v) var += (x - s.mean) * (x - s.mean);
  s.std = std::sqrt(var / n);
  std::sort(v.begin(), v.end());
  s.min = v.front();
  s.max = v.back();
  const size_t mid = v.size() / 2;
  s.median = v.size() % 2 == 1 ? v[mid] : 0.5 * (v[mid - 1] + v[mid]);
  return s;
}

// Relative motion error E = (T_gt_i^-1 T_gt_j)^-1 (T_est_i^-1 T_est_j).
void relative_error(const TimedPose& gi, const TimedPose& gj, const TimedPose& ei, const TimedPose& ej,
                    double* trans_m, double* rot_rad) {
  const Eigen::Quaterniond dq_gt = gi.q.conjugate() * gj.q;
  const Eigen::Vector3d dp_gt = gi.q.conjugate() * (gj.p - gi.p);
  const Eigen::Quaterniond dq_est = ei.q.conjugate() * ej.q;
  const Eigen::Vector3d dp_est = ei.q.conjugate() * (ej.p - ei.p);
  const Eigen::Quaterniond dq_err = dq_gt.conjugate() * dq_est;
  const Eigen::Vector3d dp_err = dq_gt.conjugate() * (dp_est - dp_gt);
  *trans_m = dp_err.norm();
  *rot_rad = angle_rad(dq_err);
}

std::string num(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", v);
  return buf;
}

bool sorted_strictly(const Trajectory& t) {
  for (size_t i = 1; i < t.size(); ++i)
    if (t[i].t_ns <= t[i - 1].t_ns) return false;
  return true;
}

// Callers building trajectories by hand may not sort them; evaluation needs it.
Trajectory sorted_unique(const Trajectory& t, const char* what, std::vector<std::string>* warnings) {
  Trajectory out = t;
  std::stable_sort(out.begin(), out.end(),
                   [](const TimedPose& a, const TimedPose& b) { return a.t_ns < b.t_ns; });
  const size_t before = out.size();
  out.erase(std::unique(out.begin(), out.end(),
                        [](const TimedPose& a, const TimedPose& b) { return a.t_ns == b.t_ns; }),
            out.end());
  warnings->push_back(std::string(what) + " trajectory was not sorted by time: sorted" +
                      (before != out.size() ? ", " + std::to_string(before - out.size()) +
                                                  " poses with repeated timestamps dropped (first kept)"
                                            : std::string()));
  return out;
}

}  // namespace

std::optional<Alignment> parse_alignment(const std::string& name) {
  if (name == "none") return Alignment::kNone;
  if (name == "se3") return Alignment::kSe3;
  if (name == "sim3") return Alignment::kSim3;
  if (name == "posyaw") return Alignment::kPosYaw;
  return std::nullopt;
}

const char* alignment_name(Alignment alignment) {
  switch (alignment) {
    case Alignment::kNone:
      return "none";
    case Alignment::kSe3:
      return "se3";
    case Alignment::kSim3:
      return "sim3";
    case Alignment::kPosYaw:
      return "posyaw";
  }
  return "?";
}

Sim3 align_positions(const std::vector<Eigen::Vector3d>& est, const std::vector<Eigen::Vector3d>& gt,
                     Alignment alignment) {
  if (est.size() != gt.size()) throw std::invalid_argument("align_positions: est and gt differ in length");
  const size_t n = est.size();
  Sim3 out;
  switch (alignment) {
    case Alignment::kNone:
      return out;
    case Alignment::kSe3:
    case Alignment::kSim3: {
      if (n < 3) {
        throw std::invalid_argument(std::string(alignment_name(alignment)) +
                                    " alignment needs >= 3 poses, got " + std::to_string(n));
      }
      Eigen::Matrix3Xd src(3, n), dst(3, n);
      for (size_t i = 0; i < n; ++i) {
        src.col(static_cast<Eigen::Index>(i)) = est[i];
        dst.col(static_cast<Eigen::Index>(i)) = gt[i];
      }
      const bool with_scale = alignment == Alignment::kSim3;
      if (with_scale) {
        const Eigen::Vector3d mu = src.rowwise().mean();
        if ((src.colwise() - mu).squaredNorm() / static_cast<double>(n) < 1e-18)
          throw std::invalid_argument("sim3 alignment: estimate positions do not move, scale undefined");
      }
      // Umeyama (1991), as implemented by Eigen: argmin sum |dst - (c R src + t)|^2.
      const Eigen::Matrix4d T = Eigen::umeyama(src, dst, with_scale);
      const Eigen::Matrix3d cR = T.topLeftCorner<3, 3>();
      out.scale = with_scale ? std::cbrt(cR.determinant()) : 1.0;
      out.R = cR / out.scale;
      out.t = T.topRightCorner<3, 1>();
      return out;
    }
    case Alignment::kPosYaw: {
      if (n < 2) throw std::invalid_argument("posyaw alignment needs >= 2 poses, got " + std::to_string(n));
      Eigen::Vector3d mu_e = Eigen::Vector3d::Zero(), mu_g = Eigen::Vector3d::Zero();
      for (size_t i = 0; i < n; ++i) {
        mu_e += est[i];
        mu_g += gt[i];
      }
      mu_e /= static_cast<double>(n);
      mu_g /= static_cast<double>(n);
      // Only yaw is free, so only the x-y part of the cross-covariance matters:
      // maximise sum g'^T Rz(yaw) e' = cos(yaw) * a + sin(yaw) * b.
      double a = 0, b = 0;
      for (size_t i = 0; i < n; ++i) {
        const Eigen::Vector3d e = est[i] - mu_e, g = gt[i] - mu_g;
        a += e.x() * g.x() + e.y() * g.y();
        b += e.x() * g.y() - e.y() * g.x();
      }
      const double yaw = std::atan2(b, a);
      out.R = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
      out.t = mu_g - out.R * mu_e;
      return out;
    }
  }
  return out;
}

std::optional<TimedPose> pose_at(const Trajectory& trajectory, int64_t t_ns, int64_t max_gap_ns,
                                 bool* interpolated) {
  if (interpolated != nullptr) *interpolated = false;
  const auto hi = std::lower_bound(trajectory.begin(), trajectory.end(), t_ns,
                                   [](const TimedPose& p, int64_t t) { return p.t_ns < t; });
  if (hi != trajectory.end() && hi->t_ns == t_ns) return *hi;
  const bool has_hi = hi != trajectory.end() && hi->t_ns - t_ns <= max_gap_ns;
  const bool has_lo = hi != trajectory.begin() && t_ns - std::prev(hi)->t_ns <= max_gap_ns;
  if (has_lo && has_hi) {
    const TimedPose& p0 = *std::prev(hi);
    const TimedPose& p1 = *hi;
    const double a = static_cast<double>(t_ns - p0.t_ns) / static_cast<double>(p1.t_ns - p0.t_ns);
    TimedPose out;
    out.t_ns = t_ns;
    out.p = (1.0 - a) * p0.p + a * p1.p;
    out.q = p0.q.slerp(a, p1.q).normalized();
    if (interpolated != nullptr) *interpolated = true;
    return out;
  }
  if (has_lo || has_hi) {
    TimedPose out = has_lo ? *std::prev(hi) : *hi;
    out.t_ns = t_ns;
    return out;
  }
  return std::nullopt;
}

Trajectory anchor_to_keyframes(const Trajectory& odometry, const std::vector<KeyframeAnchor>& keyframes,
                               double max_step_m, double max_step_rad) {
  if (keyframes.empty()) return odometry;
  auto iso = [](const TimedPose& p) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = p.q.normalized().toRotationMatrix();
    T.translation() = p.p;
    return T;
  };
  std::vector<Eigen::Isometry3d> C(keyframes.size());
  for (size_t k = 0; k < keyframes.size(); ++k) {
    const auto at = std::lower_bound(odometry.begin(), odometry.end(), keyframes[k].t_ns,
                                     [](const TimedPose& p, int64_t t) { return p.t_ns < t; });
    const bool own = at != odometry.end() && at->t_ns == keyframes[k].t_ns;
    C[k] = keyframes[k].T_MB * (own ? iso(*at) : keyframes[k].T_WB).inverse();
  }
  Trajectory out;
  out.reserve(odometry.size());
  for (const TimedPose& p : odometry) {
    const auto hi = std::upper_bound(keyframes.begin(), keyframes.end(), p.t_ns,
                                     [](int64_t t, const KeyframeAnchor& k) { return t < k.t_ns; });
    const size_t b = static_cast<size_t>(hi - keyframes.begin());
    const Eigen::Isometry3d T = iso(p);
    Eigen::Isometry3d Ct;
    if (b == 0) {
      Ct = C.front();
    } else if (b == keyframes.size()) {
      Ct = C.back();
    } else {
      // The two corrections differ by D = C_a^-1 C_b; seen at this body pose
      // that is E = T^-1 D T, a step of the body itself, whatever the
      // distance to W's origin (there a small yaw of D is a large translation).
      const size_t a = b - 1;
      const Eigen::Isometry3d E = T.inverse() * C[a].inverse() * C[b] * T;
      const Eigen::AngleAxisd aa(E.linear());
      if (E.translation().norm() > max_step_m || std::abs(aa.angle()) > max_step_rad) {
        Ct = C[a];
      } else {
        const double s = static_cast<double>(p.t_ns - keyframes[a].t_ns) /
                         static_cast<double>(keyframes[b].t_ns - keyframes[a].t_ns);
        Eigen::Isometry3d Es = Eigen::Isometry3d::Identity();
        Es.linear() = Eigen::AngleAxisd(s * aa.angle(), aa.axis()).toRotationMatrix();
        Es.translation() = s * E.translation();
        Ct = C[a] * T * Es * T.inverse();
      }
    }
    const Eigen::Isometry3d T_MB = Ct * T;
    TimedPose q;
    q.t_ns = p.t_ns;
    q.p = T_MB.translation();
    q.q = Eigen::Quaterniond(T_MB.linear()).normalized();
    out.push_back(q);
  }
  return out;
}

RpeStats relative_pose_error(const EvalResult& r, double delta_s, double max_gap_ms) {
  if (!(delta_s > 0) || !std::isfinite(delta_s)) throw std::invalid_argument("RPE delta must be > 0 s");
  RpeStats out;
  out.delta_s = delta_s;
  // Pair each pose with the first one at least delta later. It is accepted when
  // it lies within max(max_gap, median estimate period) of t_i + delta: close
  // enough for any regular estimator, but a pair across a hole (or past the end,
  // which would silently shorten delta) is not made.
  const auto delta_ns = static_cast<int64_t>(std::llround(delta_s * 1e9));
  const auto max_gap_ns = static_cast<int64_t>(std::llround(max_gap_ms * 1e6));
  const auto& E = r.est_aligned;
  int64_t median_dt_ns = 0;
  if (E.size() >= 2) {
    std::vector<int64_t> dts;
    dts.reserve(E.size() - 1);
    for (size_t i = 1; i < E.size(); ++i) dts.push_back(E[i].t_ns - E[i - 1].t_ns);
    std::nth_element(dts.begin(), dts.begin() + static_cast<std::ptrdiff_t>(dts.size() / 2), dts.end());
    median_dt_ns = dts[dts.size() / 2];
  }
  const int64_t pair_tol_ns = std::max(max_gap_ns, median_dt_ns);
  std::vector<double> rpe_t, rpe_r, rpe_t_per_s;
  for (size_t i = 0; i < E.size(); ++i) {
    const int64_t target = E[i].t_ns + delta_ns;
    const auto it = std::lower_bound(E.begin() + static_cast<std::ptrdiff_t>(i) + 1, E.end(), target,
                                     [](const TimedPose& p, int64_t t) { return p.t_ns < t; });
    if (it == E.end()) break;  // later starts reach further still
    if (it->t_ns - target > pair_tol_ns) continue;
    const size_t j = static_cast<size_t>(it - E.begin());
    double et = 0, er = 0;
    relative_error(r.gt_matched[i], r.gt_matched[j], E[i], E[j], &et, &er);
    rpe_t.push_back(et);
    rpe_r.push_back(er * kRadToDeg);
    rpe_t_per_s.push_back(et / (static_cast<double>(E[j].t_ns - E[i].t_ns) * 1e-9));
  }
  out.pairs = static_cast<int>(rpe_t.size());
  const Stats st = make_stats(rpe_t), sr = make_stats(rpe_r), sps = make_stats(rpe_t_per_s);
  out.trans_rmse_m = st.rmse;
  out.trans_mean_m = st.mean;
  out.trans_m_per_s = sps.rmse;
  out.rot_rmse_deg = sr.rmse;
  out.rot_mean_deg = sr.mean;
  return out;
}

EvalResult evaluate(const Trajectory& gt_in, const Trajectory& est_in, const EvalOptions& opt) {
  if (!(opt.max_gap_ms >= 0) || !std::isfinite(opt.max_gap_ms))
    throw std::invalid_argument("max_gap_ms must be a finite value >= 0");
  if (!(opt.rpe_delta_s > 0) || !std::isfinite(opt.rpe_delta_s))
    throw std::invalid_argument("rpe_delta_s must be > 0");
  for (double L : opt.segment_lengths_m)
    if (!(L > 0) || !std::isfinite(L)) throw std::invalid_argument("segment lengths must be > 0 m");

  EvalResult r;
  r.align = opt.align;
  r.rpe_delta_s = opt.rpe_delta_s;

  const Trajectory gt = sorted_strictly(gt_in) ? gt_in : sorted_unique(gt_in, "ground-truth", &r.warnings);
  const Trajectory est = sorted_strictly(est_in) ? est_in : sorted_unique(est_in, "estimate", &r.warnings);
  r.gt_poses = static_cast<int>(gt.size());
  r.est_poses = static_cast<int>(est.size());
  r.gt_duration_s = gt.size() >= 2 ? static_cast<double>(gt.back().t_ns - gt.front().t_ns) * 1e-9 : 0.0;

  // ---- association ----
  const auto max_gap_ns = static_cast<int64_t>(std::llround(opt.max_gap_ms * 1e6));
  std::vector<TimedPose> est_matched;
  int64_t first_unmatched_ns = 0;
  for (const TimedPose& e : est) {
    bool interp = false;
    auto g = pose_at(gt, e.t_ns, max_gap_ns, &interp);
    if (!g) {
      if (r.unmatched++ == 0) first_unmatched_ns = e.t_ns;
      continue;
    }
    r.gt_matched.push_back(*g);
    est_matched.push_back(e);
    if (interp) ++r.interpolated;
  }
  r.matched = static_cast<int>(est_matched.size());
  if (r.unmatched > 0) {
    r.warnings.push_back(std::to_string(r.unmatched) + " of " + std::to_string(r.est_poses) +
                         " estimate poses have no ground truth within " + num(opt.max_gap_ms) +
                         " ms (first at t_ns=" + std::to_string(first_unmatched_ns) + ")");
  }

  const int needed = opt.align == Alignment::kNone ? 1 : opt.align == Alignment::kPosYaw ? 2 : 3;
  if (r.matched < needed) {
    std::string msg = "only " + std::to_string(r.matched) + " of " + std::to_string(r.est_poses) +
                      " estimate poses associate with ground truth within " + num(opt.max_gap_ms) + " ms; " +
                      alignment_name(opt.align) + " needs " + std::to_string(needed);
    if (!gt.empty() && !est.empty()) {
      msg += " (ground truth spans t_ns " + std::to_string(gt.front().t_ns) + ".." +
             std::to_string(gt.back().t_ns) + ", estimate " + std::to_string(est.front().t_ns) + ".." +
             std::to_string(est.back().t_ns) + ": different clocks?)";
    }
    throw std::runtime_error(msg);
  }

  // ---- alignment ----
  std::vector<Eigen::Vector3d> pe, pg;
  pe.reserve(est_matched.size());
  pg.reserve(est_matched.size());
  for (size_t i = 0; i < est_matched.size(); ++i) {
    pe.push_back(est_matched[i].p);
    pg.push_back(r.gt_matched[i].p);
  }
  if (opt.align == Alignment::kSe3 || opt.align == Alignment::kSim3) {
    // Positions on a line leave the rotation about that line to chance.
    Eigen::Matrix3Xd c(3, pe.size());
    Eigen::Vector3d mu = Eigen::Vector3d::Zero();
    for (const auto& p : pe) mu += p;
    mu /= static_cast<double>(pe.size());
    for (size_t i = 0; i < pe.size(); ++i) c.col(static_cast<Eigen::Index>(i)) = pe[i] - mu;
    const Eigen::Vector3d sv = Eigen::JacobiSVD<Eigen::Matrix3d>(c * c.transpose()).singularValues();
    if (sv(1) <= 1e-9 * std::max(sv(0), 1e-30)) {
      r.warnings.push_back(
          "estimate positions are (nearly) collinear: the alignment rotation about that line is "
          "undetermined; prefer --align posyaw or none");
    }
  }
  r.T_align = align_positions(pe, pg, opt.align);
  const Eigen::Quaterniond q_align(r.T_align.R);
  r.est_aligned.resize(est_matched.size());
  for (size_t i = 0; i < est_matched.size(); ++i) {
    TimedPose& a = r.est_aligned[i];
    a.t_ns = est_matched[i].t_ns;
    a.p = r.T_align.scale * (r.T_align.R * est_matched[i].p) + r.T_align.t;
    a.q = (q_align * est_matched[i].q).normalized();
  }

  // ---- ATE ----
  r.pos_err_m.resize(r.est_aligned.size());
  r.rot_err_deg.resize(r.est_aligned.size());
  for (size_t i = 0; i < r.est_aligned.size(); ++i) {
    r.pos_err_m[i] = (r.est_aligned[i].p - r.gt_matched[i].p).norm();
    r.rot_err_deg[i] = angle_rad(r.gt_matched[i].q.conjugate() * r.est_aligned[i].q) * kRadToDeg;
  }
  r.ate_m = make_stats(r.pos_err_m);
  r.ate_rot_deg = make_stats(r.rot_err_deg);

  // ---- rotation gain (alignment-free: relative to the first pose) ----
  {
    Eigen::Vector3d sum_eg = Eigen::Vector3d::Zero(), sum_gg = Eigen::Vector3d::Zero();
    Eigen::Vector3d g_max = Eigen::Vector3d::Zero();
    const Eigen::Quaterniond qe0 = est_matched.front().q.normalized(),
                             qg0 = r.gt_matched.front().q.normalized();
    for (size_t i = 0; i < est_matched.size(); ++i) {
      const Eigen::AngleAxisd ae(qe0.conjugate() * est_matched[i].q.normalized());
      const Eigen::AngleAxisd ag(qg0.conjugate() * r.gt_matched[i].q.normalized());
      const Eigen::Vector3d ve = ae.angle() * ae.axis(), vg = ag.angle() * ag.axis();
      sum_eg += ve.cwiseProduct(vg);
      sum_gg += vg.cwiseProduct(vg);
      g_max = g_max.cwiseMax(vg.cwiseAbs());
    }
    for (int a = 0; a < 3; ++a)
      if (g_max(a) >= 2.0 / kRadToDeg) r.rot_gain(a) = sum_eg(a) / sum_gg(a);
  }

  // ---- coverage and path length ----
  const auto coverage_gap_ns = static_cast<int64_t>(std::llround(opt.coverage_gap_s * 1e9));
  int64_t covered_ns = 0;
  for (size_t i = 1; i < r.est_aligned.size(); ++i) {
    const int64_t dt = r.est_aligned[i].t_ns - r.est_aligned[i - 1].t_ns;
    if (dt <= coverage_gap_ns) covered_ns += dt;
    r.gt_length_m += (r.gt_matched[i].p - r.gt_matched[i - 1].p).norm();
  }
  const int64_t gt_span_ns = gt.size() >= 2 ? gt.back().t_ns - gt.front().t_ns : 0;
  r.coverage = gt_span_ns > 0
                   ? std::min(1.0, static_cast<double>(covered_ns) / static_cast<double>(gt_span_ns))
                   : (r.matched > 0 ? 1.0 : 0.0);

  // ---- RPE over a fixed time step ----
  const RpeStats rpe = relative_pose_error(r, opt.rpe_delta_s, opt.max_gap_ms);
  r.rpe_pairs = rpe.pairs;
  r.rpe_trans_rmse_m = rpe.trans_rmse_m;
  r.rpe_trans_mean_m = rpe.trans_mean_m;
  r.rpe_trans_m_per_s = rpe.trans_m_per_s;
  r.rpe_rot_rmse_deg = rpe.rot_rmse_deg;
  r.rpe_rot_mean_deg = rpe.rot_mean_deg;
  if (r.rpe_pairs == 0) {
    r.warnings.push_back("no RPE pairs: the associated estimate spans less than rpe_delta_s = " +
                         num(opt.rpe_delta_s) + " s or has no poses that far apart");
  }

  const auto& E = r.est_aligned;
  // ---- RPE over travelled distance (KITTI odometry style) ----
  std::vector<double> dist(E.size(), 0.0);
  for (size_t i = 1; i < E.size(); ++i)
    dist[i] = dist[i - 1] + (r.gt_matched[i].p - r.gt_matched[i - 1].p).norm();
  const double dist_eps = 1e-9 * (1.0 + (dist.empty() ? 0.0 : dist.back()));
  for (double L : opt.segment_lengths_m) {
    SegmentError seg;
    seg.length_m = L;
    double sum_t = 0, sum_r = 0;
    for (size_t i = 0; i < E.size(); ++i) {
      // The epsilon keeps summation round-off from pushing the end one sample further.
      const auto it =
          std::lower_bound(dist.begin() + static_cast<std::ptrdiff_t>(i), dist.end(), dist[i] + L - dist_eps);
      if (it == dist.end()) break;  // later starts are shorter still
      const size_t j = static_cast<size_t>(it - dist.begin());
      double et = 0, er = 0;
      relative_error(r.gt_matched[i], r.gt_matched[j], E[i], E[j], &et, &er);
      sum_t += et / L;
      sum_r += er * kRadToDeg / L;
      ++seg.count;
    }
    seg.trans_pct = seg.count > 0 ? 100.0 * sum_t / seg.count : kNaN;
    seg.rot_deg_per_m = seg.count > 0 ? sum_r / seg.count : kNaN;
    r.segments.push_back(seg);
  }
  return r;
}

}  // namespace kestrel::tools

// Trial runner shared by the LONSC summary test (unit) and bench_lonsc:
// runs one method on many simulated frames and reports medians.
#pragma once

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "kestrel/core/lonsc.hpp"
#include "lonsc_sim.hpp"

namespace kestrel::test {

struct MethodOutput {
  bool ok = false;
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
  const uint8_t* mask = nullptr;  // per correspondence, or null with mask_vec
  std::vector<uint8_t> mask_vec;  // for methods that do not own a mask (OpenCV)
};

struct TrialMetrics {
  bool ok = false;
  double precision = 0, recall = 0;
  double t_err_cm = std::numeric_limits<double>::infinity();
  double r_err_deg = std::numeric_limits<double>::infinity();
  double time_us = 0;
};

inline TrialMetrics score(const SimFrame& f, const MethodOutput& o, double time_us) {
  TrialMetrics m;
  m.time_us = time_us;
  m.ok = o.ok;
  if (!o.ok) return m;
  const uint8_t* mask = o.mask ? o.mask : o.mask_vec.data();
  std::size_t tp = 0, k = 0;
  for (std::size_t i = 0; i < f.c.size(); ++i) {
    k += mask[i] ? 1 : 0;
    tp += (mask[i] && f.is_inlier[i]) ? 1 : 0;
  }
  m.precision = k ? double(tp) / double(k) : 0.0;
  m.recall = double(tp) / double(std::max<std::size_t>(f.num_inliers(), 1));
  m.t_err_cm = 100.0 * (o.t - f.t_true).norm();
  m.r_err_deg = rotation_error_deg(o.R, f.R_true);
  return m;
}

struct Summary {
  std::string name;
  double precision = 0, recall = 0, t_err_cm = 0, t_err_p90_cm = 0, r_err_deg = 0, time_us = 0;
  double bad_frac = 0;  // failed, or translation error above bad_t_cm
  std::size_t trials = 0;
};

inline double quantile(std::vector<double> v, double q) {
  if (v.empty()) return std::numeric_limits<double>::quiet_NaN();
  const std::size_t k = std::min(v.size() - 1, static_cast<std::size_t>(q * double(v.size() - 1) + 0.5));
  std::nth_element(v.begin(), v.begin() + static_cast<long>(k), v.end());
  return v[k];
}

inline Summary summarize(const std::string& name, const std::vector<TrialMetrics>& ms,
                         double bad_t_cm = 2.0) {
  Summary s;
  s.name = name;
  s.trials = ms.size();
  std::vector<double> p, r, t, re, tm;
  std::size_t bad = 0;
  for (const auto& m : ms) {
    p.push_back(m.precision);
    r.push_back(m.recall);
    t.push_back(m.t_err_cm);
    re.push_back(m.r_err_deg);
    tm.push_back(m.time_us);
    bad += (!m.ok || !(m.t_err_cm <= bad_t_cm)) ? 1 : 0;
  }
  s.precision = quantile(p, 0.5);
  s.recall = quantile(r, 0.5);
  s.t_err_cm = quantile(t, 0.5);
  s.t_err_p90_cm = quantile(t, 0.9);
  s.r_err_deg = quantile(re, 0.5);
  s.time_us = quantile(tm, 0.5);
  s.bad_frac = ms.empty() ? 0.0 : double(bad) / double(ms.size());
  return s;
}

using Method = std::function<MethodOutput(const SimFrame&)>;

// Runs `method` on trials frames (seeds base_seed + k); times the call only.
inline std::vector<TrialMetrics> run_trials(const SimConfig& cfg, const Method& method, int trials,
                                            uint64_t base_seed) {
  std::vector<TrialMetrics> out;
  out.reserve(static_cast<std::size_t>(trials));
  for (int k = 0; k < trials; ++k) {
    const SimFrame f = simulate(cfg, base_seed + static_cast<uint64_t>(k));
    const auto t0 = std::chrono::steady_clock::now();
    MethodOutput o = method(f);
    const auto t1 = std::chrono::steady_clock::now();
    out.push_back(score(f, o, std::chrono::duration<double, std::micro>(t1 - t0).count()));
  }
  return out;
}

// --- the Kestrel methods ----------------------------------------------------

struct LonscMethod {
  core::LonscEstimator est;
  core::CorrespondenceOrderer orderer;
  std::vector<uint32_t> order;
  core::CorrespondenceOrder mode;
  bool refine;
  core::PoseRefineOptions refine_opt;
  uint64_t shuffle_seed = 1;
  core::MotionEstimate last;
  LonscMethod(core::CorrespondenceOrder m, bool gn, const core::LonscOptions& opt = {})
      : est(1024, opt), orderer(1024), order(1024), mode(m), refine(gn) {}
  MethodOutput operator()(const SimFrame& f) {
    MethodOutput o;
    const core::PinholeK K = kinect_k();
    orderer.order(mode, f.c.data(), f.c.size(), order.data(), 640, 480, ++shuffle_seed);
    const auto r = est.estimate(f.R_imu, K, f.c.data(), f.c.size(), order.data());
    last = r;
    o.ok = r.ok();
    o.R = f.R_imu;
    o.t = r.t;
    o.mask = est.inlier_mask();
    if (o.ok && refine) {
      auto rr = r;
      est.refine_pose(&o.R, &o.t, K, f.c.data(), f.c.size(), &rr, est.options().consistency, refine_opt,
                      &f.R_imu);
    }
    return o;
  }
};

struct RansacMethod {
  core::TwoPointRansac est;
  bool refine;
  core::PoseRefineOptions refine_opt;
  explicit RansacMethod(bool gn, const core::RansacOptions& opt = {}) : est(1024, opt), refine(gn) {}
  MethodOutput operator()(const SimFrame& f) {
    MethodOutput o;
    const core::PinholeK K = kinect_k();
    const auto r = est.estimate(f.R_imu, K, f.c.data(), f.c.size());
    o.ok = r.ok();
    o.R = f.R_imu;
    o.t = r.t;
    o.mask = est.inlier_mask();
    if (o.ok && refine) {
      auto rr = r;
      est.refine_pose(&o.R, &o.t, K, f.c.data(), f.c.size(), &rr, est.options().consistency, refine_opt,
                      &f.R_imu);
    }
    return o;
  }
};

inline void print_header(std::FILE* out) {
  std::fprintf(out, "| %-34s | prec | recall | t err cm (med / p90) | rot err deg | bad %% | time us |\n",
               "method");
  std::fprintf(out, "|%s|------|--------|----------------------|-------------|-------|---------|\n",
               std::string(36, '-').c_str());
}

inline void print_row(std::FILE* out, const Summary& s) {
  std::fprintf(out, "| %-34s | %.3f | %.3f  | %8.2f / %-9.2f | %11.3f | %5.1f | %7.1f |\n", s.name.c_str(),
               s.precision, s.recall, s.t_err_cm, s.t_err_p90_cm, s.r_err_deg, 100.0 * s.bad_frac, s.time_us);
}

}  // namespace kestrel::test

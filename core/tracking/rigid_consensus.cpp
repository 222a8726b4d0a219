#include "kestrel/core/rigid_consensus.hpp"

#include <Eigen/SVD>
#include <algorithm>
#include <cmath>

namespace kestrel::core {

const char* to_string(RigidMethod m) { return m == RigidMethod::kRansac ? "ransac" : "lonsc"; }

namespace {

// Running sums of a set of pairs, enough for the rigid fit: adding a pair
// and re-fitting costs one 3x3 SVD, so a run re-fits as it grows.
struct Sums {
  int n = 0;
  Eigen::Vector3d sp = Eigen::Vector3d::Zero(), sq = Eigen::Vector3d::Zero();
  Eigen::Matrix3d spq = Eigen::Matrix3d::Zero();
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = Eigen::Vector3d::Constant(-1e300);

  void add(const Eigen::Vector3d& p, const Eigen::Vector3d& q) {
    ++n;
    sp += p;
    sq += q;
    spq.noalias() += p * q.transpose();
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  // q = R p + t; false when degenerate (fewer than 3, too small, collinear).
  bool solve(double min_spread_m, Eigen::Matrix3d* R, Eigen::Vector3d* t) const {
    if (n < 3 || (hi - lo).maxCoeff() < min_spread_m) return false;
    const Eigen::Vector3d mp = sp / n, mq = sq / n;
    const Eigen::Matrix3d H = spq - n * mp * mq.transpose();
    const Eigen::JacobiSVD<Eigen::Matrix3d> svd(H, Eigen::ComputeFullU | Eigen::ComputeFullV);
    const Eigen::Vector3d& s = svd.singularValues();
    // Collinear points leave the rotation about their line free.
    if (!(s(1) > 1e-9 * std::max(1.0, s(0))) || !(s(1) > 1e-8)) return false;
    Eigen::Matrix3d D = Eigen::Matrix3d::Identity();
    D(2, 2) = (svd.matrixV() * svd.matrixU().transpose()).determinant() < 0 ? -1.0 : 1.0;
    *R = svd.matrixV() * D * svd.matrixU().transpose();
    *t = mq - *R * mp;
    return R->allFinite() && t->allFinite();
  }
};

}  // namespace

bool fit_rigid(const Eigen::Vector3d* p, const Eigen::Vector3d* q, const uint32_t* idx, std::size_t n,
               Eigen::Matrix3d* R, Eigen::Vector3d* t) {
  Sums s;
  for (std::size_t k = 0; k < n; ++k) {
    const std::size_t i = idx ? idx[k] : k;
    s.add(p[i], q[i]);
  }
  return s.solve(0.0, R, t);
}

RigidConsensus::RigidConsensus(std::size_t capacity, const RigidOptions& opt)
    : capacity_(capacity), opt_(opt), usable3d_(new uint32_t[capacity]), inliers_(new uint32_t[capacity]) {}

RigidConsensus::~RigidConsensus() = default;

bool RigidConsensus::consistent(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const PinholeK& K,
                                std::size_t i) const {
  ++checks_;
  const Eigen::Vector3d Rp = R * c_[i].p_prev;
  if (!opt_.consistency.consistent(Rp, t, K, c_[i])) return false;
  if (!has_q_[i]) return true;
  const double z = q_[i].z();
  return (Rp + t - q_[i]).norm() <= opt_.depth_tol_rel * z + opt_.depth_tol_m;
}

std::size_t RigidConsensus::consensus(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const PinholeK& K,
                                      std::size_t n, bool collect, double* rms_px) {
  std::size_t k = 0;
  double se = 0;
  for (std::size_t i = 0; i < n; ++i) {
    if (!correspondence_usable(c_[i]) || !consistent(R, t, K, i)) continue;
    if (collect) inliers_[k] = static_cast<uint32_t>(i);
    ++k;
    if (rms_px) {
      double e2 = 0;
      opt_.consistency.consistent(Eigen::Vector3d(R * c_[i].p_prev), t, K, c_[i], &e2);
      se += e2;
    }
  }
  if (rms_px) *rms_px = k > 0 ? std::sqrt(se / static_cast<double>(k)) : 0.0;
  return k;
}

void RigidConsensus::walk_lonsc(const PinholeK& K, std::size_t n, const uint32_t* order, RigidEstimate* out) {
  struct Run {
    int length = 0;
    Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
    Eigen::Vector3d t = Eigen::Vector3d::Zero();
  };
  constexpr int kMaxCandidates = 8;
  Run best[kMaxCandidates];
  const int n_cand = std::clamp(opt_.candidate_runs, 1, kMaxCandidates);
  auto offer = [&](const Run& r) {
    if (r.length < opt_.min_run_length) return;
    for (int k = 0; k < n_cand; ++k) {
      if (r.length > best[k].length) {
        for (int j = n_cand - 1; j > k; --j) best[j] = best[j - 1];
        best[k] = r;
        return;
      }
    }
  };
  // The walk over the 3D-3D pairs; the others cannot seed or grow a model.
  std::size_t m = 0;
  for (std::size_t k = 0; k < n; ++k) {
    const uint32_t i = order ? order[k] : static_cast<uint32_t>(k);
    if (i < n && has_q_[i] && correspondence_usable(c_[i])) usable3d_[m++] = i;
  }
  Sums sums;
  Run run;
  bool model = false;
  std::size_t seed_begin = 0;
  for (std::size_t k = 0; k < m; ++k) {
    const uint32_t i = usable3d_[k];
    if (model) {
      if (consistent(run.R, run.t, K, i)) {
        sums.add(c_[i].p_prev, q_[i]);
        ++run.length;
        ++out->model_estimates;
        Eigen::Matrix3d R;
        Eigen::Vector3d t;
        if (sums.solve(opt_.min_sample_spread_m, &R, &t)) run.R = R, run.t = t;
        continue;
      }
      // The run ends here; this pair starts the next seed.
      offer(run);
      out->longest_run = std::max(out->longest_run, run.length);
      model = false;
      seed_begin = k;
    }
    // Seeding: the last three pairs, which must agree with their own fit.
    if (k + 1 < seed_begin + 3) continue;
    sums = Sums{};
    for (std::size_t j = k - 2; j <= k; ++j) sums.add(c_[usable3d_[j]].p_prev, q_[usable3d_[j]]);
    ++out->model_estimates;
    Eigen::Matrix3d R;
    Eigen::Vector3d t;
    bool ok = sums.solve(opt_.min_sample_spread_m, &R, &t);
    for (std::size_t j = k - 2; j <= k && ok; ++j) ok = consistent(R, t, K, usable3d_[j]);
    if (!ok) continue;  // slide: the next pair makes a new triple with the last two
    model = true;
    run.length = 3;
    run.R = R;
    run.t = t;
  }
  if (model) {
    offer(run);
    out->longest_run = std::max(out->longest_run, run.length);
  }
  // The longest runs propose; the largest consensus wins (stop once one has a majority).
  std::size_t best_count = 0;
  for (int k = 0; k < n_cand && best[k].length > 0; ++k) {
    ++out->hypotheses;
    const std::size_t cnt = consensus(best[k].R, best[k].t, K, n, false, nullptr);
    if (cnt > best_count) {
      best_count = cnt;
      out->R = best[k].R;
      out->t = best[k].t;
    }
    if (2 * cnt > n) break;
  }
  out->status = best_count > 0 ? MotionStatus::kOk : MotionStatus::kNoConsistentRun;
}

void RigidConsensus::run_ransac(const PinholeK& K, std::size_t n, RigidEstimate* out) {
  std::size_t m = 0;
  for (std::size_t i = 0; i < n; ++i)
    if (has_q_[i] && correspondence_usable(c_[i])) usable3d_[m++] = static_cast<uint32_t>(i);
  if (m < 3) {
    out->status = MotionStatus::kTooFewCorrespondences;
    return;
  }
  rng_ = opt_.seed;
  auto next = [this]() {  // splitmix64
    uint64_t z = (rng_ += 0x9e3779b97f4a7c15ULL);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
    return z ^ (z >> 31);
  };
  std::size_t best_count = 0;
  double needed = opt_.max_iterations;
  for (int it = 0; it < opt_.max_iterations && it < needed; ++it) {
    const uint32_t a = usable3d_[next() % m], b = usable3d_[next() % m], c = usable3d_[next() % m];
    if (a == b || b == c || a == c) continue;
    Sums s;
    s.add(c_[a].p_prev, q_[a]);
    s.add(c_[b].p_prev, q_[b]);
    s.add(c_[c].p_prev, q_[c]);
    ++out->model_estimates;
    Eigen::Matrix3d R;
    Eigen::Vector3d t;
    if (!s.solve(opt_.min_sample_spread_m, &R, &t)) continue;
    ++out->hypotheses;
    const std::size_t cnt = consensus(R, t, K, n, false, nullptr);
    if (cnt > best_count) {
      best_count = cnt;
      out->R = R;
      out->t = t;
      // Adaptive stop: the chance that a triple is all inliers, w^3.
      const double w = static_cast<double>(cnt) / static_cast<double>(n);
      const double p_good = std::max(1e-12, w * w * w);
      needed = p_good >= 1.0 ? 1.0 : std::log(1.0 - opt_.confidence) / std::log(1.0 - p_good);
    }
  }
  out->status = best_count > 0 ? MotionStatus::kOk : MotionStatus::kNoConsistentRun;
}

RigidEstimate RigidConsensus::estimate(RigidMethod method, const PinholeK& K, const Correspondence2D3D* c,
                                       const Eigen::Vector3d* q_cur, const uint8_t* has_q, std::size_t n_in,
                                       const uint32_t* order) {
  RigidEstimate out;
  checks_ = 0;
  const std::size_t n = std::min(n_in, capacity_);
  c_ = c;
  q_ = q_cur;
  has_q_ = has_q;
  for (std::size_t i = 0; i < n; ++i) out.num_3d += has_q[i] ? 1 : 0;
  if (out.num_3d < 3) {
    out.status = MotionStatus::kTooFewCorrespondences;
    return out;
  }
  if (method == RigidMethod::kRansac) {
    run_ransac(K, n, &out);
  } else {
    walk_lonsc(K, n, order, &out);
  }
  if (!out.ok()) {
    out.consistency_checks = checks_;
    return out;
  }
  // Re-fit on the consensus of the 3D-3D inliers, then take the final set.
  Sums s;
  out.num_inliers = consensus(out.R, out.t, K, n, true, nullptr);
  for (std::size_t k = 0; k < out.num_inliers; ++k) {
    const uint32_t i = inliers_[k];
    if (has_q_[i]) s.add(c_[i].p_prev, q_[i]);
  }
  ++out.model_estimates;
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
  if (s.solve(opt_.min_sample_spread_m, &R, &t)) {
    const std::size_t cnt = consensus(R, t, K, n, false, nullptr);
    if (cnt >= out.num_inliers) out.R = R, out.t = t;
  }
  out.num_inliers = consensus(out.R, out.t, K, n, true, &out.inlier_rms_px);
  if (out.num_inliers < opt_.min_inliers) out.status = MotionStatus::kTooFewInliers;
  out.consistency_checks = checks_;
  return out;
}

}  // namespace kestrel::core

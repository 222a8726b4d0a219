#include "kestrel/core/lonsc.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <ostream>

namespace kestrel::core {

LonscOptions LonscOptions::paper() {
  LonscOptions o;
  o.verify_seed_pair = false;
  o.grow_model = false;
  o.candidate_runs = 1;
  o.weighted_least_squares = false;
  o.refine_passes = 0;
  o.min_run_length = 2;
  return o;
}

namespace {

uint64_t splitmix64(uint64_t* s) {
  uint64_t z = (*s += 0x9E3779B97F4A7C15ULL);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31);
}

// Monotone map float -> uint32 (so integer order == float order); NaN last.
uint32_t float_order_key(float f) {
  if (std::isnan(f)) return 0xFFFFFFFFu;
  uint32_t b;
  std::memcpy(&b, &f, sizeof b);
  return (b & 0x80000000u) ? ~b : (b | 0x80000000u);
}

// Distance along a Hilbert curve filling an n x n grid (n a power of two).
uint32_t hilbert_d(uint32_t n, uint32_t x, uint32_t y) {
  uint32_t d = 0;
  for (uint32_t s = n / 2; s > 0; s /= 2) {
    const uint32_t rx = (x & s) > 0;
    const uint32_t ry = (y & s) > 0;
    d += s * s * ((3 * rx) ^ ry);
    if (ry == 0) {
      if (rx == 1) {
        x = n - 1 - x;
        y = n - 1 - y;
      }
      std::swap(x, y);
    }
  }
  return d;
}

}  // namespace

const char* to_string(CorrespondenceOrder o) {
  switch (o) {
    case CorrespondenceOrder::kAsGiven:
      return "as_given";
    case CorrespondenceOrder::kByMatchCost:
      return "by_match_cost";
    case CorrespondenceOrder::kHilbert:
      return "hilbert";
    case CorrespondenceOrder::kShuffled:
      return "shuffled";
  }
  return "unknown";
}

CorrespondenceOrderer::CorrespondenceOrderer(std::size_t capacity)
    : capacity_(capacity),
      keys_(new uint64_t[capacity > 0 ? capacity : 1]),
      counts_(new uint32_t[kCountingSortRange + 1]) {}
CorrespondenceOrderer::~CorrespondenceOrderer() = default;

std::size_t CorrespondenceOrderer::order(CorrespondenceOrder mode, const Correspondence2D3D* c, std::size_t n,
                                         uint32_t* order_out, double image_w, double image_h,
                                         uint64_t seed) const {
  const std::size_t m = std::min(n, capacity_);
  for (std::size_t i = 0; i < m; ++i) order_out[i] = static_cast<uint32_t>(i);
  switch (mode) {
    case CorrespondenceOrder::kAsGiven:
      return m;
    case CorrespondenceOrder::kShuffled: {
      uint64_t s = seed;
      for (std::size_t i = m; i > 1; --i) std::swap(order_out[i - 1], order_out[splitmix64(&s) % i]);
      return m;
    }
    case CorrespondenceOrder::kByMatchCost: {
      // Hamming distances are small integers: a counting sort is O(n) and
      // stable (ties stay in index order), ~4x faster than sorting 300 keys.
      bool small_ints = true;
      for (std::size_t i = 0; i < m && small_ints; ++i) {
        const float f = c[i].match_cost;
        small_ints = f >= 0.0f && f < float(kCountingSortRange) && f == std::floor(f);
      }
      if (small_ints) {
        std::fill(counts_.get(), counts_.get() + kCountingSortRange + 1, 0u);
        for (std::size_t i = 0; i < m; ++i) ++counts_[static_cast<uint32_t>(c[i].match_cost) + 1];
        for (uint32_t b = 1; b <= kCountingSortRange; ++b) counts_[b] += counts_[b - 1];
        for (std::size_t i = 0; i < m; ++i)
          order_out[counts_[static_cast<uint32_t>(c[i].match_cost)]++] = static_cast<uint32_t>(i);
        return m;
      }
      for (std::size_t i = 0; i < m; ++i) keys_[i] = (uint64_t(float_order_key(c[i].match_cost)) << 32) | i;
      break;
    }
    case CorrespondenceOrder::kHilbert: {
      constexpr uint32_t kGrid = 1024;
      const double cell = std::max(std::max(image_w, image_h), 1.0) / kGrid;
      for (std::size_t i = 0; i < m; ++i) {
        auto q = [&](double v) {
          const double g = std::isfinite(v) ? v / cell : 0.0;
          return static_cast<uint32_t>(std::clamp(g, 0.0, double(kGrid - 1)));
        };
        keys_[i] = (uint64_t(hilbert_d(kGrid, q(c[i].u_cur.x()), q(c[i].u_cur.y()))) << 32) | i;
      }
      break;
    }
  }
  // Index in the low bits: unique keys, deterministic ties, and std::sort
  // (introsort) never allocates.
  std::sort(keys_.get(), keys_.get() + m);
  for (std::size_t i = 0; i < m; ++i) order_out[i] = static_cast<uint32_t>(keys_[i] & 0xFFFFFFFFu);
  return m;
}

// ---------------------------------------------------------------------------

MotionWorkspace::MotionWorkspace(std::size_t capacity)
    : capacity_(capacity),
      Rp_(new Eigen::Vector3d[capacity > 0 ? capacity : 1]),
      usable_(new uint8_t[capacity > 0 ? capacity : 1]),
      mask_(new uint8_t[capacity > 0 ? capacity : 1]),
      inliers_(new uint32_t[capacity > 0 ? capacity : 1]),
      run_(new uint32_t[capacity > 0 ? capacity : 1]) {}
MotionWorkspace::~MotionWorkspace() = default;

void MotionWorkspace::precompute(const Eigen::Matrix3d& R, const Correspondence2D3D* c, std::size_t n) {
  // R is fixed for the whole call (it comes from the IMU): rotate every point
  // once so that each consistency test is a vector add and a projection.
  for (std::size_t i = 0; i < n; ++i) {
    usable_[i] = correspondence_usable(c[i]) ? 1 : 0;
    Rp_[i] = R * c[i].p_prev;
    mask_[i] = 0;
  }
}

bool MotionWorkspace::solve_pair(std::size_t i, std::size_t j, const PinholeK& K, const Correspondence2D3D* c,
                                 double min_sep_px, Eigen::Vector3d* t) const {
  if (!usable_[i] || !usable_[j]) return false;
  // Two rows of eq. 3 per point differ only in the t_z column, by the pixel
  // offset: coincident pixels leave t_z unobservable (rank 2).
  if ((c[i].u_cur - c[j].u_cur).squaredNorm() < min_sep_px * min_sep_px) return false;
  TranslationNormalEquations ne;
  ne.add(Rp_[i], c[i].u_cur, K);
  ne.add(Rp_[j], c[j].u_cur, K);
  return ne.solve(t);
}

MotionStatus MotionWorkspace::solve_on(const uint32_t* idx, std::size_t k, const PinholeK& K,
                                       const Correspondence2D3D* c, bool weighted,
                                       const Eigen::Vector3d* t_ref, Eigen::Vector3d* t) const {
  Eigen::Vector3d t0;
  if (weighted && t_ref) {
    t0 = *t_ref;  // depth weights from the caller's estimate: one pass instead of two
  } else {
    TranslationNormalEquations ne;
    for (std::size_t q = 0; q < k; ++q) {
      const uint32_t i = idx[q];
      if (usable_[i]) ne.add(Rp_[i], c[i].u_cur, K);
    }
    if (ne.rows < 2) return MotionStatus::kTooFewCorrespondences;
    if (!ne.solve(&t0)) return MotionStatus::kDegenerate;
    if (!weighted) {
      *t = t0;
      return MotionStatus::kOk;
    }
  }
  TranslationNormalEquations ne;
  for (std::size_t q = 0; q < k; ++q) {
    const uint32_t i = idx[q];
    if (!usable_[i]) continue;
    const double z = std::max(Rp_[i].z() + t0.z(), 0.05);
    const double s = c[i].sigma_px > 0.0f ? double(c[i].sigma_px) : 1.0;
    ne.add(Rp_[i], c[i].u_cur, K, 1.0 / (s * s * z * z));
  }
  if (ne.rows < 2) return MotionStatus::kTooFewCorrespondences;
  return ne.solve(t) ? MotionStatus::kOk : MotionStatus::kDegenerate;
}

std::size_t MotionWorkspace::collect_inliers(const Eigen::Vector3d& t, const PinholeK& K,
                                             const Correspondence2D3D* c, std::size_t n,
                                             const ConsistencyTest& test, double* rms_px) {
  std::size_t k = 0;
  double sum2 = 0;
  for (std::size_t i = 0; i < n; ++i) {
    double e2 = 0;
    const bool in = usable_[i] && test.consistent(Rp_[i], t, K, c[i], &e2);
    mask_[i] = in ? 1 : 0;
    if (in) {
      inliers_[k++] = static_cast<uint32_t>(i);
      sum2 += e2;
    }
  }
  if (rms_px) *rms_px = k > 0 ? std::sqrt(sum2 / double(k)) : 0.0;
  return k;
}

void MotionWorkspace::finish(const Eigen::Vector3d& t_hat, const PinholeK& K, const Correspondence2D3D* c,
                             std::size_t n, const ConsistencyTest& test, bool weighted, int refine_passes,
                             std::size_t min_inliers, MotionEstimate* out, std::size_t precollected) {
  Eigen::Vector3d t = t_hat;
  // Paper lines 14-19, then optional re-collection passes with the refined t
  // (t_hat from one run can be a few px off at the image border).
  for (int pass = 0; pass <= std::max(refine_passes, 0); ++pass) {
    const std::size_t k = (pass == 0 && precollected != kNotCollected)
                              ? precollected
                              : collect_inliers(t, K, c, n, test, nullptr);
    out->num_inliers = k;
    if (k < std::max<std::size_t>(min_inliers, 2)) {
      out->status = MotionStatus::kTooFewInliers;
      out->t = t;
      return;
    }
    Eigen::Vector3d t_new;
    const MotionStatus s = solve_on(inliers_.get(), k, K, c, weighted, &t, &t_new);
    if (s != MotionStatus::kOk) {
      out->status = s;
      out->t = t;
      return;
    }
    t = t_new;
  }
  // Residual of the returned t on the returned set (mask_/inliers_ are the
  // set that produced t, as in the paper).
  double sum2 = 0;
  for (std::size_t q = 0; q < out->num_inliers; ++q) {
    const uint32_t i = inliers_[q];
    double e2 = 0;
    test.consistent(Rp_[i], t, K, c[i], &e2);
    sum2 += std::isfinite(e2) ? e2 : 0.0;
  }
  out->inlier_rms_px = std::sqrt(sum2 / double(out->num_inliers));
  out->t = t;
  out->status = MotionStatus::kOk;
}

PoseRefineResult MotionWorkspace::refine_pose(Eigen::Matrix3d* R, Eigen::Vector3d* t, const PinholeK& K,
                                              const Correspondence2D3D* c, std::size_t n, MotionEstimate* est,
                                              const ConsistencyTest& test, const PoseRefineOptions& opt,
                                              const Eigen::Matrix3d* R_prior) {
  const std::size_t m = std::min(n, est->num_used);
  const PoseRefineResult res =
      refine_pose_gauss_newton(R, t, K, c, m, inliers_.get(), est->num_inliers, opt, R_prior);
  if (!res.ok) return res;
  // With R corrected, correspondences that only failed because of the IMU's
  // rotation error (far from the image centre) come back.
  precompute(*R, c, m);
  double rms = 0;
  const std::size_t k = collect_inliers(*t, K, c, m, test, &rms);
  if (k >= 3) {
    est->num_inliers = k;
    est->inlier_rms_px = rms;
  }
  return res;
}

// ---------------------------------------------------------------------------

LonscEstimator::LonscEstimator(std::size_t capacity, const LonscOptions& opt)
    : MotionWorkspace(capacity), opt_(opt) {}

MotionEstimate LonscEstimator::estimate(const Eigen::Matrix3d& R, const PinholeK& K,
                                        const Correspondence2D3D* c, std::size_t n, const uint32_t* order,
                                        const Eigen::Vector3d& t_init) {
  MotionEstimate out;
  const std::size_t m = std::min(n, capacity_);
  out.num_used = m;
  out.truncated = n - m;
  precompute(R, c, m);

  // The walk: the given order without out-of-range or unusable entries (an
  // unusable correspondence says nothing about the motion, so it must not
  // break a run).
  std::size_t W = 0;
  for (std::size_t k = 0; k < m; ++k) {
    const uint32_t i = order ? order[k] : static_cast<uint32_t>(k);
    if (i < m && usable_[i]) run_[W++] = i;
  }
  if (W < 2) {
    out.status = MotionStatus::kTooFewCorrespondences;
    return out;
  }

  const ConsistencyTest& test = opt_.consistency;
  Eigen::Vector3d T = t_init;
  bool T_valid = t_init.allFinite();
  // Normal equations of the current run (grow_model): the run's model is its
  // least-squares t, not the first pair's, so pixel noise on two points does
  // not break a run of inliers (docs/lonsc.md, "deviations").
  TranslationNormalEquations run_ne;
  auto grow = [&](uint32_t i) {
    const double z = std::max(Rp_[i].z() + T.z(), 0.05);
    const double s_px = c[i].sigma_px > 0.0f ? double(c[i].sigma_px) : 1.0;
    run_ne.add(Rp_[i], c[i].u_cur, K, 1.0 / (s_px * s_px * z * z));
  };
  // The K longest runs (K = candidate_runs; 1 = the paper's MLen/MTail).
  // Strict '>' keeps the earlier run on ties, as the paper's CLen > MLen does.
  constexpr int kMaxCand = 8;
  struct Run {
    int len = 0, tail = -1;
  };
  Run cand[kMaxCand];
  const int n_cand = std::clamp(opt_.candidate_runs, 1, kMaxCand);
  auto offer = [&](int len, int tail) {
    if (len <= 0) return;
    for (int q = 0; q < n_cand; ++q) {
      if (len > cand[q].len) {
        for (int r = n_cand - 1; r > q; --r) cand[r] = cand[r - 1];
        cand[q] = Run{len, tail};
        return;
      }
    }
  };
  int clen = 0, ctail = -1;
  auto end_run = [&]() {
    offer(clen, ctail);
    clen = 0;
  };
  for (std::size_t w = 1; w < W; ++w) {  // paper line 2: i = 2..n
    const uint32_t i = run_[w];
    ++out.iterations;
    if (T_valid && test.consistent(Rp_[i], T, K, c[i])) {
      ++clen;
      ctail = static_cast<int>(w);
      if (opt_.grow_model) {
        grow(i);
        // Re-solve once the pair has two companions (the 2-point model is the
        // noisiest), then every 8th member. Short runs are the common case
        // (every IMU-rotation-induced miss breaks one), so solves are rationed.
        Eigen::Vector3d T_run;
        if ((run_ne.rows == 4 || run_ne.rows % 8 == 0) && run_ne.solve(&T_run)) T = T_run;
      }
      continue;
    }
    end_run();
    // Paper line 9: new model from the pair (c_{i-1}, c_i).
    ++out.model_estimates;
    const uint32_t h = run_[w - 1];
    Eigen::Vector3d T2;
    run_ne.clear();
    if (!solve_pair(h, i, K, c, opt_.min_pair_separation_px, &T2)) {
      T_valid = false;
      continue;
    }
    if (!opt_.verify_seed_pair) {
      T = T2;
      T_valid = true;
      clen = 1;  // paper line 10
      ctail = static_cast<int>(w);
      if (opt_.grow_model) grow(i);
      continue;
    }
    if (test.consistent(Rp_[h], T2, K, c[h]) && test.consistent(Rp_[i], T2, K, c[i])) {
      T = T2;
      T_valid = true;
      clen = 2;
      ctail = static_cast<int>(w);
      if (opt_.grow_model) {
        grow(h);
        grow(i);
      }
    } else {
      T_valid = false;
    }
  }
  end_run();
  out.longest_run = cand[0].len;
  const int min_len = std::max(opt_.min_run_length, 2);
  if (cand[0].len < min_len) {
    out.status = MotionStatus::kNoConsistentRun;
    return out;
  }

  // Paper line 13: t_hat from the longest run. With candidate_runs > 1 each
  // of the K longest runs proposes a t_hat and the one with the largest
  // consensus wins: a moving object seen by consecutive correspondences can
  // produce the longest run without being the majority.
  Eigen::Vector3d t_hat = Eigen::Vector3d::Zero();
  std::size_t best_support = 0;
  int chosen = -1, collected_for = -1;
  MotionStatus last_status = MotionStatus::kNoConsistentRun;
  for (int q = 0; q < n_cand && cand[q].len >= min_len; ++q) {
    const int begin = cand[q].tail - cand[q].len + 1;
    Eigen::Vector3d t_q;
    last_status = solve_on(run_.get() + begin, static_cast<std::size_t>(cand[q].len), K, c,
                           opt_.weighted_least_squares, nullptr, &t_q);
    if (last_status != MotionStatus::kOk) continue;
    ++out.candidates_evaluated;
    if (n_cand == 1) {
      t_hat = t_q;
      chosen = q;
      break;
    }
    // Support = paper line 14-18's Phi for this t_hat; collected into
    // mask_/inliers_ so that finish() can reuse it for the chosen candidate.
    const std::size_t support = collect_inliers(t_q, K, c, m, test, nullptr);
    collected_for = q;
    if (support > best_support) {
      best_support = support;
      t_hat = t_q;
      chosen = q;
    }
    // A majority cannot be outvoted by another motion (two motions more than
    // a threshold apart share few correspondences): skip the other passes.
    if (2 * support > W) break;
  }
  if (chosen < 0) {
    out.status = last_status;
    return out;
  }
  out.chosen_run = cand[chosen].len;
  out.chosen_run_begin = cand[chosen].tail - cand[chosen].len + 1;
  finish(t_hat, K, c, m, test, opt_.weighted_least_squares, opt_.refine_passes, opt_.min_inliers, &out,
         collected_for == chosen && n_cand > 1 ? best_support : kNotCollected);
  return out;
}

// ---------------------------------------------------------------------------

TwoPointRansac::TwoPointRansac(std::size_t capacity, const RansacOptions& opt)
    : MotionWorkspace(capacity), opt_(opt), rng_state_(opt.seed) {}

void TwoPointRansac::set_options(const RansacOptions& opt) {
  opt_ = opt;
  rng_state_ = opt.seed;
}

uint64_t TwoPointRansac::next_random() { return splitmix64(&rng_state_); }

MotionEstimate TwoPointRansac::estimate(const Eigen::Matrix3d& R, const PinholeK& K,
                                        const Correspondence2D3D* c, std::size_t n) {
  MotionEstimate out;
  const std::size_t m = std::min(n, capacity_);
  out.num_used = m;
  out.truncated = n - m;
  precompute(R, c, m);
  if (opt_.reseed_each_call) rng_state_ = opt_.seed;

  std::size_t W = 0;
  for (std::size_t i = 0; i < m; ++i)
    if (usable_[i]) run_[W++] = static_cast<uint32_t>(i);
  if (W < 2) {
    out.status = MotionStatus::kTooFewCorrespondences;
    return out;
  }

  const ConsistencyTest& test = opt_.consistency;
  std::size_t best = 0;
  Eigen::Vector3d best_t = Eigen::Vector3d::Zero();
  long needed = opt_.max_iterations;
  const double log1mp = std::log(1.0 - std::clamp(opt_.confidence, 0.0, 1.0 - 1e-12));
  for (int it = 0; it < opt_.max_iterations && it < needed; ++it) {
    ++out.iterations;
    const std::size_t a = next_random() % W;
    std::size_t b = next_random() % (W - 1);
    if (b >= a) ++b;
    Eigen::Vector3d T;
    if (!solve_pair(run_[a], run_[b], K, c, opt_.min_pair_separation_px, &T)) continue;
    ++out.model_estimates;
    std::size_t count = 0;
    for (std::size_t q = 0; q < W; ++q) {
      const uint32_t i = run_[q];
      count += test.consistent(Rp_[i], T, K, c[i]) ? 1 : 0;
    }
    if (count > best) {
      best = count;
      best_t = T;
      // Standard adaptive stop: enough draws for an all-inlier pair with
      // probability `confidence` at the best inlier ratio seen so far.
      const double w = double(count) / double(W);
      const double p_good = w * w;
      if (p_good >= 1.0 - 1e-12) {
        needed = it + 1;
      } else {
        needed = std::min<long>(opt_.max_iterations, long(std::ceil(log1mp / std::log(1.0 - p_good))));
      }
    }
  }
  if (best < 2) {
    out.status = MotionStatus::kTooFewInliers;
    return out;
  }
  finish(best_t, K, c, m, test, opt_.weighted_least_squares, opt_.refine_passes, opt_.min_inliers, &out);
  return out;
}

std::ostream& operator<<(std::ostream& os, const LonscOptions& o) {
  return os << "lonsc{" << o.consistency << " min_run_length=" << o.min_run_length
            << " verify_seed_pair=" << o.verify_seed_pair << " grow_model=" << o.grow_model
            << " candidate_runs=" << o.candidate_runs
            << " min_pair_separation_px=" << o.min_pair_separation_px
            << " weighted_least_squares=" << o.weighted_least_squares << " refine_passes=" << o.refine_passes
            << " min_inliers=" << o.min_inliers << "}";
}

std::ostream& operator<<(std::ostream& os, const RansacOptions& o) {
  return os << "ransac2pt{" << o.consistency << " confidence=" << o.confidence
            << " max_iterations=" << o.max_iterations << " seed=" << o.seed
            << " reseed_each_call=" << o.reseed_each_call
            << " min_pair_separation_px=" << o.min_pair_separation_px
            << " weighted_least_squares=" << o.weighted_least_squares << " refine_passes=" << o.refine_passes
            << " min_inliers=" << o.min_inliers << "}";
}

}  // namespace kestrel::core

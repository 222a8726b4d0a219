// Synthetic sliding-window problems for the optimiser tests and benchmark:
// a smooth analytic flight in a textured room, an IMU integrated from the
// exact motion (midpoint samples, so the preintegration is exact up to the
// added noise), projections with pixel noise and depth with sigma k z^2.
// Deterministic for a given seed.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "kestrel/core/preintegration.hpp"
#include "kestrel/core/so3.hpp"
#include "kestrel/core/window_optimizer.hpp"

namespace kestrel::test {

struct SimConfig {
  double frame_rate_hz = 20.0;
  int keyframe_every = 2;  // every k-th frame is a keyframe
  int imu_per_frame = 10;  // IMU samples per frame interval (200 Hz at 20 fps)
  int n_landmarks = 600;
  double pixel_sigma = 0.7;
  double depth_k = 0.0025;  // sigma(z) = k z^2
  double max_depth_m = 6.0;
  double yaw_rate_rps = 0.35;  // slow turn so that every wall is seen
  uint64_t seed = 1;
  bool bounded_bias = false;  // truth bias stays constant either way
};

struct SimFrame {
  int64_t t_ns = 0;
  core::NavState truth;
  bool keyframe = false;
  std::vector<core::WindowObservation> obs;
  std::vector<Eigen::Vector2d> uv_vel;  // image velocity per observation [px/s] (with_time_offset)
  core::Preintegrated pim;              // previous frame -> this one (empty for the first)
};

inline core::PinholeK sim_K() { return {420.0, 420.0, 320.0, 240.0}; }
inline Eigen::Isometry3d sim_T_BC() {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  Eigen::Matrix3d R;
  R << 0, 0, 1, -1, 0, 0, 0, -1, 0;  // camera z = body x (forward), camera x = -body y
  T.linear() = R;
  T.translation() = Eigen::Vector3d(0.05, 0.0, 0.02);
  return T;
}

inline core::ImuNoiseParams sim_noise() {
  ImuNoise n;
  n.gyro_noise_density_rad_s_sqrthz = 2.44e-4;  // BMX055, paper 000 Table 1
  n.acc_noise_density_mps2_sqrthz = 1.47e-3;
  n.gyro_random_walk_rad_s2_sqrthz = 2e-5;
  n.acc_random_walk_mps3_sqrthz = 3e-4;
  return core::ImuNoiseParams::from_imu_noise(n, 200.0);
}

class SimWorld {
 public:
  explicit SimWorld(const SimConfig& c) : c_(c), rng_(c.seed) {
    std::uniform_real_distribution<double> U(0.0, 1.0);
    // Points on the walls, floor and ceiling of a 9 x 9 x 3.5 m room.
    for (int i = 0; i < c.n_landmarks; ++i) {
      const int face = i % 6;
      const double a = U(rng_), b = U(rng_);
      Eigen::Vector3d p;
      switch (face) {
        case 0:
          p = {4.5, -4.5 + 9 * a, -1.0 + 3.5 * b};
          break;
        case 1:
          p = {-4.5, -4.5 + 9 * a, -1.0 + 3.5 * b};
          break;
        case 2:
          p = {-4.5 + 9 * a, 4.5, -1.0 + 3.5 * b};
          break;
        case 3:
          p = {-4.5 + 9 * a, -4.5, -1.0 + 3.5 * b};
          break;
        case 4:
          p = {-4.5 + 9 * a, -4.5 + 9 * b, -1.0};
          break;
        default:
          p = {-4.5 + 9 * a, -4.5 + 9 * b, 2.5};
          break;
      }
      points_.push_back(p);
    }
    bg_ = Eigen::Vector3d(0.002, -0.0015, 0.001);
    ba_ = Eigen::Vector3d(0.03, -0.02, 0.04);
  }

  // Truth at time t [s].
  void pose(double t, Eigen::Vector3d* p, Eigen::Matrix3d* R, Eigen::Vector3d* v = nullptr,
            Eigen::Vector3d* a = nullptr) const {
    *p = Eigen::Vector3d(0.8 * std::sin(0.6 * t), 0.6 * std::sin(0.9 * t), 0.8 + 0.2 * std::sin(1.1 * t));
    if (v) *v = Eigen::Vector3d(0.48 * std::cos(0.6 * t), 0.54 * std::cos(0.9 * t), 0.22 * std::cos(1.1 * t));
    if (a)
      *a =
          Eigen::Vector3d(-0.288 * std::sin(0.6 * t), -0.486 * std::sin(0.9 * t), -0.242 * std::sin(1.1 * t));
    const double yaw = c_.yaw_rate_rps * t + 0.2 * std::sin(0.7 * t);
    const double pitch = 0.08 * std::sin(1.3 * t), roll = 0.1 * std::sin(0.8 * t + 0.3);
    *R = (Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()) *
          Eigen::AngleAxisd(pitch, Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()))
             .toRotationMatrix();
  }

  core::NavState state(double t) const {
    core::NavState x;
    Eigen::Matrix3d R;
    pose(t, &x.p_WB, &R, &x.v_WB);
    x.q_WB = Eigen::Quaterniond(R);
    x.bg_rps = bg_;
    x.ba_mps2 = ba_;
    x.t_ns = static_cast<int64_t>(std::llround(t * 1e9));
    return x;
  }

  // Noisy IMU reading at t (body rate by central difference of the exact attitude).
  void imu(double t, Eigen::Vector3d* gyro, Eigen::Vector3d* acc) {
    const double h = 1e-5;
    Eigen::Vector3d p, a;
    Eigen::Matrix3d R, Rm, Rp;
    pose(t, &p, &R, nullptr, &a);
    pose(t - h, &p, &Rm);
    pose(t + h, &p, &Rp);
    pose(t, &p, &R, nullptr, &a);
    const Eigen::Vector3d w = core::so3::Log(Rm.transpose() * Rp) / (2 * h);
    const double dt = 1.0 / (c_.frame_rate_hz * c_.imu_per_frame);
    const core::ImuNoiseParams n = sim_noise();
    std::normal_distribution<double> N(0.0, 1.0);
    const double sg = n.gyro_noise_density_rad_s_sqrthz / std::sqrt(dt);
    const double sa = n.acc_noise_density_mps2_sqrthz / std::sqrt(dt);
    *gyro = w + bg_ + sg * Eigen::Vector3d(N(rng_), N(rng_), N(rng_));
    *acc = R.transpose() * (a - Eigen::Vector3d(0, 0, -9.81)) + ba_ +
           sa * Eigen::Vector3d(N(rng_), N(rng_), N(rng_));
  }

  // Frames 0..n-1; frame 0 starts at t0_s.
  std::vector<SimFrame> frames(int n, double t0_s = 0.0) {
    std::vector<SimFrame> out;
    const double dtf = 1.0 / c_.frame_rate_hz;
    const double dti = dtf / c_.imu_per_frame;
    core::PreintegrationParams pp;
    pp.noise = sim_noise();
    pp.gravity_mps2 = 9.81;
    std::normal_distribution<double> N(0.0, 1.0);
    for (int k = 0; k < n; ++k) {
      SimFrame f;
      const double t = t0_s + k * dtf;
      f.t_ns = static_cast<int64_t>(std::llround(t * 1e9));
      f.truth = state(t);
      f.keyframe = k % c_.keyframe_every == 0;
      f.pim = core::Preintegrated(pp);
      if (k > 0) {
        f.pim.reset(Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero(), out.back().t_ns);
        for (int i = 0; i < c_.imu_per_frame; ++i) {
          Eigen::Vector3d g, a;
          imu(t - dtf + (i + 0.5) * dti, &g, &a);  // midpoint sample: exact up to O(dt^2)
          f.pim.integrate(g, a, dti);
        }
      }
      const Eigen::Isometry3d T_BC = sim_T_BC();
      const Eigen::Matrix3d R = f.truth.q_WB.toRotationMatrix();
      const core::PinholeK K = sim_K();
      for (std::size_t i = 0; i < points_.size(); ++i) {
        const Eigen::Vector3d p_B = R.transpose() * (points_[i] - f.truth.p_WB);
        const Eigen::Vector3d p_C = T_BC.inverse() * p_B;
        if (p_C.z() < 0.3 || p_C.z() > c_.max_depth_m) continue;
        Eigen::Vector2d uv(K.fx * p_C.x() / p_C.z() + K.cx, K.fy * p_C.y() / p_C.z() + K.cy);
        if (uv.x() < 5 || uv.y() < 5 || uv.x() > 635 || uv.y() > 475) continue;
        core::WindowObservation o;
        o.landmark_id = static_cast<uint32_t>(1000 + i);
        o.uv = uv + c_.pixel_sigma * Eigen::Vector2d(N(rng_), N(rng_));
        o.depth_m = p_C.z() + c_.depth_k * p_C.z() * p_C.z() * N(rng_);
        o.sigma_px = static_cast<float>(c_.pixel_sigma);
        f.obs.push_back(o);
      }
      out.push_back(std::move(f));
    }
    return out;
  }

  // The camera saw each frame td_s later than its stamp: every pixel is
  // re-projected at t + td_s (keeping its noise), and its image velocity is the
  // backward difference over the previous frame, as the window estimator
  // computes it (frame 0: none).
  void with_time_offset(std::vector<SimFrame>& frames, double td_s) const {
    const Eigen::Isometry3d T_CB = sim_T_BC().inverse();
    const core::PinholeK K = sim_K();
    auto project = [&](double t, const Eigen::Vector3d& p_W) {
      const core::NavState x = state(t);
      const Eigen::Vector3d p_C = T_CB * (x.q_WB.conjugate() * (p_W - x.p_WB));
      return Eigen::Vector2d(K.fx * p_C.x() / p_C.z() + K.cx, K.fy * p_C.y() / p_C.z() + K.cy);
    };
    const double dtf = 1.0 / c_.frame_rate_hz;
    for (std::size_t k = 0; k < frames.size(); ++k) {
      SimFrame& f = frames[k];
      const double t = 1e-9 * static_cast<double>(f.t_ns);
      f.uv_vel.assign(f.obs.size(), Eigen::Vector2d::Zero());
      for (std::size_t i = 0; i < f.obs.size(); ++i) {
        const Eigen::Vector3d& p_W = points_[f.obs[i].landmark_id - 1000];
        const Eigen::Vector2d noise = f.obs[i].uv - project(t, p_W);
        const Eigen::Vector2d seen = project(t + td_s, p_W);
        f.obs[i].uv = seen + noise;
        if (k > 0) f.uv_vel[i] = (seen - project(t - dtf + td_s, p_W)) / dtf;
      }
    }
  }

  const std::vector<Eigen::Vector3d>& points() const { return points_; }
  std::mt19937_64& rng() { return rng_; }

 private:
  SimConfig c_;
  std::mt19937_64 rng_;
  std::vector<Eigen::Vector3d> points_;
  Eigen::Vector3d bg_, ba_;
};

// Truth perturbed by a few cm, ~1 degree, and bias/velocity offsets. keep_gauge:
// position and yaw untouched (the first frame, whose gauge holds them).
inline core::NavState perturb(const core::NavState& x, std::mt19937_64& rng, double pos_m = 0.03,
                              double rot_rad = 0.017, bool keep_gauge = false) {
  std::normal_distribution<double> N(0.0, 1.0);
  core::NavState y = x;
  Eigen::Vector3d dphi(N(rng), N(rng), N(rng));
  dphi *= rot_rad / std::sqrt(3.0);
  if (keep_gauge) {
    // Tilt only: a rotation about a horizontal world axis changes roll/pitch, and the
    // yaw (atan2(R10, R00)) is restored exactly afterwards.
    const Eigen::Matrix3d R = x.q_WB.toRotationMatrix();
    Eigen::Matrix3d Rn = core::so3::Exp(Eigen::Vector3d(dphi.x(), dphi.y(), 0.0)) * R;
    const double dyaw = std::atan2(Rn(1, 0), Rn(0, 0)) - std::atan2(R(1, 0), R(0, 0));
    Rn = Eigen::AngleAxisd(-dyaw, Eigen::Vector3d::UnitZ()).toRotationMatrix() * Rn;
    y.q_WB = Eigen::Quaterniond(Rn);
  } else {
    y.p_WB += pos_m / std::sqrt(3.0) * Eigen::Vector3d(N(rng), N(rng), N(rng));
    y.q_WB = (x.q_WB * core::so3::exp_quat(dphi)).normalized();
  }
  y.v_WB += 0.03 * Eigen::Vector3d(N(rng), N(rng), N(rng));
  y.bg_rps += 0.001 * Eigen::Vector3d(N(rng), N(rng), N(rng));
  y.ba_mps2 += 0.02 * Eigen::Vector3d(N(rng), N(rng), N(rng));
  return y;
}

inline core::WindowOptions sim_options(int S = 3, int N = 5) {
  core::WindowOptions o;
  o.S = S;
  o.N = N;
  o.imu = sim_noise();
  o.pixel_sigma = 0.7;
  // Correctness tests must not depend on the machine's speed: an unoptimised
  // sanitizer build would hit the 35 ms flight budget and stop early. The
  // budget itself has its own test.
  o.time_budget_ms = 1e5;
  return o;
}

inline core::WindowFrameInput frame_input(const SimFrame& f, const core::NavState& guess, bool first) {
  core::WindowFrameInput in;
  in.t_ns = f.t_ns;
  in.guess = guess;
  in.guess.t_ns = f.t_ns;
  in.imu_from_prev = first ? nullptr : &f.pim;
  in.obs = f.obs.data();
  in.n_obs = static_cast<int>(f.obs.size());
  in.uv_vel_pxps = f.uv_vel.empty() ? nullptr : f.uv_vel.data();
  in.keyframe = f.keyframe;
  return in;
}

// Fills a window with frames[0..n) at perturbed guesses (first frame: gauge kept).
inline void fill_window(core::WindowOptimizer& w, const std::vector<SimFrame>& frames, int n,
                        std::mt19937_64& rng) {
  for (int k = 0; k < n; ++k) {
    w.add_frame(frame_input(frames[k], perturb(frames[k].truth, rng, 0.03, 0.017, k == 0), k == 0));
  }
}

inline double rot_err(const Eigen::Quaterniond& a, const Eigen::Quaterniond& b) {
  return core::so3::Log((a.conjugate() * b).toRotationMatrix()).norm();
}

}  // namespace kestrel::test

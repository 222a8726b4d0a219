// Synthetic 2D-3D correspondence sets for the motion-estimation tests and the
// LONSC benchmark: an RGB-D camera (640x480, f = 525) between two frames 33 ms
// apart on a quadrotor. Deterministic for a given seed (mt19937_64 + libstdc++
// distributions).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "kestrel/core/motion_estimation.hpp"

namespace kestrel::test {

inline core::PinholeK kinect_k() { return core::PinholeK{525.0, 525.0, 319.5, 239.5}; }

struct SimConfig {
  int n = 300;
  double width = 640, height = 480, border_px = 8;
  double min_depth_m = 0.5, max_depth_m = 5.0;
  double depth_noise_coeff = 0.0025;  // sigma_z = coeff * z^2 [m]
  double pixel_noise_px = 0.7;        // on both keypoints
  double max_rot_deg = 5.0, max_trans_m = 0.05;
  double imu_err_min_deg = 0.1, imu_err_max_deg = 0.3;
  double outlier_frac = 0.0;
  // Structured: 2/3 of the outliers are true matches on ONE rigid object that
  // moved by an extra 10-20 cm (mostly in the image plane); the rest uniform.
  bool structured = false;
  // Matcher cost model (ORB Hamming distance): correct matches ~N(22, 8),
  // wrong ones ~N(45, 10), clamped to [0, 256]; overlapping on purpose.
  double inlier_cost_mean = 22, inlier_cost_sd = 8;
  double outlier_cost_mean = 45, outlier_cost_sd = 10;
  bool noise = true;  // false: exact data (depth and pixel noise off)
};

struct SimFrame {
  std::vector<core::Correspondence2D3D> c;  // detection (raster) order, like a FAST + matcher pipeline
  std::vector<uint8_t> is_inlier;           // ground truth: consistent with the camera motion
  std::vector<uint8_t> role;                // 0 inlier, 1 uniform outlier, 2 moving object
  Eigen::Matrix3d R_true = Eigen::Matrix3d::Identity();
  Eigen::Matrix3d R_imu = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t_true = Eigen::Vector3d::Zero();
  std::size_t num_inliers() const {
    std::size_t k = 0;
    for (auto b : is_inlier) k += b;
    return k;
  }
};

inline Eigen::Vector3d random_unit(std::mt19937_64& rng) {
  std::normal_distribution<double> N(0.0, 1.0);
  Eigen::Vector3d v(N(rng), N(rng), N(rng));
  return v.normalized();
}

inline Eigen::Matrix3d rot_from_axis_angle(const Eigen::Vector3d& axis, double angle_rad) {
  return Eigen::AngleAxisd(angle_rad, axis.normalized()).toRotationMatrix();
}

inline double rotation_error_deg(const Eigen::Matrix3d& A, const Eigen::Matrix3d& B) {
  return Eigen::AngleAxisd(A * B.transpose()).angle() * 180.0 / M_PI;
}

inline SimFrame simulate(const SimConfig& cfg, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> U(0.0, 1.0);
  std::normal_distribution<double> N(0.0, 1.0);
  const core::PinholeK K = kinect_k();
  const double deg = M_PI / 180.0;
  SimFrame f;
  f.R_true = rot_from_axis_angle(random_unit(rng), cfg.max_rot_deg * deg * U(rng));
  f.t_true = random_unit(rng) * cfg.max_trans_m * U(rng);
  const double imu_err = (cfg.imu_err_min_deg + (cfg.imu_err_max_deg - cfg.imu_err_min_deg) * U(rng)) * deg;
  f.R_imu = rot_from_axis_angle(random_unit(rng), imu_err) * f.R_true;

  const int n_out = static_cast<int>(std::lround(cfg.outlier_frac * cfg.n));
  const int n_struct = cfg.structured ? (2 * n_out) / 3 : 0;
  const int n_uniform = n_out - n_struct;

  // Features of the previous frame: pixel, true depth, and visible after the motion.
  struct Feat {
    Eigen::Vector2d u_prev;
    Eigen::Vector3d p_true;
  };
  std::vector<Feat> feats;
  feats.reserve(cfg.n);
  auto project = [&](const Eigen::Vector3d& p) {
    return Eigen::Vector2d(K.fx * p.x() / p.z() + K.cx, K.fy * p.y() / p.z() + K.cy);
  };
  auto in_image = [&](const Eigen::Vector2d& u) {
    return u.x() >= cfg.border_px && u.x() < cfg.width - cfg.border_px && u.y() >= cfg.border_px &&
           u.y() < cfg.height - cfg.border_px;
  };
  while (static_cast<int>(feats.size()) < cfg.n) {
    const Eigen::Vector2d u(cfg.border_px + U(rng) * (cfg.width - 2 * cfg.border_px),
                            cfg.border_px + U(rng) * (cfg.height - 2 * cfg.border_px));
    const double z = cfg.min_depth_m + U(rng) * (cfg.max_depth_m - cfg.min_depth_m);
    const Eigen::Vector3d p((u.x() - K.cx) / K.fx * z, (u.y() - K.cy) / K.fy * z, z);
    const Eigen::Vector3d pc = f.R_true * p + f.t_true;
    if (pc.z() < 0.1 || !in_image(project(pc))) continue;
    feats.push_back({u, p});
  }
  // FAST reports corners row by row: the matcher's natural order is raster order.
  std::sort(feats.begin(), feats.end(), [](const Feat& a, const Feat& b) {
    const int ra = static_cast<int>(a.u_prev.y()), rb = static_cast<int>(b.u_prev.y());
    return ra != rb ? ra < rb : a.u_prev.x() < b.u_prev.x();
  });

  // Roles: 0 inlier, 1 uniform outlier, 2 moving object.
  std::vector<int> role(cfg.n, 0);
  if (n_struct > 0) {
    // The object: the n_struct features nearest to a random image point (a blob).
    const Eigen::Vector2d centre(U(rng) * cfg.width, U(rng) * cfg.height);
    std::vector<std::pair<double, int>> d;
    for (int i = 0; i < cfg.n; ++i) d.emplace_back((feats[i].u_prev - centre).squaredNorm(), i);
    std::sort(d.begin(), d.end());
    for (int k = 0; k < n_struct; ++k) role[d[k].second] = 2;
  }
  {
    std::vector<int> free;
    for (int i = 0; i < cfg.n; ++i)
      if (role[i] == 0) free.push_back(i);
    std::shuffle(free.begin(), free.end(), rng);
    for (int k = 0; k < n_uniform && k < static_cast<int>(free.size()); ++k) role[free[k]] = 1;
  }
  // Object motion: the camera motion plus 10-20 cm, mostly in the image plane
  // (an along-axis offset would be nearly invisible near the image centre).
  Eigen::Vector3d extra = random_unit(rng);
  extra.z() *= 0.3;
  const Eigen::Vector3d t_obj = f.t_true + extra.normalized() * (0.10 + 0.10 * U(rng));

  const double pn = cfg.noise ? cfg.pixel_noise_px : 0.0;
  auto cost = [&](double mean, double sd) {
    return static_cast<float>(
        std::round(std::clamp(mean + sd * N(rng), 0.0, 256.0)));  // integral, like Hamming
  };
  f.c.resize(cfg.n);
  f.is_inlier.assign(cfg.n, 0);
  f.role.assign(cfg.n, 0);
  for (int i = 0; i < cfg.n; ++i) {
    const Feat& ft = feats[i];
    core::Correspondence2D3D& c = f.c[i];
    c.id = static_cast<uint32_t>(i);
    c.sigma_px = static_cast<float>(cfg.noise ? cfg.pixel_noise_px : 1.0);
    // Measured 3D point: noisy keypoint back-projected with noisy depth.
    const double z = ft.p_true.z();
    const double zm = cfg.noise ? z + cfg.depth_noise_coeff * z * z * N(rng) : z;
    const Eigen::Vector2d um = ft.u_prev + pn * Eigen::Vector2d(N(rng), N(rng));
    c.p_prev = Eigen::Vector3d((um.x() - K.cx) / K.fx * zm, (um.y() - K.cy) / K.fy * zm, zm);
    if (role[i] == 1) {
      c.u_cur = Eigen::Vector2d(U(rng) * cfg.width, U(rng) * cfg.height);
      c.match_cost = cost(cfg.outlier_cost_mean, cfg.outlier_cost_sd);
    } else {
      const Eigen::Vector3d t = role[i] == 2 ? t_obj : f.t_true;
      c.u_cur = project(f.R_true * ft.p_true + t) + pn * Eigen::Vector2d(N(rng), N(rng));
      // Moving-object matches are correct matches: they look as good as inliers.
      c.match_cost = cost(cfg.inlier_cost_mean, cfg.inlier_cost_sd);
    }
    f.is_inlier[i] = role[i] == 0 ? 1 : 0;
    f.role[i] = static_cast<uint8_t>(role[i]);
  }
  return f;
}

}  // namespace kestrel::test

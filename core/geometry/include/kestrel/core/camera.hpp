// Pinhole camera with radial-tangential distortion: projection of points in
// the camera frame C (x right, y down, z forward) to distorted pixels, and
// back. Fixed-size, allocation-free: called per feature in the tracker.
#pragma once

#include <Eigen/Core>

#include "kestrel/msgs.hpp"

namespace kestrel::core {

class PinholeCamera {
 public:
  PinholeCamera() = default;
  explicit PinholeCamera(const CameraIntrinsics& in);

  int width() const { return width_; }
  int height() const { return height_; }
  double fx() const { return fx_; }
  double fy() const { return fy_; }
  double cx() const { return cx_; }
  double cy() const { return cy_; }
  bool has_distortion() const { return distorted_; }

  // Normalised undistorted coordinates (x/z, y/z) -> distorted pixel.
  Eigen::Vector2d distort_normalized_to_pixel(const Eigen::Vector2d& xn) const;
  // Distorted pixel -> normalised undistorted coordinates (fixed-point
  // iteration; converges for the mild distortion of RGB-D cameras).
  Eigen::Vector2d pixel_to_normalized(const Eigen::Vector2d& uv) const;
  // Distorted pixel -> undistorted pixel (K * normalised): what the 2D-3D
  // solvers of paper 000 eq. 2-3 take.
  Eigen::Vector2d undistort_pixel(const Eigen::Vector2d& uv) const;
  // Undistorted pixel <-> camera point with the ideal pinhole K.
  Eigen::Vector2d project_undistorted(const Eigen::Vector3d& p_C) const {
    return {fx_ * p_C.x() / p_C.z() + cx_, fy_ * p_C.y() / p_C.z() + cy_};
  }
  // Back-projection of a distorted pixel at metric depth z (along the optical axis).
  Eigen::Vector3d back_project(const Eigen::Vector2d& uv, double z_m) const {
    const Eigen::Vector2d xn = pixel_to_normalized(uv);
    return {xn.x() * z_m, xn.y() * z_m, z_m};
  }
  bool in_image(const Eigen::Vector2d& uv, double margin_px = 0.0) const {
    return uv.x() >= margin_px && uv.y() >= margin_px && uv.x() < width_ - margin_px &&
           uv.y() < height_ - margin_px;
  }

 private:
  int width_ = 0, height_ = 0;
  double fx_ = 1, fy_ = 1, cx_ = 0, cy_ = 0;
  double k1_ = 0, k2_ = 0, p1_ = 0, p2_ = 0, k3_ = 0;
  bool distorted_ = false;
};

}  // namespace kestrel::core

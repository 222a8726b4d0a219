#include "kestrel/core/camera.hpp"

#include <stdexcept>

namespace kestrel::core {

PinholeCamera::PinholeCamera(const CameraIntrinsics& in)
    : width_(in.width), height_(in.height), fx_(in.fx), fy_(in.fy), cx_(in.cx), cy_(in.cy) {
  if (in.distortion == DistortionModel::kEquidistant) {
    // The RGB-D cameras Kestrel targets are radtan; a fisheye rig needs its
    // own model rather than a silently wrong one.
    throw std::invalid_argument("PinholeCamera: equidistant distortion is not supported");
  }
  if (in.distortion == DistortionModel::kRadTan) {
    k1_ = in.dist[0];
    k2_ = in.dist[1];
    p1_ = in.dist[2];
    p2_ = in.dist[3];
    k3_ = in.dist[4];
    distorted_ = k1_ != 0 || k2_ != 0 || p1_ != 0 || p2_ != 0 || k3_ != 0;
  }
}

Eigen::Vector2d PinholeCamera::distort_normalized_to_pixel(const Eigen::Vector2d& xn) const {
  const double x = xn.x(), y = xn.y();
  double xd = x, yd = y;
  if (distorted_) {
    const double r2 = x * x + y * y;
    const double radial = 1.0 + r2 * (k1_ + r2 * (k2_ + r2 * k3_));
    xd = x * radial + 2.0 * p1_ * x * y + p2_ * (r2 + 2.0 * x * x);
    yd = y * radial + p1_ * (r2 + 2.0 * y * y) + 2.0 * p2_ * x * y;
  }
  return {fx_ * xd + cx_, fy_ * yd + cy_};
}

Eigen::Vector2d PinholeCamera::pixel_to_normalized(const Eigen::Vector2d& uv) const {
  Eigen::Vector2d xd((uv.x() - cx_) / fx_, (uv.y() - cy_) / fy_);
  if (!distorted_) return xd;
  Eigen::Vector2d x = xd;
  for (int it = 0; it < 20; ++it) {
    const double r2 = x.squaredNorm();
    const double radial = 1.0 + r2 * (k1_ + r2 * (k2_ + r2 * k3_));
    const double dx = 2.0 * p1_ * x.x() * x.y() + p2_ * (r2 + 2.0 * x.x() * x.x());
    const double dy = p1_ * (r2 + 2.0 * x.y() * x.y()) + 2.0 * p2_ * x.x() * x.y();
    Eigen::Vector2d next((xd.x() - dx) / radial, (xd.y() - dy) / radial);
    if ((next - x).squaredNorm() < 1e-24) return next;
    x = next;
  }
  return x;
}

Eigen::Vector2d PinholeCamera::undistort_pixel(const Eigen::Vector2d& uv) const {
  const Eigen::Vector2d xn = pixel_to_normalized(uv);
  return {fx_ * xn.x() + cx_, fy_ * xn.y() + cy_};
}

}  // namespace kestrel::core

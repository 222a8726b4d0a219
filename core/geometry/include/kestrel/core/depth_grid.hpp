// A keyframe's depth image, coarse: one depth per cell of a cols x rows grid
// laid over the undistorted (pinhole K) image. The map keeps it per keyframe
// so the loop thread can align two keyframes' surfaces (surface_alignment.hpp)
// where their descriptors disagree, e.g. a revisit at another range
// (docs/map.md, "Surface verification").
//
// The tracking thread samples it (DepthGridSampler: a pixel table made once,
// no allocation per keyframe); the map back-projects it with the shape alone.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>

#include "kestrel/core/motion_estimation.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::core {

struct DepthGridShape {
  int cols = 0, rows = 0;  // 0: no grid
  PinholeK K;              // the undistorted image the grid covers
  int width = 0, height = 0;

  int cells() const { return cols * rows; }
  // rows from cols, keeping the image's aspect; cols <= 0 gives no grid.
  static DepthGridShape make(int cols, const PinholeK& K, int width, int height);
  // Normalised undistorted coordinates (x/z, y/z) of cell c's centre.
  Eigen::Vector2d ray(int c) const {
    const int col = c % cols, row = c / cols;
    const double u = (col + 0.5) * width / cols, v = (row + 0.5) * height / rows;
    return {(u - K.cx) / K.fx, (v - K.cy) / K.fy};
  }
  // The cell a camera-frame point projects into, or -1.
  int cell_of(const Eigen::Vector3d& p_C) const {
    if (p_C.z() <= 0) return -1;
    const double u = K.fx * p_C.x() / p_C.z() + K.cx, v = K.fy * p_C.y() / p_C.z() + K.cy;
    if (!(u >= 0 && v >= 0 && u < width && v < height)) return -1;
    return static_cast<int>(v * rows / height) * cols + static_cast<int>(u * cols / width);
  }
  // Cell c's point in the camera frame at depth z_mm (> 0).
  Eigen::Vector3d point_C(int c, uint16_t z_mm) const {
    const Eigen::Vector2d r = ray(c);
    const double z = z_mm * 1e-3;
    return {r.x() * z, r.y() * z, z};
  }
};

class DepthGridSampler {
 public:
  DepthGridSampler() = default;
  // cam: the colour camera the depth is registered to (with its distortion);
  // a cell is left empty where the 3x3 pixels around its centre miss depth or
  // spread more than edge_rel x z (a depth edge: neither surface).
  DepthGridSampler(const DepthGridShape& shape, const CameraIntrinsics& cam, const DepthModel& depth,
                   double edge_rel);
  bool enabled() const { return shape_.cells() > 0; }
  const DepthGridShape& shape() const { return shape_; }
  // z_mm[shape().cells()], 0 where empty; returns the cells with depth. No allocation.
  int sample(const ImageView& depth, uint16_t* z_mm) const;

 private:
  DepthGridShape shape_;
  DepthModel depth_;
  double edge_rel_ = 0.05;
  int width_ = 0, height_ = 0;
  std::unique_ptr<int32_t[]> pixel_;  // per cell: the distorted pixel (y * width + x), -1 outside
};

}  // namespace kestrel::core

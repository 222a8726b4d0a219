// One tracked landmark seen in one frame: what the tracker hands every
// backend (window optimizer, EKF). Lives with the tracker that produces it so
// the tracking module does not depend on the window that consumes it.
#pragma once

#include <Eigen/Core>
#include <cstdint>

namespace kestrel::core {

struct WindowObservation {
  uint32_t landmark_id = 0;
  Eigen::Vector2d uv = Eigen::Vector2d::Zero();  // undistorted pixel [px]
  double depth_m = 0.0;                          // 0 = none
  float sigma_px = 1.0f;                         // <= 0: the consumer's default (WindowOptions::pixel_sigma)
};

}  // namespace kestrel::core

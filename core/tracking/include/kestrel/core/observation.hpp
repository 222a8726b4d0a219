// What the tracker hands the back ends, and what the map hands back. Lives
// with the tracker that produces it so the tracking module does not depend on
// the window, the map or the EKF that consume it.
#pragma once

#include <Eigen/Core>
#include <cstdint>

#include "kestrel/core/orb.hpp"

namespace kestrel::core {

// One tracked landmark seen in one frame.
struct WindowObservation {
  uint32_t landmark_id = 0;
  Eigen::Vector2d uv = Eigen::Vector2d::Zero();  // undistorted pixel [px]
  double depth_m = 0.0;                          // 0 = none
  float sigma_px = 1.0f;                         // <= 0: the consumer's default (WindowOptions::pixel_sigma)
  // The landmark is a point of the map, refined by local bundle adjustment:
  // its position in W (the odometry frame) and 1-sigma [m]. 0: not a map
  // point (the window estimates it from the frames alone). docs/map.md.
  float map_sigma_m = 0.0f;
  Eigen::Vector3d map_p_W = Eigen::Vector3d::Zero();
};

// One feature of a keyframe, as the tracker hands it to the map.
struct KeyframeFeature {
  float x_px = 0, y_px = 0;  // keypoint, distorted (where the descriptor was taken)
  float u_px = 0, v_px = 0;  // undistorted
  float depth_m = 0;         // 0: none
  int16_t level = 0;
  uint32_t landmark_id = 0;  // the tracker's persistent id; 0: none
  OrbDescriptor desc{};
};

// A map point as the map hands it to the tracker's local map: a position in
// W (the odometry frame) and what it looks like.
struct MapPointUpdate {
  uint32_t landmark_id = 0;
  int16_t level = 0;
  float sigma_m = 0.0f;  // 1-sigma of the position [m]
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
  OrbDescriptor desc{};
};

}  // namespace kestrel::core

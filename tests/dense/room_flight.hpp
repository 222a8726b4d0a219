// One frame of a flight through the rendered room (dense_room.hpp) handed to
// the dense map's thread the way the estimator thread hands it over
// (test_dense_live, test_dense_query).
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <vector>

#include "dense_room.hpp"
#include "kestrel/dense/dense_mapper.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/tools/sim_render.hpp"

namespace kestrel::dense_test {

// Renders frame f at its true pose, then passes the map's correction (alignment
// 1 and C_loop once the loop closed, identity before) and the frame at its
// odometry pose. Returns the heap allocations those two calls made.
inline uint64_t hand_frame(dense::DenseMapper& m, tools::Renderer& render, const Rig& r, int f,
                           const Eigen::Isometry3d& T_true, const Eigen::Isometry3d& T_odom, bool loop,
                           const Eigen::Isometry3d& C_loop, std::vector<uint8_t>& rgb,
                           std::vector<uint16_t>& depth) {
  render.render(T_true, static_cast<uint64_t>(f), rgb.data(), depth.data());
  const ImageView dv{r.rgb.width, r.rgb.height, 2 * r.rgb.width, PixelFormat::kDepthU16,
                     reinterpret_cast<const uint8_t*>(depth.data())};
  const ImageView cv{r.rgb.width, r.rgb.height, 3 * r.rgb.width, PixelFormat::kRgb8, rgb.data()};
  const uint64_t a0 = rt::alloc_count_this_thread();
  m.note_correction(room_frame_t_ns(f), loop ? 1 : 0, loop ? C_loop : Eigen::Isometry3d::Identity());
  m.offer(room_frame_t_ns(f), cv, dv, T_odom);
  return rt::alloc_count_this_thread() - a0;
}

}  // namespace kestrel::dense_test

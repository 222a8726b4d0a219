// The simulator's world (a textured room with clutter) and a CPU ray caster
// that renders it into colour + registered depth, as an RGB-D camera would.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/msgs.hpp"
#include "kestrel/tools/sim_trajectory.hpp"

namespace kestrel::tools {

// An upright box turned by yaw about its vertical axis.
struct SceneBox {
  Eigen::Vector3d center_W = Eigen::Vector3d::Zero();
  Eigen::Vector3d half_m = Eigen::Vector3d::Constant(0.5);
  double yaw_rad = 0.0;
};

// A vertical cylinder standing on z0, up to z1.
struct SceneCylinder {
  Eigen::Vector2d center_W = Eigen::Vector2d::Zero();
  double radius_m = 0.2;
  double z0_m = 0.0;
  double z1_m = 1.0;
};

struct SceneOptions {
  double margin_m = 2.0;             // room walls this far outside the path's bounding box...
  double min_margin_m = 1.2;         // ...or less, down to this, to keep the far wall within
  double max_wall_distance_m = 5.0;  // this of the path
  double min_room_m = 5.0;           // the floor at least this long on each side
  double min_height_m = 3.0;         // floor to ceiling
  double clearance_m = 0.5;          // clutter never comes closer to the body or camera path
  double clutter_per_m2 = 0.4;       // objects per square metre of floor
  int max_clutter = 150;
};

struct Scene {
  // Axis-aligned room; the camera is always inside it. Floor z = room.min().z().
  Eigen::AlignedBox3d room{Eigen::Vector3d(-2.5, -2.5, 0.0), Eigen::Vector3d(2.5, 2.5, 3.0)};
  std::vector<SceneBox> boxes;
  std::vector<SceneCylinder> cylinders;

  // Distance from p to the nearest clutter object (0 inside one); +inf without clutter.
  double clutter_distance(const Eigen::Vector3d& p_W) const;
  // Room sized around the body and camera path (sampled at 50 Hz) and
  // clutter placed from the seed, never within clearance_m of that path.
  static Scene build(const MotionModel& trajectory, const Eigen::Isometry3d& T_BC, uint64_t seed,
                     const SceneOptions& options = SceneOptions{});
};

struct RenderOptions {
  int threads = 2;                  // render bands in parallel (the caller's thread is one of them)
  bool depth_noise = true;          // sigma(z) = DepthModel::sigma_coeff_per_m * z^2
  double dropout_fraction = 0.003;  // share of depth pixels lost in small blobs
  double image_noise_sigma = 1.0;   // colour noise, 8-bit DN per channel; 0 = off
  double max_incidence_deg = 75.0;  // no depth on surfaces seen more obliquely
  std::string texture_path;         // optional image (OpenCV imread) for the room's walls, floor, ceiling
  double texture_size_m = 2.0;      // width of one tile of that image in the world
  // A room face drawn as bare paint (a low-texture wall): 0..5 = -x, +x, -y,
  // +y, floor, ceiling; -1 = none.
  int bare_surface = -1;
  uint64_t seed = 1;
};

// Pinhole + radial-tangential distortion (k1 k2 p1 p2 k3), as OpenCV/Kalibr.
Eigen::Vector2d distort_normalized(const CameraIntrinsics& cam, const Eigen::Vector2d& xy);
// Inverse of distort_normalized by Newton iterations.
Eigen::Vector2d undistort_normalized(const CameraIntrinsics& cam, const Eigen::Vector2d& xy_d);
// Pixel of a point in camera coordinates (z > 0).
Eigen::Vector2d project(const CameraIntrinsics& cam, const Eigen::Vector3d& p_C);

class Renderer {
 public:
  // Throws std::invalid_argument for an unsupported camera and
  // std::runtime_error when the texture file cannot be read.
  Renderer(const Scene& scene, const CameraIntrinsics& camera, const DepthModel& depth,
           const RenderOptions& options);
  ~Renderer();
  Renderer(const Renderer&) = delete;
  Renderer& operator=(const Renderer&) = delete;

  // Renders the view of camera pose T_WC. rgb: width*height*3 bytes (R G B);
  // depth: width*height values in DepthModel units, 0 = no depth. Pixel noise
  // and dropouts are a function of (seed, frame_index) only, so any thread
  // count gives the same image. One call at a time per Renderer (it keeps
  // per-frame culling lists); the parallelism is inside.
  void render(const Eigen::Isometry3d& T_WC, uint64_t frame_index, uint8_t* rgb, uint16_t* depth) const;

  // Distance along the unit ray to the first surface (room or clutter).
  double cast(const Eigen::Vector3d& origin_W, const Eigen::Vector3d& dir_W) const;

  // Viewing ray of pixel (u, v) in camera coordinates, normalised to z = 1.
  Eigen::Vector3d pixel_ray(int u, int v) const;

  const CameraIntrinsics& camera() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace kestrel::tools

// Depth registration: a depth image of a separate depth camera re-projected
// into the colour camera (docs/datasets.md, "Depth registration").
//
// Every valid depth pixel is back-projected with the depth camera's
// intrinsics (distortion included, through a ray table built once), moved
// into the colour camera by T_CD, projected with the colour intrinsics and
// written where it lands unless a nearer point is there already (a z-buffer:
// where the two cameras see different surfaces, the one in front wins).
// Colour pixels nothing lands on stay 0 (invalid): the parts of the scene
// the depth camera does not see, and the colour image's border beyond the
// depth camera's field of view. When the colour camera has the finer pixel
// grid (its focal length is larger) each point covers a square of colour
// pixels instead of one, so the grid's spacing leaves no holes.
//
// Memory is sized at construction; register_into() makes no heap allocation
// and may run on a driver thread.
#pragma once

#include <cstdint>
#include <memory>

#include "kestrel/msgs.hpp"

namespace kestrel::drivers {

struct RegistrationStats {
  int valid_in = 0;   // depth pixels with a reading
  int projected = 0;  // of those, landing inside the colour image in front of it
  int occluded = 0;   // writes that met another point on the same pixel (the farther one lost)
  int valid_out = 0;  // colour pixels with a registered depth
};

class DepthRegistration {
 public:
  // depth_camera.present must hold; scale_m_per_unit: metres per depth unit
  // (Rig::depth). Throws std::invalid_argument naming what is unusable.
  DepthRegistration(const DepthCamera& depth_camera, const CameraIntrinsics& colour, double scale_m_per_unit);
  ~DepthRegistration();
  DepthRegistration(const DepthRegistration&) = delete;
  DepthRegistration& operator=(const DepthRegistration&) = delete;

  int depth_width() const { return dw_; }
  int depth_height() const { return dh_; }
  int colour_width() const { return cw_; }
  int colour_height() const { return ch_; }
  // Side of the square of colour pixels one depth point covers (1 unless the
  // colour camera resolves finer than the depth camera).
  int footprint_px() const { return footprint_; }

  // depth: DepthU16 of the depth camera's size (any stride); out: the colour
  // camera's size, out_stride_bytes per row, same depth units as the input
  // (0 = invalid). False, out untouched, when the input does not match.
  bool register_into(const ImageView& depth, uint16_t* out, int out_stride_bytes,
                     RegistrationStats* stats = nullptr) const;

 private:
  int dw_ = 0, dh_ = 0, cw_ = 0, ch_ = 0;
  int footprint_ = 1;
  CameraIntrinsics colour_;
  double R_[9] = {};
  double t_[3] = {};              // in depth units
  std::unique_ptr<float[]> ray_;  // undistorted (x/z, y/z) per depth pixel
};

}  // namespace kestrel::drivers

// Rectification of a stereo pair, computed once at start-up.
//
// The rig's left camera (Rig::rgb, T_BC) and right camera (Rig::stereo) are
// rotated onto a common image plane so that a point lies on the same row in
// both images (OpenCV stereoRectify / fisheye::stereoRectify, zero disparity
// at infinity, only valid pixels kept). rectified_rig() is the rig the
// estimator then sees: a pinhole left camera without distortion, T_BC the
// rectified left camera -> body, stereo.rectified with the baseline. Each
// frame's pair is remapped with fixed-point maps into buffers allocated here,
// so rectify() makes no heap allocation.
#pragma once

#include <cstdint>
#include <memory>

#include "kestrel/msgs.hpp"

namespace kestrel::drivers {

class StereoRectifier {
 public:
  // Throws std::invalid_argument naming the field when the rig has no stereo
  // pair or the pair cannot be rectified.
  explicit StereoRectifier(const Rig& rig);
  ~StereoRectifier();
  StereoRectifier(const StereoRectifier&) = delete;
  StereoRectifier& operator=(const StereoRectifier&) = delete;

  // Depth model left as the input rig's: the caller sets the stereo one
  // (core::stereo_depth_model) with its matcher's options.
  const Rig& rectified_rig() const { return rectified_; }

  // Raw left (and right, data == nullptr when missing) images, kGray8, kRgb8
  // or kBgr8 at the calibrated size. Writes views of the rectified grey
  // images, valid until the next call; *right_out has data == nullptr when
  // the right image is missing or refused. False when the left image is
  // refused (wrong size or format).
  bool rectify(const ImageView& left, const ImageView& right, ImageView* left_out, ImageView* right_out);

  uint64_t refused_images() const { return refused_; }

  // Whether the remap reads eight pixels at a time (AVX2, where the CPU has
  // it; the default). Off runs the scalar loop, which computes the same bytes:
  // for tests that hold the two to each other and for benches.
  bool vector_path() const;
  void set_vector_path(bool enabled);

 private:
  struct Impl;
  Rig rectified_;
  std::unique_ptr<Impl> impl_;
  uint64_t refused_ = 0;
};

}  // namespace kestrel::drivers

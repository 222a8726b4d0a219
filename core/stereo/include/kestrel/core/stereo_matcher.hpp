// Depth for features from a rectified stereo pair: the row search of paper 000.
//
// Each left keypoint's patch is compared by the sum of absolute differences
// along its row of the right image, over the disparities the options allow;
// a unique minimum is refined to sub-pixel by a parabola through its two
// neighbours. The images are rectified (drivers/stereo), so a match lies on
// the same row; z = f * b / d. Fixed memory: nothing allocates after the
// constructor, so the tracker calls it on the tracking thread.
#pragma once

#include <cstdint>
#include <string>

#include "kestrel/msgs.hpp"

namespace kestrel::core {

struct StereoMatchOptions {
  // Disparity range searched. The largest sets the nearest depth
  // (z_min = f b / max), the smallest the farthest (z_max = f b / min).
  double min_disparity_px = 2.0;
  double max_disparity_px = 96.0;
  // Patch: 16 columns (the vector width) by 2 * patch_half_rows_px + 1 rows.
  int patch_half_rows_px = 4;
  // The best SAD must beat every shift more than one pixel away by this
  // factor (OpenCV's uniquenessRatio 15 % is 1 / 1.15 = 0.87).
  double uniqueness_ratio = 0.85;
  // Mean absolute difference per pixel of the best match [grey levels]; above: no match.
  double max_mean_abs_diff = 20.0;
  // 1-sigma of a matched disparity [px]: the depth noise sigma_z = z^2 * this / (f b).
  double disparity_sigma_px = 0.5;

  [[nodiscard]] std::string validate() const;
};

// The depth model stereo gives a rig with focal length f_px and baseline b:
// the range the disparity search covers, and sigma(z) = z^2 * sigma_d / (f b)
// in the DepthModel's form sigma_coeff_per_m * z^2.
DepthModel stereo_depth_model(double f_px, double baseline_m, const StereoMatchOptions& opt);

struct StereoMatchStats {
  int searched = 0;  // keypoints whose patch and at least one disparity fit in the images
  int matched = 0;   // with a unique, good-enough match
};

class StereoMatcher {
 public:
  explicit StereoMatcher(const StereoMatchOptions& opt = {});

  // left, right: rectified kGray8 images of one size. x_px, y_px: n left
  // keypoints (level-0 pixels). Writes disparity_px[i] > 0 for a match, 0
  // for none. Returns false (all zero) when the images do not fit.
  bool match(const ImageView& left, const ImageView& right, const float* x_px, const float* y_px, int n,
             float* disparity_px, StereoMatchStats* stats = nullptr) const;

  const StereoMatchOptions& options() const { return opt_; }

  // For tests and the bench: the scalar SAD loop instead of the vector one.
  static void set_vector_path(bool on);

 private:
  StereoMatchOptions opt_;
};

}  // namespace kestrel::core

// Pixel conversions that both the drivers (stereo rectification) and the
// estimator (ORB on colour input) run on the tracking thread, kept beside the
// message types they read so neither side includes the other.
#pragma once

#include <cstdint>

#include "kestrel/msgs.hpp"

namespace kestrel {

// BT.601 luma in 8-bit fixed point, (77 R + 150 G + 29 B + 128) >> 8, of one
// row of `width` packed RGB (or BGR when `bgr`) pixels. Uses AVX2 where the CPU
// has it (chosen once at load time); the result is the same on every path.
void luma_row(const uint8_t* rgb, uint8_t* grey, int width, bool bgr) noexcept;

// The grey plane of a kRgb8/kBgr8 view into `grey`, rows `grey_stride` bytes
// apart. False (nothing written) for any other format or an empty view.
bool luma_plane(const ImageView& colour, uint8_t* grey, int grey_stride) noexcept;

// Whether luma_row runs its AVX2 path on this CPU (for benches and tests).
bool luma_row_is_vectorised() noexcept;

}  // namespace kestrel

// The stages of OrbExtractor as free functions over caller-owned buffers, so
// unit tests can check each against a hand-built image (FAST on a rectangle,
// orientation of a rotated patch, steering of the descriptor). None allocates.
// Not a stable API: OrbExtractor (orb.hpp) is what the tracker uses.
#pragma once

#include <array>
#include <cstdint>

#include "kestrel/core/orb.hpp"

namespace kestrel::core::orb_detail {

constexpr int kPatchRadius = 15;    // orientation patch (circular), as in ORB
constexpr int kPatternRadius = 13;  // every BRIEF test point lies in this disc
constexpr int kPatchDiameter = 2 * kPatchRadius + 1;
constexpr int kBriefPairs = 256;
constexpr int kBlurRadius = 3;  // 7x7 Gaussian, sigma 2

struct Plane {
  const uint8_t* data = nullptr;
  int width = 0;
  int height = 0;
  int stride = 0;  // bytes between rows
  const uint8_t* at(int x, int y) const { return data + static_cast<std::ptrdiff_t>(y) * stride + x; }
};
struct MutPlane {
  uint8_t* data = nullptr;
  int width = 0;
  int height = 0;
  int stride = 0;
  uint8_t* at(int x, int y) const { return data + static_cast<std::ptrdiff_t>(y) * stride + x; }
  Plane view() const { return Plane{data, width, height, stride}; }
};

// ---- FAST-9 -----------------------------------------------------------------
// Byte offsets of the 16-pixel Bresenham circle of radius 3, clockwise from
// (0, -3) in image axes.
std::array<int, 16> fast_circle_offsets(int stride);
// Largest t for which `p` is a FAST-9 corner at threshold t (9 contiguous
// circle pixels all brighter than I_p + t, or all darker than I_p - t), or -1
// when it is not a corner even at t = 0. "Corner at threshold t" <=> score >= t.
int fast_score(const uint8_t* p, const std::array<int, 16>& offsets);

// ---- pyramid / smoothing ------------------------------------------------------
// Area ("box") resampling src -> dst (dst no larger than src, ratio <= 2 per
// axis, both at least 3 pixels): each output pixel is the mean of the input
// area it covers, with fractional weights at its edges (8-bit fixed point).
// tmp: src.width bytes; xtab/ytab: dst.width and dst.height entries.
struct AreaTap {
  int32_t first = 0;            // first input index
  std::array<uint16_t, 3> w{};  // weights of first, first+1, first+2 (sum 256)
};
// tmp: area_resize_tmp_bytes(src.width, dst.width) bytes (the vector path's
// 16-row block, its transpose and the transposed output); xtab: dst.width
// entries, ytab: dst.height.
void area_resize(Plane src, MutPlane dst, uint8_t* tmp, AreaTap* xtab, AreaTap* ytab);
std::size_t area_resize_tmp_bytes(int src_width, int dst_width);

// 7x7 Gaussian, sigma 2, separable, 8-bit fixed point, borders replicated.
// tmp: src.width * src.height bytes.
void gaussian_blur7(Plane src, MutPlane dst, uint8_t* tmp);
std::array<uint16_t, 2 * kBlurRadius + 1> gaussian_kernel7();  // integer weights, sum 256
// The blurred square BRIEF reads around (cx, cy): gaussian_blur7's values on
// [cx - kPatternRadius, cx + kPatternRadius] x [cy - kPatternRadius, cy + kPatternRadius],
// into out (kBriefPatchSide^2 bytes, row-major), bit for bit. With a few hundred
// keypoints this is a fraction of blurring the whole level. (cx, cy) must be
// at least kBriefPatchMargin pixels inside the image; tmp: kBriefPatchSide *
// (kBriefPatchSide + 2 * kBlurRadius) bytes.
constexpr int kBriefPatchSide = 2 * kPatternRadius + 1;
constexpr int kBriefPatchMargin = kPatternRadius + kBlurRadius;
void gaussian_blur7_patch(Plane src, int cx, int cy, uint8_t* out, uint8_t* tmp);

// ---- orientation ---------------------------------------------------------------
// umax[v] = half-width of the circular patch at row offset v (0..15); the disc
// u^2 + v^2 <= r^2 + r is symmetric under u <-> v, so a 90 degree rotation of
// the image maps the patch onto itself exactly.
std::array<int, kPatchRadius + 1> patch_umax();
// Intensity-centroid angle (Rosin) around (x, y): atan2(m01, m10) in [0, 2pi).
// (x, y) must be at least kPatchRadius + 1 pixels inside the image (the vector
// path reads one column beyond the disc on the right).
float ic_angle(Plane img, int x, int y, const std::array<int, kPatchRadius + 1>& umax);

// ---- steered BRIEF --------------------------------------------------------------
// Test point pairs (ax, ay, bx, by), generated once from `seed`: coordinates
// i.i.d. Gaussian with sigma = 31/5 (BRIEF's "G II"), rejected outside the disc
// of radius kPatternRadius so any rotation keeps them inside the patch.
using BriefPattern = std::array<std::array<int8_t, 4>, kBriefPairs>;
BriefPattern make_brief_pattern(uint64_t seed);
// Descriptor at (x, y) of the blurred image with the pattern rotated by angle.
// (x, y) must be at least kPatternRadius + 1 pixels inside the image.
OrbDescriptor brief_describe(Plane blurred, int x, int y, float angle_rad, const BriefPattern& pattern);
// The pattern's test points as floats, in the order brief_describe rotates
// them (a and b of pair 0, of pair 1, ...): made once per extractor, so each
// keypoint loads them as vectors instead of converting 512 bytes.
struct BriefPoints {
  alignas(16) std::array<float, 2 * kBriefPairs> x{};
  alignas(16) std::array<float, 2 * kBriefPairs> y{};
};
BriefPoints brief_points(const BriefPattern& pattern);
OrbDescriptor brief_describe(Plane blurred, int x, int y, float angle_rad, const BriefPoints& points);

// The vector paths (SSE2 on x86-64, NEON on AArch64; core/features simd.hpp).
// On by default where the target has them; tests switch them off to hold them
// to the scalar reference, which must give bit-identical features. Process-wide:
// a test hook, not a tunable.
bool vector_paths();
void set_vector_paths(bool on);
const char* vector_isa();  // "SSE2", "NEON", or "none" (scalar only)

}  // namespace kestrel::core::orb_detail

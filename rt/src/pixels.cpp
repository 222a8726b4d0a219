#include "kestrel/pixels.hpp"

#include <cstddef>

namespace kestrel {
namespace {

// The loop is written once per path so each compiles on its own terms: GCC
// only vectorises the three-channel de-interleave with SSSE3 or better and its
// dynamic cost model (docs/stereo.md has the gain), which the portable -O2 build lacks.
// clang-format off
#define KESTREL_LUMA_LOOP                                                                              \
  for (int x = 0; x < width; ++x)                                                                     \
    grey[x] = static_cast<uint8_t>((wr * rgb[3 * x] + 150 * rgb[3 * x + 1] + wb * rgb[3 * x + 2] + 128) >> 8)
// clang-format on

using RowFn = void (*)(const uint8_t* __restrict, uint8_t* __restrict, int, int, int);

// AArch64's NEON de-interleaves three channels in one load (ld3), so there the
// portable loop vectorises too once the cost model lets it.
#if defined(__aarch64__) && defined(__GNUC__) && !defined(__clang__)
__attribute__((optimize("tree-vectorize", "vect-cost-model=dynamic")))
#endif
void luma_row_portable(const uint8_t* __restrict rgb, uint8_t* __restrict grey, int width, int wr,
                       int wb) noexcept {
  KESTREL_LUMA_LOOP;
}

#if defined(__x86_64__) && defined(__GNUC__)
#if defined(__clang__)
#define KESTREL_VECTORISE __attribute__((target("avx2")))
#else
#define KESTREL_VECTORISE \
  __attribute__((target("avx2"), optimize("tree-vectorize", "vect-cost-model=dynamic")))
#endif
KESTREL_VECTORISE void luma_row_avx2(const uint8_t* __restrict rgb, uint8_t* __restrict grey, int width,
                                     int wr, int wb) noexcept {
  KESTREL_LUMA_LOOP;
}
bool cpu_has_avx2() noexcept {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2") != 0;
}
const bool kVectorised = cpu_has_avx2();
const RowFn kRow = kVectorised ? luma_row_avx2 : luma_row_portable;
#else
const bool kVectorised = false;
const RowFn kRow = luma_row_portable;
#endif

}  // namespace

void luma_row(const uint8_t* rgb, uint8_t* grey, int width, bool bgr) noexcept {
  kRow(rgb, grey, width, bgr ? 29 : 77, bgr ? 77 : 29);
}

bool luma_plane(const ImageView& colour, uint8_t* grey, int grey_stride) noexcept {
  if (colour.data == nullptr || colour.width <= 0 || colour.height <= 0) return false;
  if (colour.format != PixelFormat::kRgb8 && colour.format != PixelFormat::kBgr8) return false;
  const bool bgr = colour.format == PixelFormat::kBgr8;
  for (int y = 0; y < colour.height; ++y) {
    luma_row(colour.data + static_cast<std::ptrdiff_t>(y) * colour.stride_bytes,
             grey + static_cast<std::ptrdiff_t>(y) * grey_stride, colour.width, bgr);
  }
  return true;
}

bool luma_row_is_vectorised() noexcept { return kVectorised; }

}  // namespace kestrel

// rt/src/pixels.cpp: the luma conversion on its dispatched path (AVX2 where
// the CPU has it) against the BT.601 fixed-point formula, pixel by pixel.
#include <gtest/gtest.h>

#include <cstdint>
#include <cstdio>
#include <random>
#include <vector>

#include "kestrel/pixels.hpp"

namespace kestrel {
namespace {

uint8_t luma(int r, int g, int b) { return static_cast<uint8_t>((77 * r + 150 * g + 29 * b + 128) >> 8); }

TEST(Pixels, LumaRowIsTheFormulaAtEveryWidthAndOrder) {
  std::printf("[ figure ] luma_row vectorised: %s\n", luma_row_is_vectorised() ? "yes (AVX2)" : "no");
  std::mt19937 rng(7);
  std::uniform_int_distribution<int> byte(0, 255);
  for (int width : {1, 2, 7, 15, 16, 17, 31, 32, 33, 63, 64, 65, 640, 643}) {
    // One spare byte on either side of the output proves the row writes exactly `width` bytes.
    std::vector<uint8_t> rgb(static_cast<size_t>(width) * 3), grey(static_cast<size_t>(width) + 2, 0xAB);
    for (auto& v : rgb) v = static_cast<uint8_t>(byte(rng));
    for (bool bgr : {false, true}) {
      luma_row(rgb.data(), grey.data() + 1, width, bgr);
      for (int x = 0; x < width; ++x) {
        const uint8_t* p = &rgb[static_cast<size_t>(x) * 3];
        const uint8_t want = bgr ? luma(p[2], p[1], p[0]) : luma(p[0], p[1], p[2]);
        ASSERT_EQ(grey[static_cast<size_t>(x) + 1], want)
            << "width " << width << " x " << x << " bgr " << bgr;
      }
      EXPECT_EQ(grey.front(), 0xAB);
      EXPECT_EQ(grey.back(), 0xAB);
    }
  }
  // The extremes: white stays white (77 + 150 + 29 = 256), black black.
  const uint8_t white[3] = {255, 255, 255}, black[3] = {0, 0, 0};
  uint8_t out = 0;
  luma_row(white, &out, 1, false);
  EXPECT_EQ(out, 255);
  luma_row(black, &out, 1, true);
  EXPECT_EQ(out, 0);
}

TEST(Pixels, LumaPlaneFollowsBothStridesAndRefusesOtherFormats) {
  const int w = 37, h = 5, in_stride = 37 * 3 + 5, out_stride = 40;
  std::vector<uint8_t> rgb(static_cast<size_t>(in_stride) * h),
      grey(static_cast<size_t>(out_stride) * h, 0xCD);
  for (size_t i = 0; i < rgb.size(); ++i) rgb[i] = static_cast<uint8_t>(i * 37 + 11);
  ASSERT_TRUE(luma_plane({w, h, in_stride, PixelFormat::kBgr8, rgb.data()}, grey.data(), out_stride));
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const uint8_t* p = &rgb[static_cast<size_t>(y) * in_stride + static_cast<size_t>(x) * 3];
      ASSERT_EQ(grey[static_cast<size_t>(y) * out_stride + x], luma(p[2], p[1], p[0]));
    }
    for (int x = w; x < out_stride; ++x) EXPECT_EQ(grey[static_cast<size_t>(y) * out_stride + x], 0xCD);
  }
  EXPECT_FALSE(luma_plane({w, h, w, PixelFormat::kGray8, rgb.data()}, grey.data(), out_stride));
  EXPECT_FALSE(luma_plane({w, h, w * 2, PixelFormat::kYuyv, rgb.data()}, grey.data(), out_stride));
  EXPECT_FALSE(luma_plane({w, h, in_stride, PixelFormat::kRgb8, nullptr}, grey.data(), out_stride));
}

}  // namespace
}  // namespace kestrel

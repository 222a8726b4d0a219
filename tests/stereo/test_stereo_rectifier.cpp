// drivers/stereo/stereo_rectifier.cpp: a fisheye pair, and the remap against
// cv::remap on OpenCV's own maps, its vector path against its scalar path byte
// for byte, and its reads held inside the image by guard pages. (Refusals, the
// EuRoC pair and the pass-through are in test_stereo_euroc.cpp.)
#include <gtest/gtest.h>
#include <sys/mman.h>
#include <unistd.h>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <vector>

#include "kestrel/drivers/stereo_rectifier.hpp"

namespace kestrel {
namespace {

// A VI-Sensor-like pair (EuRoC's cam0/cam1 intrinsics, their strong barrel
// distortion, a slightly turned right camera 11 cm along x) at any size.
Rig radtan_rig(int w, int h) {
  Rig rig;
  const double sx = w / 752.0, sy = h / 480.0;
  rig.rgb = CameraIntrinsics{w,
                             h,
                             458.654 * sx,
                             457.296 * sy,
                             367.215 * sx,
                             248.375 * sy,
                             DistortionModel::kRadTan,
                             {-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0}};
  rig.stereo.present = true;
  rig.stereo.intrinsics = CameraIntrinsics{w,
                                           h,
                                           457.587 * sx,
                                           456.134 * sy,
                                           379.999 * sx,
                                           255.238 * sy,
                                           DistortionModel::kRadTan,
                                           {-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05, 0}};
  // T_BC1 = T_BC * (rotation of 0.4 degrees about y and 0.2 about z, then 0.11 m along x).
  const double a = 0.4 * M_PI / 180, b = 0.2 * M_PI / 180;
  rig.stereo.T_BC1 = {std::cos(a) * std::cos(b),
                      -std::sin(b),
                      std::sin(a),
                      0.11,
                      std::sin(b),
                      std::cos(b),
                      0,
                      0.001,
                      -std::sin(a),
                      0,
                      std::cos(a),
                      0.0005,
                      0,
                      0,
                      0,
                      1};
  return rig;
}

Rig fisheye_rig() {
  // TUM-VI's two cameras, roughly: equidistant k1..k4, equal focal lengths.
  auto cam = [](double f, double cx, double cy, double k2) {
    return CameraIntrinsics{
        512, 512, f, f, cx, cy, DistortionModel::kEquidistant, {0.0034, k2, -0.0020, 0.0002, 0}};
  };
  Rig rig;
  rig.rgb = cam(190.98, 254.93, 256.90, 0.0007);
  rig.stereo.present = true;
  rig.stereo.intrinsics = cam(190.44, 252.60, 254.92, 0.0008);
  rig.stereo.T_BC1 = kIdentity4;
  rig.stereo.T_BC1[3] = 0.101;
  return rig;
}

// OpenCV's maps for the rig, computed as the rectifier documents it does (stereoRectify with
// alpha 0 or fisheye::stereoRectify with balance 0, then initUndistortRectifyMap).
void opencv_maps(const Rig& rig, cv::Mat* lx, cv::Mat* ly, cv::Mat* rx, cv::Mat* ry) {
  auto K = [](const CameraIntrinsics& k) { return cv::Matx33d(k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1); };
  const bool fisheye = rig.rgb.distortion == DistortionModel::kEquidistant;
  auto D = [&](const CameraIntrinsics& k) {
    cv::Mat d(fisheye ? 4 : 5, 1, CV_64F);
    for (int i = 0; i < d.rows; ++i) d.at<double>(i) = k.dist[static_cast<size_t>(i)];
    return d;
  };

  cv::Matx44d T_BC0, T_BC1;
  for (int i = 0; i < 16; ++i) T_BC0.val[i] = rig.T_BC[static_cast<size_t>(i)];
  for (int i = 0; i < 16; ++i) T_BC1.val[i] = rig.stereo.T_BC1[static_cast<size_t>(i)];
  const cv::Matx44d T_C1C0 = T_BC1.inv() * T_BC0;
  cv::Matx33d R;
  cv::Vec3d t;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) R(r, c) = T_C1C0(r, c);
    t[r] = T_C1C0(r, 3);
  }
  const cv::Size size(rig.rgb.width, rig.rgb.height);
  cv::Mat R0, R1, P0, P1, Q;
  const CameraIntrinsics &k0 = rig.rgb, &k1 = rig.stereo.intrinsics;
  if (fisheye) {
    cv::fisheye::stereoRectify(K(k0), D(k0), K(k1), D(k1), size, R, t, R0, R1, P0, P1, Q,
                               cv::CALIB_ZERO_DISPARITY, size, 0.0, 1.0);
    cv::fisheye::initUndistortRectifyMap(K(k0), D(k0), R0, P0(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, *lx,
                                         *ly);
    cv::fisheye::initUndistortRectifyMap(K(k1), D(k1), R1, P1(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, *rx,
                                         *ry);
  } else {
    cv::stereoRectify(K(k0), D(k0), K(k1), D(k1), size, R, t, R0, R1, P0, P1, Q, cv::CALIB_ZERO_DISPARITY,
                      0.0, size);
    cv::initUndistortRectifyMap(K(k0), D(k0), R0, P0(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, *lx, *ly);
    cv::initUndistortRectifyMap(K(k1), D(k1), R1, P1(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, *rx, *ry);
  }
}

// A textured image with structure at several scales (noise blurred at 1.5 px, plus edges).
cv::Mat texture(int w, int h, unsigned seed) {
  cv::Mat m(h, w, CV_8U);
  cv::theRNG().state = seed;
  cv::randu(m, 0, 256);
  cv::GaussianBlur(m, m, cv::Size(0, 0), 1.5);
  cv::normalize(m, m, 0, 255, cv::NORM_MINMAX);
  for (int k = 0; k < 12; ++k) {
    cv::rectangle(m, cv::Rect((k * 97) % w, (k * 53) % h, 40, 30), cv::Scalar(k % 2 ? 255 : 0), cv::FILLED);
  }
  return m;
}

ImageView view(const cv::Mat& m) {
  return ImageView{m.cols, m.rows, static_cast<int>(m.step[0]),
                   m.channels() == 3 ? PixelFormat::kRgb8 : PixelFormat::kGray8, m.data};
}

TEST(StereoRectifier, EquidistantPairRectifies) {
  // TUM-VI-like fisheye numbers (512x512, equidistant k1..k4, 10 cm baseline).
  const Rig rig = fisheye_rig();
  drivers::StereoRectifier rect(rig);
  const Rig& rr = rect.rectified_rig();
  EXPECT_NEAR(rr.stereo.baseline_m, 0.101, 1e-6);
  EXPECT_GT(rr.rgb.fx, 50);
  EXPECT_TRUE(std::isfinite(rr.rgb.cx) && std::isfinite(rr.rgb.cy));
  std::vector<uint8_t> px(512 * 512, 100);
  const ImageView v{512, 512, 512, PixelFormat::kGray8, px.data()};
  ImageView lo, ro;
  EXPECT_TRUE(rect.rectify(v, v, &lo, &ro));
  EXPECT_NE(ro.data, nullptr);
  // A wrong-size image is refused and counted, not read past its end.
  const ImageView small{256, 256, 256, PixelFormat::kGray8, px.data()};
  EXPECT_FALSE(rect.rectify(small, v, &lo, &ro));
  EXPECT_EQ(rect.refused_images(), 1u);
}

TEST(StereoRectifierRemap, AgreesWithOpenCvsRemapOnItsOwnMaps) {
  for (const Rig& rig : {radtan_rig(752, 480), fisheye_rig()}) {
    const int w = rig.rgb.width, h = rig.rgb.height;
    cv::Mat lx, ly, rx, ry;
    opencv_maps(rig, &lx, &ly, &rx, &ry);
    const cv::Mat L = texture(w, h, 1), R = texture(w, h, 2);
    cv::Mat want_l, want_r;
    cv::remap(L, want_l, lx, ly, cv::INTER_LINEAR, cv::BORDER_CONSTANT, 0);
    cv::remap(R, want_r, rx, ry, cv::INTER_LINEAR, cv::BORDER_CONSTANT, 0);
    drivers::StereoRectifier rect(rig);
    ImageView lo, ro;
    ASSERT_TRUE(rect.rectify(view(L), view(R), &lo, &ro));
    ASSERT_NE(ro.data, nullptr);
    for (int side = 0; side < 2; ++side) {
      const cv::Mat& want = side == 0 ? want_l : want_r;
      const cv::Mat &mx = side == 0 ? lx : rx, &my = side == 0 ? ly : ry;
      const uint8_t* got = side == 0 ? lo.data : ro.data;
      int worst = 0;
      double sum = 0;
      size_t n = 0, black_where_no_source = 0, no_source = 0;
      for (int y = 0; y < h; ++y) {
        for (int x = 0; x < w; ++x) {
          const float sx = mx.at<float>(y, x), sy = my.at<float>(y, x);
          const int g = got[static_cast<size_t>(y) * w + x];
          // Where the source leaves the image OpenCV blends with its border; we write black.
          if (!(sx >= 0 && sy >= 0 && sx <= w - 1 && sy <= h - 1)) {
            ++no_source;
            black_where_no_source += g == 0;
            continue;
          }
          if (sx > w - 2 || sy > h - 2) continue;  // OpenCV blends the last column/row with the border too
          const int d = std::abs(g - want.at<uint8_t>(y, x));
          worst = std::max(worst, d);
          sum += d;
          ++n;
        }
      }
      std::printf(
          "[ figure ] %s %s: |ours - cv::remap| mean %.3f, max %d grey levels over %zu px; %zu without a "
          "source\n",
          rig.rgb.distortion == DistortionModel::kEquidistant ? "equidistant" : "radtan",
          side == 0 ? "left" : "right", sum / static_cast<double>(n), worst, n, no_source);
      EXPECT_GT(n, static_cast<size_t>(w) * h * 9 / 10);
      // Both interpolate in 1/32 px steps; ours samples the map linearly along runs within 1/64 px, so a
      // weight may round one step the other way: at a black-to-white edge that is 255 / 32, 8 levels.
      EXPECT_LT(sum / static_cast<double>(n), 0.5);
      EXPECT_LE(worst, 8);
      EXPECT_EQ(black_where_no_source, no_source);
    }
  }
}

TEST(StereoRectifierRemap, VectorAndScalarPathsWriteTheSameBytes) {
  {
    drivers::StereoRectifier probe(radtan_rig(64, 48));
    if (!probe.vector_path()) {
      GTEST_SKIP() << "SKIPPED LOUDLY: this CPU has no AVX2, so the remap runs its scalar path only";
    }
  }
  std::mt19937 rng(11);
  // Odd sizes (runs and eight-pixel steps do not divide the width), a stride wider than the image, noise
  // (every weight matters), colour and grey.
  for (const Rig& rig : {radtan_rig(643, 481), radtan_rig(752, 480), fisheye_rig()}) {
    const int w = rig.rgb.width, h = rig.rgb.height;
    for (int channels : {1, 3}) {
      const int stride = w * channels + 13;
      std::vector<uint8_t> l(static_cast<size_t>(stride) * h), r(l.size());
      for (auto& v : l) v = static_cast<uint8_t>(rng());
      for (auto& v : r) v = static_cast<uint8_t>(rng());
      const PixelFormat f = channels == 3 ? PixelFormat::kBgr8 : PixelFormat::kGray8;
      const ImageView lv{w, h, stride, f, l.data()}, rv{w, h, stride, f, r.data()};
      drivers::StereoRectifier vec(rig), scalar(rig);
      scalar.set_vector_path(false);
      ASSERT_TRUE(vec.vector_path());
      ASSERT_FALSE(scalar.vector_path());
      ImageView a_l, a_r, b_l, b_r;
      ASSERT_TRUE(vec.rectify(lv, rv, &a_l, &a_r));
      ASSERT_TRUE(scalar.rectify(lv, rv, &b_l, &b_r));
      size_t differ = 0;
      for (size_t i = 0; i < static_cast<size_t>(w) * h; ++i) {
        differ += a_l.data[i] != b_l.data[i];
        differ += a_r.data[i] != b_r.data[i];
      }
      EXPECT_EQ(differ, 0u) << w << "x" << h << " channels " << channels;
    }
  }
}

// Each image sits against a page that may not be read, before its first byte and after its last: a remap
// that reads one byte outside the image (a gather at the last row, a clamp gone wrong) dies here.
TEST(StereoRectifierRemap, NeverReadsOutsideTheImage) {
  const size_t page = static_cast<size_t>(sysconf(_SC_PAGESIZE));
  for (const Rig& rig : {radtan_rig(643, 481), fisheye_rig()}) {
    const int w = rig.rgb.width, h = rig.rgb.height;
    const size_t bytes = static_cast<size_t>(w) * h;
    const size_t pages = (bytes + page - 1) / page;
    for (bool at_end : {true, false}) {
      // guard | data pages | guard
      auto* base = static_cast<uint8_t*>(
          mmap(nullptr, (pages + 2) * page, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0));
      ASSERT_NE(base, MAP_FAILED);
      ASSERT_EQ(mprotect(base, page, PROT_NONE), 0);
      ASSERT_EQ(mprotect(base + (pages + 1) * page, page, PROT_NONE), 0);
      uint8_t* img = at_end ? base + (pages + 1) * page - bytes : base + page;
      for (size_t i = 0; i < bytes; ++i) img[i] = static_cast<uint8_t>(i * 31);
      const ImageView v{w, h, w, PixelFormat::kGray8, img};
      for (bool vec : {true, false}) {
        drivers::StereoRectifier rect(rig);
        rect.set_vector_path(vec);
        ImageView lo, ro;
        EXPECT_TRUE(rect.rectify(v, v, &lo, &ro));
        EXPECT_NE(ro.data, nullptr);
      }
      munmap(base, (pages + 2) * page);
    }
  }
}

}  // namespace
}  // namespace kestrel

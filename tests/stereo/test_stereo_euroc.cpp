// Stereo on the real EuRoC V1_01 frames in ../shared/data: the reader's cam1
// (and its rows without a PNG), the rectification (rows agree after it), the
// row search against OpenCV's block matcher on the same features, calibrations
// that cannot be rectified, and allocation-free rectification.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/core/stereo_matcher.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/stereo_rectifier.hpp"
#include "kestrel/rt/alloc_counter.hpp"

namespace {

using namespace kestrel;
using drivers::LogImage;
using drivers::LogRecord;
using drivers::RecordType;

const std::string kSeq = std::string(KESTREL_SHARED_DATA) + "/euroc/V1_01_easy_first95";

bool have_data() {
  return drivers::is_euroc_folder(kSeq) && std::ifstream(kSeq + "/mav0/cam1/sensor.yaml").good();
}

#define REQUIRE_DATA() \
  if (!have_data()) GTEST_SKIP() << "SKIPPED LOUDLY: " << kSeq << " absent (../shared/data not mounted)"

// The n-th stereo pair of the log (left and right with one stamp).
bool nth_pair(drivers::LogSource& log, int n, LogImage& left, LogImage& right) {
  LogRecord r;
  LogImage pending;
  bool have_left = false;
  int k = 0;
  while (log.next(r)) {
    if (r.type == RecordType::kRgb) {
      pending = r.image;
      have_left = true;
    } else if (r.type == RecordType::kRight && have_left && r.image.t_ns == pending.t_ns) {
      if (k++ == n) {
        left = pending;
        right = r.image;
        return true;
      }
    }
  }
  return false;
}

cv::Mat as_mat(const ImageView& v) {
  return cv::Mat(v.height, v.width, CV_8UC1, const_cast<uint8_t*>(v.data),
                 static_cast<size_t>(v.stride_bytes));
}

TEST(StereoEuroc, ReaderPairsCam1AndNamesTheMissingPngs) {
  REQUIRE_DATA();
  drivers::EurocReader log(kSeq);
  const Rig& rig = log.rig();
  ASSERT_TRUE(rig.stereo.present);
  EXPECT_EQ(rig.stereo.intrinsics.width, 752);
  EXPECT_NEAR(rig.stereo.intrinsics.fx, 457.587, 1e-9);
  EXPECT_EQ(rig.stereo.intrinsics.distortion, DistortionModel::kRadTan);
  EXPECT_NEAR(rig.stereo.T_BC1[3], -0.0198435579556, 1e-12);
  EXPECT_EQ(log.rgb_count(), 95u);
  EXPECT_EQ(log.right_count(), 95u);  // 99 rows, 4 without their PNG
  int missing = 0;
  for (const auto& p : log.problems())
    if (p.kind == "missing-file" && p.where.find("cam1/data.csv:") != std::string::npos) ++missing;
  EXPECT_EQ(missing, 4);
  LogRecord r;
  int right = 0;
  while (log.next(r))
    if (r.type == RecordType::kRight) {
      ++right;
      EXPECT_EQ(r.image.format, PixelFormat::kGray8);
    }
  EXPECT_EQ(right, 95);
}

TEST(StereoEuroc, RectifiedRowsAgree) {
  REQUIRE_DATA();
  // Four pairs spread over the segment: one pair's count of false ORB matches is noise on a threshold.
  size_t raw_n = 0, raw_all = 0, rec_n = 0, rec_all = 0;
  std::vector<double> raw_dy, rec_dy;
  auto row_error = [](const cv::Mat& a, const cv::Mat& b, size_t* n, size_t* all, std::vector<double>* dy) {
    auto orb = cv::ORB::create(800);
    std::vector<cv::KeyPoint> ka, kb;
    cv::Mat da, db;
    orb->detectAndCompute(a, cv::noArray(), ka, da);
    orb->detectAndCompute(b, cv::noArray(), kb, db);
    cv::BFMatcher bf(cv::NORM_HAMMING, true);
    std::vector<cv::DMatch> m;
    bf.match(da, db, m);
    // Matches a stereo pair can hold (the right image's point left of the left one's, within 100 px and
    // 20 rows); their row difference, over those within 3 rows (the rest are false matches).
    for (const auto& x : m) {
      const cv::Point2f pa = ka[x.queryIdx].pt, pb = kb[x.trainIdx].pt;
      const double d = pa.x - pb.x, e = std::abs(pa.y - pb.y);
      if (x.distance >= 40 || d < 0 || d > 100 || e > 20) continue;
      ++*all;
      if (e <= 3) {
        ++*n;
        dy->push_back(e);
      }
    }
  };
  for (int pair : {10, 30, 50, 70}) {
    drivers::EurocReader log(kSeq);
    drivers::StereoRectifier rect(log.rig());
    const Rig& rr = rect.rectified_rig();
    EXPECT_TRUE(rr.stereo.rectified);
    EXPECT_NEAR(rr.stereo.baseline_m, 0.110, 0.002);  // the VI-Sensor's baseline
    EXPECT_EQ(rr.rgb.distortion, DistortionModel::kNone);
    LogImage l, r;
    ASSERT_TRUE(nth_pair(log, pair, l, r));
    ImageView lo, ro;
    ASSERT_TRUE(rect.rectify(l.view(), r.view(), &lo, &ro));
    ASSERT_NE(ro.data, nullptr);
    // ORB matches between the two images, cross-checked: their row difference is the rectification error.
    row_error(as_mat(l.view()), as_mat(r.view()), &raw_n, &raw_all, &raw_dy);
    row_error(as_mat(lo), as_mat(ro), &rec_n, &rec_all, &rec_dy);
  }
  auto median = [](std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v.empty() ? 1e9 : v[v.size() / 2];
  };
  std::printf(
      "[ figure ] EuRoC V1_01 pairs 10, 30, 50, 70, ORB matches: raw %zu of %zu within 3 rows, median %.2f "
      "px; "
      "rectified %zu of %zu, median %.2f px\n",
      raw_n, raw_all, median(raw_dy), rec_n, rec_all, median(rec_dy));
  ASSERT_GT(rec_n, 160u);
  EXPECT_GT(rec_n, 0.8 * rec_all) << "rectified rows disagree";
  EXPECT_LT(median(rec_dy), 0.6);
}

// The row search against cv::StereoBM on the same features of the same rectified pairs.
TEST(StereoEuroc, RowSearchAgreesWithBlockMatcher) {
  REQUIRE_DATA();
  drivers::EurocReader log(kSeq);
  drivers::StereoRectifier rect(log.rig());
  const core::StereoMatchOptions opt;
  const core::StereoMatcher ours(opt);
  auto bm = cv::StereoBM::create(96, 11);
  bm->setMinDisparity(0);
  bm->setUniquenessRatio(15);
  bm->setTextureThreshold(10);
  int both = 0, agree = 0, ours_only = 0, bm_only = 0, total = 0;
  double t_ours_ms = 0, t_bm_ms = 0;
  int pairs = 0;
  for (int n = 0; n < 90; n += 15) {
    log.rewind();
    LogImage l, r;
    ASSERT_TRUE(nth_pair(log, n, l, r));
    ImageView lo, ro;
    ASSERT_TRUE(rect.rectify(l.view(), r.view(), &lo, &ro));
    const cv::Mat L = as_mat(lo).clone(), R = as_mat(ro).clone();
    std::vector<cv::KeyPoint> kp;
    cv::FAST(L, kp, 20, true);
    cv::KeyPointsFilter::retainBest(kp, 300);
    std::vector<float> x, y, d(kp.size());
    for (const auto& k : kp) x.push_back(k.pt.x), y.push_back(k.pt.y);
    const ImageView lv{L.cols, L.rows, static_cast<int>(L.step[0]), PixelFormat::kGray8, L.data};
    const ImageView rv{R.cols, R.rows, static_cast<int>(R.step[0]), PixelFormat::kGray8, R.data};
    auto t0 = std::chrono::steady_clock::now();
    ours.match(lv, rv, x.data(), y.data(), static_cast<int>(x.size()), d.data());
    auto t1 = std::chrono::steady_clock::now();
    cv::Mat disp;
    bm->compute(L, R, disp);
    auto t2 = std::chrono::steady_clock::now();
    t_ours_ms += std::chrono::duration<double, std::milli>(t1 - t0).count();
    t_bm_ms += std::chrono::duration<double, std::milli>(t2 - t1).count();
    ++pairs;
    for (size_t i = 0; i < kp.size(); ++i) {
      const int xi = static_cast<int>(std::lround(x[i])), yi = static_cast<int>(std::lround(y[i]));
      const short raw = disp.at<short>(yi, xi);
      const double dbm = raw > 0 ? raw / 16.0 : 0.0;  // StereoBM: fixed point, 4 fractional bits
      const bool b_ok = dbm >= opt.min_disparity_px, o_ok = d[i] > 0;
      ++total;
      if (b_ok && o_ok) {
        ++both;
        if (std::abs(dbm - d[i]) < 1.0) ++agree;
      } else if (o_ok) {
        ++ours_only;
      } else if (b_ok) {
        ++bm_only;
      }
    }
  }
  std::printf(
      "[ figure ] EuRoC V1_01, %d pairs, %d FAST features: both matched %d (agree within 1 px: %d = %.1f "
      "%%), "
      "ours only %d, StereoBM only %d; time per pair: row search %.3f ms, StereoBM (dense) %.2f ms\n",
      pairs, total, both, agree, 100.0 * agree / std::max(both, 1), ours_only, bm_only, t_ours_ms / pairs,
      t_bm_ms / pairs);
  ASSERT_GT(both, total / 4) << "too few features matched by both to compare";
  EXPECT_GT(agree, 0.9 * both);
  EXPECT_GT(both + ours_only, total / 2) << "the row search matched fewer than half the features";
}

TEST(StereoEuroc, RectifyAllocatesNothingAfterTheFirstPair) {
  REQUIRE_DATA();
  drivers::EurocReader log(kSeq);
  drivers::StereoRectifier rect(log.rig());
  LogImage l, r;
  ASSERT_TRUE(nth_pair(log, 3, l, r));
  ImageView lo, ro;
  ASSERT_TRUE(rect.rectify(l.view(), r.view(), &lo, &ro));
  ASSERT_TRUE(rt::alloc_hook_linked());
  rt::AllocCountScope scope;
  const auto t0 = std::chrono::steady_clock::now();
  for (int k = 0; k < 10; ++k) rect.rectify(l.view(), r.view(), &lo, &ro);
  const double ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count() / 10;
  std::printf("[ figure ] rectification of one 752x480 grey pair (both images): %.2f ms\n", ms);
  // A missing right image: the left alone, no right view.
  rect.rectify(l.view(), ImageView{}, &lo, &ro);
  EXPECT_EQ(scope.count(), 0u);
  EXPECT_EQ(ro.data, nullptr);
  EXPECT_NE(lo.data, nullptr);
}

Rig good_rig() {
  Rig rig;
  rig.rgb = CameraIntrinsics{640, 480, 400, 400, 320, 240, DistortionModel::kRadTan, {-0.2, 0.05, 0, 0, 0}};
  rig.stereo.present = true;
  rig.stereo.intrinsics = rig.rgb;
  rig.stereo.T_BC1 = kIdentity4;
  rig.stereo.T_BC1[3] = 0.08;  // right camera 8 cm along the left camera's x
  return rig;
}

std::string refusal(const Rig& rig) {
  try {
    drivers::StereoRectifier r(rig);
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "";
}

TEST(StereoRectifier, RefusesWhatCannotBeRectifiedAndNamesIt) {
  EXPECT_EQ(refusal(good_rig()), "");
  Rig r = good_rig();
  r.stereo.present = false;
  EXPECT_NE(refusal(r).find("no stereo"), std::string::npos);
  r = good_rig();
  r.stereo.intrinsics.width = 320;
  EXPECT_NE(refusal(r).find("differ in size"), std::string::npos);
  r = good_rig();
  r.stereo.T_BC1[3] = 0;
  r.stereo.T_BC1[7] = 0.08;  // stacked vertically
  EXPECT_NE(refusal(r).find("vertical"), std::string::npos);
  r = good_rig();
  r.stereo.T_BC1[3] = 0.0001;
  EXPECT_NE(refusal(r).find("baseline"), std::string::npos);
  r = good_rig();
  r.stereo.T_BC1[3] = -0.08;
  EXPECT_NE(refusal(r).find("swap cam0 and cam1"), std::string::npos);
  r = good_rig();
  r.stereo.intrinsics.distortion = DistortionModel::kEquidistant;
  EXPECT_NE(refusal(r).find("equidistant"), std::string::npos);
  r = good_rig();
  r.stereo.intrinsics.fx = 0;
  EXPECT_NE(refusal(r).find("stereo: stereo: no valid intrinsics"), std::string::npos) << refusal(r);
  r = good_rig();
  // Right camera turned 90 degrees about y: the optical axes are far apart.
  r.stereo.T_BC1 = {0, 0, 1, 0.08, 0, 1, 0, 0, -1, 0, 0, 0, 0, 0, 0, 1};
  EXPECT_NE(refusal(r).find("optical axes"), std::string::npos);
}

}  // namespace

namespace {

// A pair rectified by its maker (equal pinhole cameras, parallel axes): no remap, the pixels pass as they
// are.
TEST(StereoRectifier, RectifiedPairPassesThrough) {
  Rig rig;
  rig.rgb = CameraIntrinsics{64, 48, 50, 50, 32, 24, DistortionModel::kNone, {}};
  rig.stereo.present = true;
  rig.stereo.intrinsics = rig.rgb;
  rig.T_BC = {0, 0, 1, 0.05, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 0, 1};
  rig.stereo.T_BC1 = rig.T_BC;
  // Right camera 5 cm along the left camera's x, which is the body's -y here.
  rig.stereo.T_BC1[7] = -0.05;
  drivers::StereoRectifier rect(rig);
  EXPECT_NEAR(rect.rectified_rig().stereo.baseline_m, 0.05, 1e-12);
  EXPECT_EQ(rect.rectified_rig().T_BC, rig.T_BC);
  EXPECT_EQ(rect.rectified_rig().rgb.fx, 50);
  std::vector<uint8_t> a(64 * 48, 1), b(64 * 48, 2), rgb(64 * 48 * 3, 90);
  ImageView lo, ro;
  ASSERT_TRUE(rect.rectify({64, 48, 64, PixelFormat::kGray8, a.data()},
                           {64, 48, 64, PixelFormat::kGray8, b.data()}, &lo, &ro));
  EXPECT_EQ(lo.data, a.data());
  EXPECT_EQ(ro.data, b.data());
  // Colour is converted to grey (into the rectifier's buffers).
  ASSERT_TRUE(rect.rectify({64, 48, 192, PixelFormat::kRgb8, rgb.data()}, {}, &lo, &ro));
  EXPECT_EQ(lo.format, PixelFormat::kGray8);
  EXPECT_EQ(lo.data[100], 90);
  EXPECT_EQ(ro.data, nullptr);
}

}  // namespace

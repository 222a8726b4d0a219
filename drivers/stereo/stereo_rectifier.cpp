#include "kestrel/drivers/stereo_rectifier.hpp"

#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <string>
#include <vector>

namespace kestrel::drivers {
namespace {

cv::Matx44d to_cv(const Mat4d& T) {
  cv::Matx44d m;
  for (int i = 0; i < 16; ++i) m.val[i] = T[static_cast<size_t>(i)];
  return m;
}

cv::Matx33d camera_matrix(const CameraIntrinsics& k) { return {k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1}; }

cv::Mat dist_coeffs(const CameraIntrinsics& k) {
  if (k.distortion == DistortionModel::kEquidistant)
    return (cv::Mat_<double>(4, 1) << k.dist[0], k.dist[1], k.dist[2], k.dist[3]);
  if (k.distortion == DistortionModel::kRadTan)
    return (cv::Mat_<double>(5, 1) << k.dist[0], k.dist[1], k.dist[2], k.dist[3], k.dist[4]);
  return cv::Mat::zeros(5, 1, CV_64F);
}

void check_intrinsics(const CameraIntrinsics& k, const std::string& field) {
  if (k.width <= 0 || k.height <= 0 || !(k.fx > 0) || !(k.fy > 0) || !std::isfinite(k.cx) ||
      !std::isfinite(k.cy))
    throw std::invalid_argument("stereo: " + field + ": no valid intrinsics (width, height, fx, fy > 0)");
  for (double d : k.dist)
    if (!std::isfinite(d)) throw std::invalid_argument("stereo: " + field + ".dist_coeffs: not finite");
}

[[noreturn]] void refuse(const std::string& why) {
  throw std::invalid_argument("stereo: cannot rectify: " + why);
}

}  // namespace

// Where each rectified pixel comes from: the top-left source pixel of its
// bilinear neighbourhood as an offset into the source image, and the weights
// of the right and lower neighbours in 1/64 steps. Our own remap rather than
// cv::remap, which hands its rows to OpenCV's thread pool and allocates per
// call: this one runs on the tracking thread as it is. The offsets hold for
// one source stride; a view with another stride rebuilds them (no allocation).
struct RemapEntry {
  int32_t offset = 0;
  uint8_t wx = 0, wy = 0;
};

struct RemapTable {
  std::vector<RemapEntry> at;
  std::vector<uint32_t> xy;       // x0 | y0 << 16 per entry, to rebuild the offsets for another stride
  std::vector<uint32_t> outside;  // pixels without a source pixel (black)
  int stride = 0;
  void build(const cv::Mat& map_x, const cv::Mat& map_y, int width, int height) {
    const size_t n = static_cast<size_t>(width) * static_cast<size_t>(height);
    at.assign(n, RemapEntry{});
    xy.assign(n, 0);
    outside.clear();
    for (int y = 0; y < height; ++y) {
      for (int x = 0; x < width; ++x) {
        const size_t i = static_cast<size_t>(y) * width + x;
        const float sx = map_x.at<float>(y, x), sy = map_y.at<float>(y, x);
        if (!(sx >= 0 && sy >= 0 && sx <= width - 1 && sy <= height - 1)) {
          outside.push_back(static_cast<uint32_t>(i));
          continue;
        }
        int x0 = static_cast<int>(std::floor(sx)), y0 = static_cast<int>(std::floor(sy));
        int wx = static_cast<int>(std::lround((sx - x0) * 64.0f)),
            wy = static_cast<int>(std::lround((sy - y0) * 64.0f));
        // A weight of a full step moves to the next pixel; the last column/row has no right/lower neighbour.
        if (wx == 64) ++x0, wx = 0;
        if (wy == 64) ++y0, wy = 0;
        if (x0 >= width - 1) x0 = width - 2, wx = 64;
        if (y0 >= height - 1) y0 = height - 2, wy = 64;
        xy[i] = static_cast<uint32_t>(x0) | static_cast<uint32_t>(y0) << 16;
        at[i].wx = static_cast<uint8_t>(wx);
        at[i].wy = static_cast<uint8_t>(wy);
      }
    }
    set_stride(width);
  }
  void set_stride(int s) {
    stride = s;
    for (size_t i = 0; i < at.size(); ++i)
      at[i].offset = static_cast<int32_t>(xy[i] >> 16) * s + static_cast<int32_t>(xy[i] & 0xffffu);
  }
  void apply(const uint8_t* src, int src_stride, uint8_t* dst, int width, int height) {
    if (src_stride != stride) set_stride(src_stride);
    const size_t n = static_cast<size_t>(width) * static_cast<size_t>(height);
    const RemapEntry* e = at.data();
    for (size_t i = 0; i < n; ++i) {
      const uint8_t* p = src + e[i].offset;
      const int wx = e[i].wx, wy = e[i].wy;
      const int top = p[0] * 64 + (p[1] - p[0]) * wx;
      const int bottom = p[src_stride] * 64 + (p[src_stride + 1] - p[src_stride]) * wx;
      dst[i] = static_cast<uint8_t>((top * 64 + (bottom - top) * wy + 2048) >> 12);
    }
    // Rare (alpha 0 keeps only valid pixels): blacked out after the loop, so the loop has no branch.
    for (uint32_t i : outside) dst[i] = 0;
  }
};

struct StereoRectifier::Impl {
  RemapTable left, right;
  std::vector<uint8_t> gray_l, gray_r;  // raw colour converted to grey
  std::vector<uint8_t> out_l, out_r;
  int width = 0, height = 0;
  // The pair is rectified already (a D4xx IR pair, a ZED, the simulator's): no remap, only grey conversion.
  bool identity = false;
};

StereoRectifier::StereoRectifier(const Rig& rig) : rectified_(rig), impl_(std::make_unique<Impl>()) {
  if (!rig.stereo.present)
    throw std::invalid_argument("stereo: the rig has no stereo: section (no right camera)");
  const CameraIntrinsics& k0 = rig.rgb;
  const CameraIntrinsics& k1 = rig.stereo.intrinsics;
  check_intrinsics(k0, "camera");
  check_intrinsics(k1, "stereo");
  if (k0.width != k1.width || k0.height != k1.height) {
    refuse("camera and stereo differ in size (" + std::to_string(k0.width) + "x" + std::to_string(k0.height) +
           " vs " + std::to_string(k1.width) + "x" + std::to_string(k1.height) + ")");
  }
  const bool fisheye0 = k0.distortion == DistortionModel::kEquidistant;
  const bool fisheye1 = k1.distortion == DistortionModel::kEquidistant;
  if (fisheye0 != fisheye1)
    refuse("camera.distortion and stereo.distortion differ (equidistant with another model)");

  // OpenCV's R, T map left-camera coordinates into the right camera: T_C1C0 = T_BC1^-1 T_BC0.
  const cv::Matx44d T_C1C0 = to_cv(rig.stereo.T_BC1).inv() * to_cv(rig.T_BC);
  cv::Matx33d R;
  cv::Vec3d t;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) R(r, c) = T_C1C0(r, c);
    t[r] = T_C1C0(r, 3);
  }
  for (double v : R.val)
    if (!std::isfinite(v)) refuse("T_BC or stereo.T_BC1 is not finite or not invertible");
  const double baseline = cv::norm(t);
  if (!(baseline > 1e-3))
    refuse("baseline " + std::to_string(baseline) + " m between T_BC and stereo.T_BC1 (< 1 mm)");
  // The optical axes must look roughly the same way for rows to be shared.
  const double axis_cos = R(2, 2);
  if (axis_cos < std::cos(45.0 * M_PI / 180.0))
    refuse("the cameras' optical axes differ by more than 45 degrees (T_BC vs stereo.T_BC1)");
  // The rectified rows run along the baseline: a pair stacked vertically would need a transposed search.
  if (std::abs(t[0]) < std::abs(t[1]))
    refuse("the baseline is vertical (right camera above or below the left)");

  const cv::Size size(k0.width, k0.height);
  if (size.width > 32767 || size.height > 32767) refuse("images wider or taller than 32767 px");
  const size_t px = static_cast<size_t>(size.width) * static_cast<size_t>(size.height);
  impl_->width = size.width;
  impl_->height = size.height;
  impl_->gray_l.resize(px);
  impl_->gray_r.resize(px);
  // Rectified already: equal pinhole cameras, parallel axes, the right one along the left one's +x.
  const double rot_err = cv::norm(cv::Mat(R) - cv::Mat(cv::Matx33d::eye()));
  if (k0.distortion == DistortionModel::kNone && k1.distortion == DistortionModel::kNone && k0.fx == k1.fx &&
      k0.fy == k1.fy && k0.cx == k1.cx && k0.cy == k1.cy && rot_err < 1e-9 &&
      std::abs(t[1]) < 1e-9 * baseline && std::abs(t[2]) < 1e-9 * baseline && t[0] < 0) {
    impl_->identity = true;
    rectified_.rgb.dist = {};
    rectified_.stereo.rectified = true;
    rectified_.stereo.baseline_m = -t[0];
    rectified_.depth_camera.present = false;
    return;
  }
  const cv::Matx33d K0 = camera_matrix(k0), K1 = camera_matrix(k1);
  const cv::Mat D0 = dist_coeffs(k0), D1 = dist_coeffs(k1);
  cv::Mat R0, R1, P0, P1, Q, lx, ly, rx, ry;
  try {
    if (fisheye0) {
      cv::fisheye::stereoRectify(K0, D0, K1, D1, size, R, t, R0, R1, P0, P1, Q, cv::CALIB_ZERO_DISPARITY,
                                 size, 0.0, 1.0);
      cv::fisheye::initUndistortRectifyMap(K0, D0, R0, P0(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, lx, ly);
      cv::fisheye::initUndistortRectifyMap(K1, D1, R1, P1(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, rx, ry);
    } else {
      // alpha 0: only valid pixels, so no black border makes false corners.
      cv::stereoRectify(K0, D0, K1, D1, size, R, t, R0, R1, P0, P1, Q, cv::CALIB_ZERO_DISPARITY, 0.0, size);
      cv::initUndistortRectifyMap(K0, D0, R0, P0(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, lx, ly);
      cv::initUndistortRectifyMap(K1, D1, R1, P1(cv::Rect(0, 0, 3, 3)), size, CV_32FC1, rx, ry);
    }
  } catch (const cv::Exception& e) {
    refuse(std::string("OpenCV: ") + e.what());
  }
  const double f = P0.at<double>(0, 0);
  const double b = -P1.at<double>(0, 3) / P1.at<double>(0, 0);
  if (!(std::isfinite(f) && f > 0 && std::isfinite(b))) refuse("the rectified projection is not finite");
  // With the right camera on the left of the left one, disparities would be negative.
  if (!(b > 0)) refuse("stereo.T_BC1 puts the right camera to the left of camera (swap cam0 and cam1)");

  CameraIntrinsics& k = rectified_.rgb;
  k.fx = f;
  k.fy = P0.at<double>(1, 1);
  k.cx = P0.at<double>(0, 2);
  k.cy = P0.at<double>(1, 2);
  k.distortion = DistortionModel::kNone;
  k.dist = {};
  // The rectified left camera: p_R0 = R0 p_C0, so T_B,R0 = T_BC0 * [R0^T].
  cv::Matx44d T_C0R0 = cv::Matx44d::eye();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) T_C0R0(r, c) = R0.at<double>(c, r);
  const cv::Matx44d T_BR0 = to_cv(rig.T_BC) * T_C0R0;
  for (int i = 0; i < 16; ++i) rectified_.T_BC[static_cast<size_t>(i)] = T_BR0.val[i];
  rectified_.stereo.rectified = true;
  rectified_.stereo.baseline_m = b;
  rectified_.depth_camera.present = false;

  impl_->left.build(lx, ly, size.width, size.height);
  impl_->right.build(rx, ry, size.width, size.height);
  impl_->out_l.resize(px);
  impl_->out_r.resize(px);
}

StereoRectifier::~StereoRectifier() = default;

namespace {

// The view's grey pixels: the view itself, or its colour converted into `gray`
// (BT.601 weights in 1/256). Null when refused (size or format).
const uint8_t* grey_of(const ImageView& v, int width, int height, std::vector<uint8_t>& gray, int* stride) {
  if (v.data == nullptr || v.width != width || v.height != height) return nullptr;
  if (v.format == PixelFormat::kGray8) {
    *stride = v.stride_bytes;
    return v.data;
  }
  if (v.format != PixelFormat::kRgb8 && v.format != PixelFormat::kBgr8) return nullptr;
  const int r = v.format == PixelFormat::kRgb8 ? 0 : 2, b = 2 - r;
  for (int y = 0; y < height; ++y) {
    const uint8_t* p = v.data + static_cast<size_t>(y) * v.stride_bytes;
    uint8_t* o = gray.data() + static_cast<size_t>(y) * width;
    for (int x = 0; x < width; ++x, p += 3)
      o[x] = static_cast<uint8_t>((77 * p[r] + 150 * p[1] + 29 * p[b] + 128) >> 8);
  }
  *stride = width;
  return gray.data();
}

}  // namespace

bool StereoRectifier::rectify(const ImageView& left, const ImageView& right, ImageView* left_out,
                              ImageView* right_out) {
  Impl& m = *impl_;
  *left_out = ImageView{};
  *right_out = ImageView{};
  int stride = 0;
  const uint8_t* l = grey_of(left, m.width, m.height, m.gray_l, &stride);
  if (l == nullptr) {
    ++refused_;
    return false;
  }
  if (m.identity) {
    *left_out = ImageView{m.width, m.height, stride, PixelFormat::kGray8, l};
  } else {
    m.left.apply(l, stride, m.out_l.data(), m.width, m.height);
    *left_out = ImageView{m.width, m.height, m.width, PixelFormat::kGray8, m.out_l.data()};
  }
  if (right.data != nullptr) {
    const uint8_t* r = grey_of(right, m.width, m.height, m.gray_r, &stride);
    if (r == nullptr) {
      ++refused_;
    } else {
      if (m.identity) {
        *right_out = ImageView{m.width, m.height, stride, PixelFormat::kGray8, r};
      } else {
        m.right.apply(r, stride, m.out_r.data(), m.width, m.height);
        *right_out = ImageView{m.width, m.height, m.width, PixelFormat::kGray8, m.out_r.data()};
      }
    }
  }
  return true;
}

}  // namespace kestrel::drivers

#include "kestrel/drivers/depth_registration.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <stdexcept>
#include <string>

namespace kestrel::drivers {
namespace {

// Normalised (x, y) -> distorted normalised (Kalibr's radtan / equidistant).
void distort(const CameraIntrinsics& k, double x, double y, double& xd, double& yd) {
  switch (k.distortion) {
    case DistortionModel::kNone:
      xd = x, yd = y;
      return;
    case DistortionModel::kRadTan: {
      const double r2 = x * x + y * y;
      const double radial = 1 + r2 * (k.dist[0] + r2 * (k.dist[1] + r2 * k.dist[4]));
      xd = x * radial + 2 * k.dist[2] * x * y + k.dist[3] * (r2 + 2 * x * x);
      yd = y * radial + k.dist[2] * (r2 + 2 * y * y) + 2 * k.dist[3] * x * y;
      return;
    }
    case DistortionModel::kEquidistant: {
      const double r = std::sqrt(x * x + y * y);
      if (r < 1e-12) {
        xd = x, yd = y;
        return;
      }
      const double th = std::atan(r), th2 = th * th;
      const double thd =
          th * (1 + th2 * (k.dist[0] + th2 * (k.dist[1] + th2 * (k.dist[2] + th2 * k.dist[3]))));
      xd = x * thd / r, yd = y * thd / r;
      return;
    }
  }
  xd = x, yd = y;
}

// Inverse of distort() by fixed-point iteration, started at the distorted
// point (converges for the mild distortion of depth cameras).
void undistort(const CameraIntrinsics& k, double xd, double yd, double& x, double& y) {
  x = xd, y = yd;
  if (k.distortion == DistortionModel::kNone) return;
  for (int it = 0; it < 20; ++it) {
    double ex, ey;
    distort(k, x, y, ex, ey);
    x += xd - ex;
    y += yd - ey;
  }
}

void check(const CameraIntrinsics& k, const char* which) {
  if (k.width <= 0 || k.height <= 0 || !(k.fx > 0) || !(k.fy > 0) || !std::isfinite(k.cx) ||
      !std::isfinite(k.cy)) {
    throw std::invalid_argument(std::string("DepthRegistration: the ") + which +
                                " camera needs a size and focal lengths > 0");
  }
}

}  // namespace

DepthRegistration::DepthRegistration(const DepthCamera& dc, const CameraIntrinsics& colour,
                                     double scale_m_per_unit)
    : colour_(colour) {
  if (!dc.present) throw std::invalid_argument("DepthRegistration: the rig has no separate depth camera");
  check(dc.intrinsics, "depth");
  check(colour, "colour");
  if (!(scale_m_per_unit > 0)) throw std::invalid_argument("DepthRegistration: the depth scale must be > 0");
  for (double v : dc.T_CD)
    if (!std::isfinite(v)) throw std::invalid_argument("DepthRegistration: T_CD is not finite");
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) R_[3 * r + c] = dc.T_CD[4 * r + c];
    t_[r] = dc.T_CD[4 * r + 3] / scale_m_per_unit;
  }
  const CameraIntrinsics& d = dc.intrinsics;
  dw_ = d.width, dh_ = d.height, cw_ = colour.width, ch_ = colour.height;
  // A depth pixel spans fc / fd colour pixels: above 1 the points would leave
  // a grid of holes, so each covers a square of that side.
  const double ratio = std::max(colour.fx / d.fx, colour.fy / d.fy);
  footprint_ = std::max(1, static_cast<int>(std::ceil(ratio - 1e-6)));
  ray_.reset(new float[static_cast<size_t>(dw_) * dh_ * 2]);
  for (int v = 0; v < dh_; ++v) {
    for (int u = 0; u < dw_; ++u) {
      double x, y;
      undistort(d, (u - d.cx) / d.fx, (v - d.cy) / d.fy, x, y);
      float* r = ray_.get() + 2 * (static_cast<size_t>(v) * dw_ + u);
      r[0] = static_cast<float>(x);
      r[1] = static_cast<float>(y);
    }
  }
}

DepthRegistration::~DepthRegistration() = default;

bool DepthRegistration::register_into(const ImageView& depth, uint16_t* out, int out_stride_bytes,
                                      RegistrationStats* stats) const {
  if (depth.data == nullptr || depth.format != PixelFormat::kDepthU16 || depth.width != dw_ ||
      depth.height != dh_ || out == nullptr || out_stride_bytes < 2 * cw_)
    return false;
  RegistrationStats s;
  auto row_out = [&](int y) {
    return reinterpret_cast<uint16_t*>(reinterpret_cast<uint8_t*>(out) +
                                       static_cast<size_t>(y) * out_stride_bytes);
  };
  for (int y = 0; y < ch_; ++y) std::memset(row_out(y), 0, static_cast<size_t>(cw_) * 2);
  const CameraIntrinsics& k = colour_;
  const bool distorted = k.distortion != DistortionModel::kNone;
  const double half = 0.5 * (footprint_ - 1);
  for (int v = 0; v < dh_; ++v) {
    const auto* row =
        reinterpret_cast<const uint16_t*>(depth.data + static_cast<size_t>(v) * depth.stride_bytes);
    const float* ray = ray_.get() + 2 * static_cast<size_t>(v) * dw_;
    for (int u = 0; u < dw_; ++u) {
      const uint16_t raw = row[u];
      if (raw == 0) continue;
      ++s.valid_in;
      // In depth units throughout (t_ was scaled to them at construction).
      const double z = raw, px = ray[2 * u] * z, py = ray[2 * u + 1] * z;
      const double qx = R_[0] * px + R_[1] * py + R_[2] * z + t_[0];
      const double qy = R_[3] * px + R_[4] * py + R_[5] * z + t_[1];
      const double qz = R_[6] * px + R_[7] * py + R_[8] * z + t_[2];
      if (!(qz >= 1.0) || qz > 65535.0) continue;
      double xn = qx / qz, yn = qy / qz;
      if (distorted) distort(k, qx / qz, qy / qz, xn, yn);
      const double uc = k.fx * xn + k.cx - half, vc = k.fy * yn + k.cy - half;
      const int x0 = static_cast<int>(std::lround(uc)), y0 = static_cast<int>(std::lround(vc));
      if (x0 + footprint_ <= 0 || y0 + footprint_ <= 0 || x0 >= cw_ || y0 >= ch_) continue;
      ++s.projected;
      const auto zc = static_cast<uint16_t>(std::lround(qz));
      for (int y = std::max(0, y0); y < std::min(ch_, y0 + footprint_); ++y) {
        uint16_t* o = row_out(y);
        for (int x = std::max(0, x0); x < std::min(cw_, x0 + footprint_); ++x) {
          if (o[x] != 0) ++s.occluded;
          if (o[x] == 0 || zc < o[x]) o[x] = zc;
        }
      }
    }
  }
  if (stats) {
    for (int y = 0; y < ch_; ++y) {
      const uint16_t* o = row_out(y);
      for (int x = 0; x < cw_; ++x) s.valid_out += o[x] != 0;
    }
  }
  if (stats) *stats = s;
  return true;
}

}  // namespace kestrel::drivers

// A TUM-VI folder ("dataset-<name>_512_16" layout) written by the tests from a
// stereo log with a rectified pinhole pair (`kestrel sim --stereo`): each image
// is re-projected into an equidistant (fisheye) camera, as TUM-VI's are, and
// stored as a 16-bit PNG; the chain goes to dso/camchain.yaml in Kalibr's form.
// No data of the real dataset is used.
#pragma once

#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <string>

#include "kestrel/drivers/log_source.hpp"

namespace kestrel::test {

struct TumviFixtureOptions {
  // The fisheye's focal length against the pinhole's: above 1 the fisheye sees
  // less than the pinhole image holds, so no fisheye pixel samples outside it.
  double focal_scale = 1.3;
  std::array<double, 4> k = {0.02, -0.01, 0.004, -0.001};  // equidistant k1..k4
  int max_frames = 1 << 30;
  // false: the images stay as rendered and the chain carries the source camera's own model (radtan or
  // none); only the layout is TUM-VI's.
  bool equidistant = true;
};

// p_C = T_cam_imu p_I is the inverse of T_BC (body = IMU).
inline std::array<double, 16> rigid_inverse16(const Mat4d& T) {
  std::array<double, 16> o{};
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) o[4 * r + c] = T[4 * c + r];
    o[4 * r + 3] = -(T[r] * T[3] + T[4 + r] * T[7] + T[8 + r] * T[11]);
  }
  o[15] = 1;
  return o;
}

inline std::string kalibr_camera(const std::string& name, const CameraIntrinsics& k, double focal_scale,
                                 const char* model, const std::array<double, 4>& d, const Mat4d& T_BC) {
  const auto T = rigid_inverse16(T_BC);
  char buf[2048];
  std::snprintf(
      buf, sizeof buf,
      "%s:\n  T_cam_imu:\n  - [%.17g, %.17g, %.17g, %.17g]\n  - [%.17g, %.17g, %.17g, %.17g]\n"
      "  - [%.17g, %.17g, %.17g, %.17g]\n  - [0.0, 0.0, 0.0, 1.0]\n  camera_model: pinhole\n"
      "  distortion_coeffs: [%.17g, %.17g, %.17g, %.17g]\n  distortion_model: %s\n"
      "  intrinsics: [%.17g, %.17g, %.17g, %.17g]\n  resolution: [%d, %d]\n  rostopic: /%s/image_raw\n",
      name.c_str(), T[0], T[1], T[2], T[3], T[4], T[5], T[6], T[7], T[8], T[9], T[10], T[11], d[0], d[1],
      d[2], d[3], model, k.fx * focal_scale, k.fy * focal_scale, k.cx, k.cy, k.width, k.height, name.c_str());
  return buf;
}

// Writes `dir` (created) from every record of `src`; returns the number of left images written.
inline int write_tumvi_folder(drivers::LogSource& src, const std::string& dir,
                              const TumviFixtureOptions& o = {}) {
  namespace fs = std::filesystem;
  const Rig& rig = src.rig();
  if (!rig.stereo.present) throw std::runtime_error("write_tumvi_folder: the log is not stereo");
  const std::string m = dir + "/mav0";
  for (const char* d : {"/cam0/data", "/cam1/data", "/imu0", "/mocap0"}) fs::create_directories(m + d);
  fs::create_directories(dir + "/dso");
  {
    std::ofstream f(dir + "/dso/camchain.yaml");
    // Kalibr's radtan has four coefficients (k1 k2 p1 p2).
    auto own = [](const CameraIntrinsics& k) {
      if (k.dist[4] != 0)
        throw std::runtime_error("write_tumvi_folder: radtan k3 has no place in a Kalibr chain");
      return std::array<double, 4>{k.dist[0], k.dist[1], k.dist[2], k.dist[3]};
    };
    auto model = [](const CameraIntrinsics& k) {
      return k.distortion == DistortionModel::kRadTan ? "radtan" : "none";
    };
    const CameraIntrinsics& k0 = rig.rgb;
    const CameraIntrinsics& k1 = rig.stereo.intrinsics;
    if (o.equidistant)
      f << kalibr_camera("cam0", k0, o.focal_scale, "equidistant", o.k, rig.T_BC)
        << kalibr_camera("cam1", k1, o.focal_scale, "equidistant", o.k, rig.stereo.T_BC1);
    else
      f << kalibr_camera("cam0", k0, 1.0, model(k0), own(k0), rig.T_BC)
        << kalibr_camera("cam1", k1, 1.0, model(k1), own(k1), rig.stereo.T_BC1);
    std::ofstream g(dir + "/dso/imu_config.yaml");
    g.precision(17);
    g << "accelerometer_noise_density: " << rig.imu.acc_noise_density_mps2_sqrthz
      << "\naccelerometer_random_walk: " << rig.imu.acc_random_walk_mps3_sqrthz
      << "\ngyroscope_noise_density: " << rig.imu.gyro_noise_density_rad_s_sqrthz
      << "\ngyroscope_random_walk: " << rig.imu.gyro_random_walk_rad_s2_sqrthz
      << "\nrostopic: /imu0\nupdate_rate: " << rig.imu_rate_hz << "\n";
  }
  // For each fisheye pixel, where its ray meets the source image, through the source camera's own model
  // (the simulator's pair carries radial-tangential distortion).
  auto make_map = [&](const CameraIntrinsics& k, cv::Mat& mx, cv::Mat& my) {
    const cv::Matx33d K_fish(k.fx * o.focal_scale, 0, k.cx, 0, k.fy * o.focal_scale, k.cy, 0, 0, 1);
    const cv::Vec4d D(o.k[0], o.k[1], o.k[2], o.k[3]);
    cv::Mat pts(k.width * k.height, 1, CV_64FC2);
    for (int v = 0; v < k.height; ++v)
      for (int u = 0; u < k.width; ++u) pts.at<cv::Vec2d>(v * k.width + u) = cv::Vec2d(u, v);
    cv::Mat und;
    cv::fisheye::undistortPoints(pts, und, K_fish, D);
    mx.create(k.height, k.width, CV_32F);
    my.create(k.height, k.width, CV_32F);
    for (int v = 0; v < k.height; ++v)
      for (int u = 0; u < k.width; ++u) {
        const cv::Vec2d x = und.at<cv::Vec2d>(v * k.width + u);
        double xd = x[0], yd = x[1];
        if (k.distortion == DistortionModel::kRadTan) {
          const double r2 = x[0] * x[0] + x[1] * x[1];
          const double radial = 1 + k.dist[0] * r2 + k.dist[1] * r2 * r2 + k.dist[4] * r2 * r2 * r2;
          xd = x[0] * radial + 2 * k.dist[2] * x[0] * x[1] + k.dist[3] * (r2 + 2 * x[0] * x[0]);
          yd = x[1] * radial + k.dist[2] * (r2 + 2 * x[1] * x[1]) + 2 * k.dist[3] * x[0] * x[1];
        } else if (k.distortion != DistortionModel::kNone) {
          throw std::runtime_error("write_tumvi_folder: the source camera must be radtan or undistorted");
        }
        mx.at<float>(v, u) = static_cast<float>(k.fx * xd + k.cx);
        my.at<float>(v, u) = static_cast<float>(k.fy * yd + k.cy);
      }
  };
  cv::Mat mx0, my0, mx1, my1;
  make_map(rig.rgb, mx0, my0);
  make_map(rig.stereo.intrinsics, mx1, my1);
  std::ofstream imu(m + "/imu0/data.csv"), gt(m + "/mocap0/data.csv"), c0(m + "/cam0/data.csv"),
      c1(m + "/cam1/data.csv");
  imu.precision(17);
  gt.precision(17);
  imu << "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],"
         "a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n";
  gt << "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z "
        "[]\n";
  c0 << "#timestamp [ns],filename\n";
  c1 << "#timestamp [ns],filename\n";
  int left = 0, right = 0;
  drivers::LogRecord r;
  while (src.next(r)) {
    if (r.type == drivers::RecordType::kImu) {
      const auto& s = r.imu;
      imu << s.t_ns << ',' << s.gyro_rps[0] << ',' << s.gyro_rps[1] << ',' << s.gyro_rps[2] << ','
          << s.acc_mps2[0] << ',' << s.acc_mps2[1] << ',' << s.acc_mps2[2] << '\n';
    } else if (r.type == drivers::RecordType::kGroundTruth) {
      const auto& g = r.gt;
      gt << g.t_ns << ',' << g.p_WB[0] << ',' << g.p_WB[1] << ',' << g.p_WB[2] << ',' << g.q_WB[0] << ','
         << g.q_WB[1] << ',' << g.q_WB[2] << ',' << g.q_WB[3] << '\n';
    } else if (r.type == drivers::RecordType::kRgb || r.type == drivers::RecordType::kRight) {
      const bool is_left = r.type == drivers::RecordType::kRgb;
      if ((is_left ? left : right) >= o.max_frames) continue;
      const auto& im = r.image;
      cv::Mat grey;
      if (im.format == PixelFormat::kRgb8) {
        cv::cvtColor(cv::Mat(im.height, im.width, CV_8UC3, const_cast<uint8_t*>(im.pixels.data())), grey,
                     cv::COLOR_RGB2GRAY);
      } else if (im.format == PixelFormat::kGray8) {
        grey = cv::Mat(im.height, im.width, CV_8UC1, const_cast<uint8_t*>(im.pixels.data())).clone();
      } else {
        throw std::runtime_error("write_tumvi_folder: unexpected pixel format");
      }
      cv::Mat fish, fish16;
      if (o.equidistant)
        cv::remap(grey, fish, is_left ? mx0 : mx1, is_left ? my0 : my1, cv::INTER_LINEAR,
                  cv::BORDER_CONSTANT);
      else
        fish = grey;
      fish.convertTo(fish16, CV_16U, 257.0);  // the full 16-bit range, as TUM-VI's *_16 images
      const std::string name = std::to_string(im.t_ns) + ".png";
      cv::imwrite(m + (is_left ? "/cam0/data/" : "/cam1/data/") + name, fish16);
      (is_left ? c0 : c1) << im.t_ns << ',' << name << '\n';
      ++(is_left ? left : right);
    }
  }
  return left;
}

}  // namespace kestrel::test

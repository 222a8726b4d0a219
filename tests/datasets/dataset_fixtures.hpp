// Small recordings written by the tests themselves: a .klog with every
// stream, and hand-made ETH3D / OpenLORIS folders with real structure.
#pragma once

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <string>
#include <vector>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "test_data.hpp"

namespace kestrel::test {

inline Rig small_rig() {
  Rig r;
  r.name = "dataset fixture";
  r.rgb.width = 8;
  r.rgb.height = 6;
  r.rgb.fx = 5.25, r.rgb.fy = 5.5, r.rgb.cx = 3.875, r.rgb.cy = 2.9375;
  r.depth.scale_m_per_unit = 0.001;
  // A rotation about z by 90 degrees and a lever arm: frames must be handled, not ignored.
  r.T_BC = {0, -1, 0, 0.05, 1, 0, 0, -0.02, 0, 0, 1, 0.01, 0, 0, 0, 1};
  r.imu_rate_hz = 400;
  r.camera_rate_hz = 20;
  r.imu.gyro_noise_density_rad_s_sqrthz = 1.6968e-04;
  return r;
}

constexpr int64_t kT0 = 1'500'000'000'123'456'789;  // a realistic epoch stamp, odd nanoseconds

inline ImuSample imu_at(uint32_t i) {
  ImuSample s;
  s.t_ns = kT0 + int64_t{i} * 2'500'000;
  s.t_recv_ns = s.t_ns;
  s.seq = i;
  for (int k = 0; k < 3; ++k) {
    s.gyro_rps[k] = 0.01 * std::sin(0.1 * i + k);
    s.acc_mps2[k] = (k == 2 ? 9.81 : 0.0) + 0.3 * std::cos(0.07 * i + k);
  }
  return s;
}

inline drivers::LogImage image_at(int64_t t_ns, uint32_t i, PixelFormat f, int w = 8, int h = 6) {
  drivers::LogImage img;
  img.t_ns = img.t_recv_ns = t_ns;
  img.seq = i;
  img.width = w;
  img.height = h;
  img.format = f;
  img.pixels.resize(static_cast<size_t>(w) * h * bytes_per_pixel(f));
  for (size_t k = 0; k < img.pixels.size(); ++k)
    img.pixels[k] = static_cast<uint8_t>((k * 7 + i * 13) & 0xff);
  if (f == PixelFormat::kDepthU16)  // millimetres 500..4000, some invalid zeros
    for (size_t k = 0; k < img.pixels.size() / 2; ++k) {
      const uint16_t v = k % 11 == 0 ? 0 : static_cast<uint16_t>(500 + (k * 37 + i * 101) % 3500);
      std::memcpy(img.pixels.data() + 2 * k, &v, 2);
    }
  return img;
}

inline GroundTruthPose gt_at(int64_t t_ns, uint32_t i) {
  GroundTruthPose g;
  g.t_ns = t_ns;
  g.p_WB = {0.1 * i, -0.2 * i, 1.5};
  const double a = 0.05 * i;
  g.q_WB = {std::cos(a), 0, std::sin(a) * 0.6, std::sin(a) * 0.8};
  return g;
}

// 0.5 s: IMU at 400 Hz, RGB + depth at 20 Hz (same stamp), ground truth at 100 Hz.
inline void write_small_klog(const std::string& path, const Rig& rig = small_rig(), int frames = 10,
                             PixelFormat colour = PixelFormat::kRgb8) {
  drivers::KlogWriter w;
  w.open(path, rig);
  const uint32_t n_imu = static_cast<uint32_t>(frames) * 20;
  for (uint32_t i = 0; i < n_imu; ++i) {
    const ImuSample s = imu_at(i);
    w.write_imu(s);
    if (i % 20 == 0) {
      w.write_image(drivers::RecordType::kRgb, image_at(s.t_ns, i / 20, colour));
      w.write_image(drivers::RecordType::kDepth, image_at(s.t_ns, i / 20, PixelFormat::kDepthU16));
    }
    if (i % 4 == 0) w.write_ground_truth(gt_at(s.t_ns, i / 4));
  }
}

inline std::vector<drivers::LogRecord> read_all(drivers::LogSource& s) {
  std::vector<drivers::LogRecord> v;
  drivers::LogRecord r;
  s.rewind();
  while (s.next(r)) v.push_back(r);
  return v;
}

inline std::vector<drivers::LogRecord> of_type(const std::vector<drivers::LogRecord>& v,
                                               drivers::RecordType t) {
  std::vector<drivers::LogRecord> o;
  for (const auto& r : v)
    if (r.type == t) o.push_back(r);
  return o;
}

inline bool has_problem(const drivers::LogSource& s, const std::string& kind, const std::string& where_part) {
  for (const auto& p : s.problems())
    if (p.kind == kind && p.where.find(where_part) != std::string::npos) return true;
  return false;
}

inline std::string problems_text(const drivers::LogSource& s) {
  std::string t;
  for (const auto& p : s.problems()) t += p.where + ": " + p.kind + ": " + p.detail + "\n";
  return t;
}

inline std::string text_seconds(int64_t t_ns) {
  char b[48];
  std::snprintf(b, sizeof b, "%lld.%09lld", static_cast<long long>(t_ns / 1000000000),
                static_cast<long long>(t_ns % 1000000000));
  return b;
}

inline void write_text(const std::string& path, const std::string& body) {
  std::ofstream f(path);
  f << body;
}

// Metres of one depth pixel.
inline double depth_m(const drivers::LogImage& img, size_t k, double scale) {
  uint16_t v;
  std::memcpy(&v, img.pixels.data() + 2 * k, 2);
  return v * scale;
}

}  // namespace kestrel::test

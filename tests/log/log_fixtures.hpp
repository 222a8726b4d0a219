// Small deterministic logs for the log tests and the klog fuzz target.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <limits>
#include <string>
#include <vector>

#include "kestrel/drivers/klog.hpp"

namespace kestrel::test {

// Every record of a source from its start.
inline std::vector<drivers::LogRecord> all_records(drivers::LogSource& s) {
  std::vector<drivers::LogRecord> v;
  drivers::LogRecord r;
  s.rewind();
  while (s.next(r)) v.push_back(r);
  return v;
}

struct RecordSpan {
  drivers::RecordType type;
  uint64_t begin;  // byte offset of the record header
  uint64_t end;    // one past its last payload byte
};

inline Rig fixture_rig() {
  Rig r;
  r.name = "fixture: \"quoted\" rig";
  r.rgb.width = 8;
  r.rgb.height = 6;
  r.rgb.fx = 5.25;
  r.rgb.fy = 5.5;
  r.rgb.cx = 3.875;
  r.rgb.cy = 2.9375;
  r.rgb.distortion = DistortionModel::kRadTan;
  r.rgb.dist = {0.1, -0.2, 1e-4, -2e-4, 0.01};
  r.T_BC = {0, -1, 0, 0.05, 1, 0, 0, -0.02, 0, 0, 1, 0.01, 0, 0, 0, 1};
  r.imu_rate_hz = 400;
  r.camera_rate_hz = 30;
  r.imu.gyro_noise_density_rad_s_sqrthz = 1.6968e-04;
  // 0: the format tests compare records with what was written, and a reader
  // moves camera stamps by a non-zero offset (camera_time_shift_test covers
  // that; rig_yaml_test round-trips the field itself).
  r.time_offset_cam_imu_ns = 0;
  return r;
}

inline ImuSample fixture_imu(uint32_t i) {
  ImuSample s;
  s.t_ns = 1'000'000'000 + int64_t{i} * 2'500'000;
  s.t_recv_ns = s.t_ns + 130'000 + i;
  s.seq = i;
  s.flags = i % 7 == 3 ? kImuGapBefore : 0u;
  for (int k = 0; k < 3; ++k) {
    s.gyro_rps[k] = 0.01 * std::sin(0.1 * i + k) + 1e-300 * k;
    s.acc_mps2[k] = 9.81 * std::cos(0.07 * i + k) - (k == 2 ? 0.0 : -0.0);
  }
  s.temp_c = 25.5f + 0.25f * static_cast<float>(i);
  return s;
}

inline drivers::LogImage fixture_image(uint32_t i, PixelFormat f, int w = 8, int h = 6) {
  drivers::LogImage img;
  img.t_ns = 1'000'000'000 + int64_t{i} * 33'333'333;
  img.t_recv_ns = img.t_ns + 5'000'000;
  img.seq = i;
  img.exposure_us = 8000 + static_cast<int32_t>(i);
  img.width = w;
  img.height = h;
  img.format = f;
  img.pixels.resize(static_cast<size_t>(w) * h * bytes_per_pixel(f));
  for (size_t k = 0; k < img.pixels.size(); ++k)
    img.pixels[k] = static_cast<uint8_t>((k * 7 + i * 13) & 0xff);
  return img;
}

inline GroundTruthPose fixture_gt(uint32_t i, bool with_velocity) {
  GroundTruthPose g;
  g.t_ns = 1'000'000'000 + int64_t{i} * 5'000'000;
  g.p_WB = {0.1 * i, -0.2 * i, 1.5};
  const double a = 0.01 * i;
  g.q_WB = {std::cos(a), 0, 0, std::sin(a)};
  g.has_velocity = with_velocity;
  if (with_velocity) g.v_WB = {0.5, -0.25, 0.125 * i};
  return g;
}

inline std::vector<uint8_t> read_bytes(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return std::vector<uint8_t>(std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>());
}

inline void write_bytes(const std::string& path, const uint8_t* data, size_t n) {
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  f.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(n));
}

// Writes a small log holding every record type (and every pixel format) to
// `path`; spans (optional) receives where each record sits.
inline void write_small_klog(const std::string& path, std::vector<RecordSpan>* spans) {
  drivers::KlogWriter w;
  w.open(path, fixture_rig());
  uint64_t at = w.bytes_written();
  auto mark = [&](drivers::RecordType t) {
    if (spans) spans->push_back({t, at, w.bytes_written()});
    at = w.bytes_written();
  };
  using drivers::RecordType;
  uint32_t n_imu = 0;
  for (uint32_t k = 0; k < 3; ++k) {
    w.write_imu(fixture_imu(n_imu++));
    mark(RecordType::kImu);
  }
  w.write_image(RecordType::kRgb, fixture_image(0, PixelFormat::kRgb8));
  mark(RecordType::kRgb);
  w.write_image(RecordType::kDepth, fixture_image(0, PixelFormat::kDepthU16));
  mark(RecordType::kDepth);
  w.write_ground_truth(fixture_gt(0, false));
  mark(RecordType::kGroundTruth);
  w.write_imu(fixture_imu(n_imu++));
  mark(RecordType::kImu);
  w.write_event(Event{1'010'000'000, EventCode::kFrameDrop, "frame 7 dropped, ring full"});
  mark(RecordType::kEvent);
  w.write_image(RecordType::kRgb, fixture_image(1, PixelFormat::kGray8, 5, 3));
  mark(RecordType::kRgb);
  w.write_ground_truth(fixture_gt(1, true));
  mark(RecordType::kGroundTruth);
  w.write_event(Event{1'020'000'000, EventCode::kInfo, ""});
  mark(RecordType::kEvent);
  w.write_image(RecordType::kRgb, fixture_image(2, PixelFormat::kYuyv, 4, 2));
  mark(RecordType::kRgb);
  w.write_image(RecordType::kRgb, fixture_image(3, PixelFormat::kBgr8, 2, 2));
  mark(RecordType::kRgb);
  for (uint32_t k = 0; k < 2; ++k) {
    w.write_imu(fixture_imu(n_imu++));
    mark(RecordType::kImu);
  }
  w.close();
}

// A smooth, slightly noisy w x h image (deterministic): compresses the way
// camera frames do, so a writer stores it compressed.
inline drivers::LogImage smooth_image(uint32_t i, PixelFormat f, int w, int h) {
  drivers::LogImage img = fixture_image(i, f, w, h);
  const int bpp = bytes_per_pixel(f);
  uint32_t state = 12345u + i;
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      state = state * 1664525u + 1013904223u;
      const int v = 60 + x * 2 + y + static_cast<int>((state >> 28) & 3u);
      uint8_t* p = &img.pixels[(static_cast<size_t>(y) * w + x) * bpp];
      if (f == PixelFormat::kDepthU16) {
        const int d = (x + y) % 11 == 0 ? 0 : 900 + 4 * v;
        p[0] = static_cast<uint8_t>(d & 0xff);
        p[1] = static_cast<uint8_t>(d >> 8);
      } else {
        for (int c = 0; c < bpp; ++c) p[c] = static_cast<uint8_t>(v + 9 * c);
      }
    }
  return img;
}

// A version 2 log whose images are compressed: zstd RGB and depth, an lz4
// gray frame, IMU between them (the fuzz target's compressed seed).
inline void write_compressed_klog(const std::string& path, std::vector<RecordSpan>* spans) {
  drivers::KlogWriter w;
  w.open(path, fixture_rig());
  uint64_t at = w.bytes_written();
  auto mark = [&](drivers::RecordType t) {
    if (spans) spans->push_back({t, at, w.bytes_written()});
    at = w.bytes_written();
  };
  using drivers::RecordType;
  w.write_imu(fixture_imu(0));
  mark(RecordType::kImu);
  w.write_image(RecordType::kRgb, smooth_image(0, PixelFormat::kRgb8, 24, 16));
  mark(RecordType::kRgb);
  w.write_image(RecordType::kDepth, smooth_image(0, PixelFormat::kDepthU16, 24, 16));
  mark(RecordType::kDepth);
  w.write_imu(fixture_imu(1));
  mark(RecordType::kImu);
  drivers::klog::ImageCompression lz4;
  lz4.codec = drivers::klog::ImageCodec::kLz4;
  w.set_compression(lz4);
  w.write_image(RecordType::kRgb, smooth_image(1, PixelFormat::kGray8, 24, 16));
  mark(RecordType::kRgb);
  w.write_imu(fixture_imu(2));
  mark(RecordType::kImu);
  w.close();
}

}  // namespace kestrel::test

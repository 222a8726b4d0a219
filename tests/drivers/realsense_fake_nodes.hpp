// The fake V4L2 nodes the RealSense D4xx tests feed (the driver's Node seam):
// scripted buffers per node, the formats they report, YUYV from RGB, and the
// device clock plus the metadata records a D4xx attaches to each frame.
// Shared by test_realsense_d4xx.cpp (the driver's units, under ASan too) and
// test_realsense_d4xx_flight.cpp (a flight scored through `kestrel`).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/drivers/d4xx_camera.hpp"
#include "kestrel/drivers/d4xx_metadata.hpp"

namespace kestrel::drivers::d4xx {
namespace {

// ---- fake nodes ---------------------------------------------------------------------------
struct FakeBuf {
  std::vector<uint8_t> bytes;
  uint32_t seq = 0;
  uint32_t flags = v4l2::kBufFlagTimestampMonotonic;
  int64_t t_ns = 0;  // the kernel's buffer stamp
};
struct FakeScript {
  NodeFormat format;
  std::vector<FakeBuf> bufs;  // in arrival order
  size_t next = 0;
  uint64_t requeued = 0;
  int out = 0;  // dequeued and not yet requeued
  // A metadata node's buffers arrive with their frame: buffer k is there once
  // the video node `gate` has handed out a frame with sequence >= k's.
  const FakeScript* gate = nullptr;
  bool any = false;
  uint32_t last_seq = 0;
  bool available() const {
    if (next >= bufs.size()) return false;
    if (gate == nullptr) return true;
    return gate->any && static_cast<int32_t>(bufs[next].seq - gate->last_seq) <= 0;
  }
};
using FakeDevice = std::map<std::string, FakeScript>;

class FakeNode final : public Node {
 public:
  explicit FakeNode(FakeDevice& dev) : dev_(dev) {}
  std::string open(const std::string& path, const NodeRequest& r) override {
    auto it = dev_.find(path);
    if (it == dev_.end()) return path + ": No such file or directory";
    if (r.metadata != (it->second.format.fourcc == kMetaFmtUvc || it->second.format.fourcc == kMetaFmtD4xx))
      return path + ": wrong node kind";
    s_ = &it->second;
    return "";
  }
  void close() override { s_ = nullptr; }
  bool is_open() const override { return s_ != nullptr; }
  const NodeFormat& format() const override { return s_->format; }
  NodeWait wait(int) override { return s_->available() ? NodeWait::kReady : NodeWait::kTimeout; }
  bool dequeue(NodeBuffer& b) override {
    if (s_ == nullptr || !s_->available()) return false;
    const FakeBuf& f = s_->bufs[s_->next];
    s_->any = true;
    s_->last_seq = f.seq;
    b.index = static_cast<int>(s_->next++);
    b.data = f.bytes.data();
    b.bytes_used = f.bytes.size();
    b.sequence = f.seq;
    b.flags = f.flags;
    b.tv_sec = f.t_ns / 1'000'000'000;
    b.tv_usec = (f.t_ns % 1'000'000'000) / 1000;
    ++s_->out;
    return true;
  }
  bool requeue(const NodeBuffer&) override {
    ++s_->requeued;
    --s_->out;
    return true;
  }

 private:
  FakeDevice& dev_;
  FakeScript* s_ = nullptr;
};

inline NodeFactory fake_factory(FakeDevice& dev) {
  return [&dev]() { return std::make_unique<FakeNode>(dev); };
}

inline NodeFormat video_format(uint32_t fourcc, int w, int h, double fps, int bpp) {
  NodeFormat f;
  f.fourcc = fourcc;
  f.width = w;
  f.height = h;
  f.fps = fps;
  f.stride = w * bpp;
  f.buffer_bytes = static_cast<size_t>(f.stride) * static_cast<size_t>(h);
  return f;
}
inline NodeFormat meta_format() {
  NodeFormat f;
  f.fourcc = kMetaFmtD4xx;
  f.buffer_bytes = 4096;
  return f;
}

// RGB8 -> YUYV (BT.601 limited range), the inverse of v4l2::yuyv_to_rgb up to rounding.
inline std::vector<uint8_t> rgb_to_yuyv(const uint8_t* rgb, int w, int h) {
  std::vector<uint8_t> out(static_cast<size_t>(w) * h * 2);
  auto c8 = [](double v) { return static_cast<uint8_t>(std::clamp(std::lround(v), 0L, 255L)); };
  for (int y = 0; y < h; ++y)
    for (int x = 0; x + 1 < w; x += 2) {
      const uint8_t* p = rgb + (static_cast<size_t>(y) * w + x) * 3;
      double Y[2], U = 0, V = 0;
      for (int k = 0; k < 2; ++k) {
        const double r = p[3 * k], g = p[3 * k + 1], b = p[3 * k + 2];
        Y[k] = 16 + 0.2568 * r + 0.5041 * g + 0.0979 * b;
        U += 0.5 * (128 - 0.1482 * r - 0.2910 * g + 0.4392 * b);
        V += 0.5 * (128 + 0.4392 * r - 0.3678 * g - 0.0714 * b);
      }
      uint8_t* o = out.data() + (static_cast<size_t>(y) * w + x) * 2;
      o[0] = c8(Y[0]);
      o[1] = c8(U);
      o[2] = c8(Y[1]);
      o[3] = c8(V);
    }
  return out;
}

// The camera's clock as the fakes tell it: device us = (host - h0) / (1 + skew).
struct DeviceTime {
  int64_t h0_ns = 1'000'000'000'000;  // host time of device zero... far from the frames' times
  double skew = 40e-6;                // the device clock runs 40 ppm slow
  uint32_t base_us = 0xFFF00000u;     // wraps about a second in
  uint32_t us(int64_t host_ns) const {
    const double d = static_cast<double>(host_ns - h0_ns) / (1 + skew) / 1000.0;
    return base_us + static_cast<uint32_t>(static_cast<int64_t>(std::floor(d)));
  }
};

// One frame's metadata buffer bytes, as uvcvideo would hand them over.
inline std::vector<uint8_t> frame_metadata(const DeviceTime& dt, int64_t t_mid_ns, int64_t exposure_ns,
                                           int64_t readout_ns, int64_t latency_ns, uint32_t counter,
                                           bool depth) {
  FrameMetadata m;
  const int64_t t_tx = t_mid_ns + exposure_ns / 2 + readout_ns;
  m.host_ns = t_tx + latency_ns;
  m.pts_us = dt.us(t_tx);
  m.scr_stc = m.pts_us;
  m.timing.flags = kTimingFrameCounterValid | kTimingSensorTimestampValid | kTimingExposureValid;
  m.timing.frame_counter = counter;
  m.timing.sensor_timestamp_us = dt.us(t_mid_ns);
  m.timing.exposure_time_us = static_cast<uint32_t>(exposure_ns / 1000);
  m.control.flags = depth ? kDepthControlExposureValid : kRgbControlManualExposureValid;
  m.control.exposure_us = static_cast<uint32_t>(exposure_ns / 1000);
  EncodeOptions o;
  o.depth_control = depth;
  std::vector<uint8_t> b(512);
  b.resize(encode_record(m, o, b.data(), b.size()));
  return b;
}

}  // namespace
}  // namespace kestrel::drivers::d4xx

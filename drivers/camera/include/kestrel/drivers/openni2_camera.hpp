// OpenNI2 RGB-D camera (Asus Xtion, PrimeSense Carmine, Orbbec Astra): colour
// and depth streams, depth registered to colour in the device, frame sync on,
// mirroring off. Device timestamps (microseconds, device clock) are mapped to
// the host clock with a ClockSync against each frame's arrival time, so frame
// times carry no host scheduling jitter.
//
// Thin transport: only what needs the SDK lives behind KESTREL_WITH_OPENNI2;
// the pairing and timestamp logic is plain code (tested without a device).
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/drivers/clock_sync.hpp"
#include "kestrel/drivers/sensor_rings.hpp"

namespace kestrel::drivers::openni2 {

struct Options {
  std::string uri;  // "" = first device
  int width = 640;
  int height = 480;
  int fps = 30;
  bool registration = true;  // depth registered to colour (IMAGE_REGISTRATION_DEPTH_TO_COLOR)
  bool frame_sync = true;    // setDepthColorSyncEnabled
  bool mirror = false;
  double rig_depth_scale_m = 0.001;    // DEPTH_1_MM is converted when the rig unit differs
  int64_t exposure_mid_offset_ns = 0;  // device stamp -> mid-exposure (calibration)
};

struct FrameMeta {
  int64_t t_ns = 0;  // host clock, from the device stamp
  int64_t t_device_us = 0;
  int64_t t_recv_ns = 0;
  uint32_t seq = 0;  // colour frame index
  uint32_t dropped_before = 0;
  int32_t exposure_us = 0;
};

enum class GrabResult { kFrame, kTimeout, kError };

struct Counters {
  uint64_t frames = 0;
  uint64_t dropped = 0;   // frame index gaps
  uint64_t unpaired = 0;  // depth and colour stamps too far apart
  uint64_t timeouts = 0;
  uint64_t errors = 0;
  uint64_t clock_jumps = 0;
};

// Pairs colour and depth device stamps: true when |t_c - t_d| <= half a frame.
inline bool stamps_pair(int64_t color_us, int64_t depth_us, int fps) {
  const int64_t half_us = fps > 0 ? 500'000 / fps : 16'000;
  const int64_t d = color_us - depth_us;
  return d <= half_us && -d <= half_us;
}

bool openni2_built();
// URIs and names of connected devices; `error` says why none could be listed.
std::vector<std::string> list_devices(std::string* error = nullptr);

class Camera {
 public:
  Camera();
  ~Camera();
  Camera(const Camera&) = delete;
  Camera& operator=(const Camera&) = delete;

  std::string open(const Options& o);  // "" or a message (no device, not built, mode unsupported)
  void close();
  bool is_open() const;
  GrabResult grab(int timeout_ms, ImageBuffer& rgb, ImageBuffer& depth, FrameMeta& meta);
  const Counters& counters() const { return counters_; }
  const ClockSync& clock_sync() const { return sync_; }

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  Options opt_;
  Counters counters_;
  ClockSync sync_;
  bool have_index_ = false;
  uint32_t next_index_ = 0;
};

}  // namespace kestrel::drivers::openni2

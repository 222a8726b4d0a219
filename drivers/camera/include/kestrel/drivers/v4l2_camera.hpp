// V4L2 camera: pure logic (format negotiation, buffer bookkeeping, sequence
// gaps, buffer timestamps, pixel conversions) that tests exercise without a
// device, and a thin transport (open/enumerate/mmap streaming) over ioctl.
//
// Timestamps: a buffer stamped V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC is on our
// clock already; TSTAMP_SRC_SOE means start of exposure, otherwise end of
// frame (UVC drivers: first/last packet of the frame). The frame time we
// publish is mid-exposure: SOE + exposure/2, or EOF - readout - exposure/2.
// Buffers without a monotonic stamp fall back to the dequeue time (flagged).
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/drivers/depth_registration.hpp"
#include "kestrel/drivers/sensor_rings.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::drivers::v4l2 {

constexpr uint32_t fourcc(char a, char b, char c, char d) {
  return static_cast<uint32_t>(static_cast<uint8_t>(a)) |
         (static_cast<uint32_t>(static_cast<uint8_t>(b)) << 8) |
         (static_cast<uint32_t>(static_cast<uint8_t>(c)) << 16) |
         (static_cast<uint32_t>(static_cast<uint8_t>(d)) << 24);
}
constexpr uint32_t kYuyv = fourcc('Y', 'U', 'Y', 'V');
constexpr uint32_t kMjpeg = fourcc('M', 'J', 'P', 'G');
constexpr uint32_t kGrey = fourcc('G', 'R', 'E', 'Y');
constexpr uint32_t kZ16 = fourcc('Z', '1', '6', ' ');  // UVC depth (RealSense D4xx): uint16 depth units
std::string fourcc_name(uint32_t f);
// "yuyv" | "mjpeg" | "grey" | "z16" -> fourcc; 0 for an unknown name.
uint32_t fourcc_from_name(const std::string& name);

// One (pixel format, frame size, frame interval) the device offers.
struct FormatOption {
  uint32_t fourcc = 0;
  int width = 0;
  int height = 0;
  double fps = 0;
};

struct FormatRequest {
  int width = 640;
  int height = 480;
  double fps = 30;
  std::vector<uint32_t> preferred;  // in order of preference
};

struct FormatChoice {
  bool ok = false;
  FormatOption option;
  std::string why;  // when !ok: what was asked and what the device offers
};

// Exact size required; the first preferred format that has it; among its
// rates the lowest one >= the request (else the highest available).
FormatChoice choose_format(const std::vector<FormatOption>& available, const FormatRequest& req);

// ---- timestamps --------------------------------------------------------------------
constexpr uint32_t kBufFlagTimestampMask = 0x0000e000;
constexpr uint32_t kBufFlagTimestampMonotonic = 0x00002000;
constexpr uint32_t kBufFlagTstampSrcMask = 0x00070000;
constexpr uint32_t kBufFlagTstampSrcSoe = 0x00010000;

struct BufferTime {
  int64_t t_ns = 0;        // the buffer's stamp on the host clock (or the dequeue time)
  bool monotonic = false;  // stamp was CLOCK_MONOTONIC
  bool start_of_exposure = false;
};
BufferTime buffer_time(int64_t tv_sec, int64_t tv_usec, uint32_t flags, int64_t t_dequeue_ns);
int64_t mid_exposure_ns(const BufferTime& t, int32_t exposure_us, int64_t readout_ns);

// ---- sequence numbers ----------------------------------------------------------------
// Frames missing before each buffer, from v4l2_buffer.sequence (u32, wraps).
class SequenceTracker {
 public:
  uint32_t update(uint32_t seq);  // returns the gap (0 = none)
  uint64_t dropped() const { return dropped_; }
  uint64_t restarts() const { return restarts_; }  // sequence went backwards (stream restarted)

 private:
  bool have_ = false;
  uint32_t expected_ = 0;
  uint64_t dropped_ = 0;
  uint64_t restarts_ = 0;
};

// ---- mmap buffer bookkeeping ------------------------------------------------------------
// Which driver buffers are queued (owned by the driver) or dequeued (owned by
// us). Every transition is checked, so a double queue or a lost buffer is a
// counted error instead of a hang.
class BufferBook {
 public:
  static constexpr int kMaxBuffers = 32;
  explicit BufferBook(int n = 0) { reset(n); }
  void reset(int n);
  bool on_queued(int index);    // false: index invalid or already queued
  bool on_dequeued(int index);  // false: index invalid or not queued
  int queued() const { return queued_; }
  int dequeued() const { return count_ - queued_; }
  int count() const { return count_; }
  uint64_t errors() const { return errors_; }
  // The driver can fill nothing when we hold every buffer.
  bool starved() const { return count_ > 0 && queued_ == 0; }

 private:
  std::array<bool, kMaxBuffers> queued_flags_{};
  int count_ = 0;
  int queued_ = 0;
  uint64_t errors_ = 0;
};

// ---- conversions (pure) ---------------------------------------------------------------
// YUYV 4:2:2 (BT.601, limited range) -> RGB8. Width must be even.
void yuyv_to_rgb(const uint8_t* src, int width, int height, int src_stride, uint8_t* dst, int dst_stride);
// Z16 depth units -> DepthU16 in rig units: value * src_scale / dst_scale,
// rounded; 0 stays 0 (invalid); results beyond 65535 become 0 (invalid).
void z16_to_depth(const uint8_t* src, int width, int height, int src_stride, double src_scale_m,
                  double dst_scale_m, uint16_t* dst);
void copy_rows(const uint8_t* src, int row_bytes, int height, int src_stride, uint8_t* dst);
// Z16 of a separate depth camera -> DepthU16 registered to the colour camera
// (drivers/depth): converted into `scratch` (the depth camera's size), then
// forward-projected into dst (the colour camera's size, dst_stride bytes a
// row). False when the frame does not match the registration's depth camera.
bool z16_to_registered_depth(const uint8_t* src, int width, int height, int src_stride, double src_scale_m,
                             double dst_scale_m, const DepthRegistration& reg, uint16_t* scratch,
                             uint16_t* dst, int dst_stride, RegistrationStats* stats = nullptr);

// ---- transport ---------------------------------------------------------------------------

struct DeviceInfo {
  std::string path;
  std::string card;
  std::string driver;
  std::string bus_info;
  std::vector<uint32_t> formats;
};
bool v4l2_built();
// Capture devices among /dev/video*; `error` set when none can be listed.
std::vector<DeviceInfo> list_devices(std::string* error = nullptr);

struct Options {
  std::string device;  // /dev/videoN
  FormatRequest request;
  int buffers = 4;
  int64_t readout_ns = 0;            // sensor readout time, for end-of-frame stamps
  double depth_scale_m = 0.001;      // device depth unit (Z16)
  double rig_depth_scale_m = 0.001;  // Rig::depth.scale_m_per_unit
  // A Z16 node of a separate depth camera (a RealSense depth stream is not
  // registered to its colour stream over UVC): present = its frames are
  // registered to `colour` (the rig's camera) before they leave the driver.
  DepthCamera depth_camera;
  CameraIntrinsics colour;
};

struct FrameMeta {
  int64_t t_ns = 0;         // mid-exposure, host clock
  int64_t t_buffer_ns = 0;  // the raw buffer stamp
  int64_t t_recv_ns = 0;
  uint32_t seq = 0;  // driver sequence
  uint32_t dropped_before = 0;
  int32_t exposure_us = 0;  // 0 unknown
  bool start_of_exposure = false;
  bool monotonic = false;
};

enum class GrabResult { kFrame, kTimeout, kError };

struct Counters {
  uint64_t frames = 0;
  uint64_t dropped = 0;  // sequence gaps
  uint64_t timeouts = 0;
  uint64_t errors = 0;         // ioctl failures, bookkeeping errors
  uint64_t non_monotonic = 0;  // buffers stamped on another clock
  uint64_t decode_errors = 0;  // MJPEG that did not decode
};

class Camera {
 public:
  Camera() = default;
  ~Camera();
  Camera(const Camera&) = delete;
  Camera& operator=(const Camera&) = delete;

  // Opens, negotiates, maps buffers, starts streaming. "" or a message naming
  // the device and what failed (or "not built").
  std::string open(const Options& o);
  void close();
  bool is_open() const { return fd_ >= 0; }
  const FormatOption& format() const { return active_; }
  const std::vector<FormatOption>& offered() const { return offered_; }
  PixelFormat output_format() const;

  // Waits up to timeout_ms for a frame, converts it into `dst` (sized at
  // start-up) and re-queues the driver buffer at once.
  GrabResult grab(int timeout_ms, ImageBuffer& dst, FrameMeta& meta);
  const Counters& counters() const { return counters_; }

 private:
  struct Mapped {
    void* ptr = nullptr;
    size_t len = 0;
  };
  int fd_ = -1;
  Options opt_;
  FormatOption active_;
  std::vector<FormatOption> offered_;
  int stride_ = 0;
  std::vector<Mapped> maps_;
  BufferBook book_;
  SequenceTracker seq_;
  Counters counters_;
  bool exposure_ctrl_ok_ = true;
  std::vector<uint8_t> decode_scratch_;
  std::unique_ptr<DepthRegistration> registration_;  // sized at open()
  std::vector<uint16_t> depth_scratch_;
};

}  // namespace kestrel::drivers::v4l2

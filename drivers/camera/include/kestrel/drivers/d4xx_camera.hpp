// RealSense D4xx over V4L2: colour, Z16 depth and infrared nodes, each with
// its UVC metadata node, frames stamped with the camera's hardware clock.
//
// Layers (the house driver pattern):
//  - transport: `Node`, one V4L2 node (video or metadata) with mmap buffers.
//    make_v4l2_node() is the kernel's; tests fake it with byte fixtures.
//  - protocol: `Stream` pairs each frame buffer with its metadata buffer (the
//    uvcvideo driver gives the metadata buffer the frame's sequence number)
//    and stamps it; `Camera` runs the streams and pairs depth (and infrared)
//    with the image stream by hardware time.
//  - parser: d4xx_metadata.hpp (pure).
//
// Time (docs/realsense.md, "Time"): md_capture_timing.sensor_timestamp is the
// middle of the exposure on the D4xx's microsecond clock, the clock its IMU
// stamps samples with. The UVC header's PTS (same clock, start of transmit)
// and the metadata record's host time (uvcvideo, CLOCK_MONOTONIC, when the
// header arrived) are one observation per frame of that clock against the
// host's with only USB latency between them: they feed one ClockSync, whose
// line maps every stream's sensor timestamps and is published for the IMU
// driver (SharedDeviceClock), so frames and IMU are in one clock.
// A frame whose metadata is missing, corrupt or without a sensor timestamp is
// stamped from its kernel buffer time instead (counted per cause).
//
// Real time: open() sizes everything; grab() makes no allocation and takes no
// lock; it blocks only in the nodes' wait (poll on the device descriptor).
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/drivers/clock_sync.hpp"
#include "kestrel/drivers/d4xx_metadata.hpp"
#include "kestrel/drivers/depth_registration.hpp"
#include "kestrel/drivers/sensor_rings.hpp"
#include "kestrel/drivers/shared_clock.hpp"
#include "kestrel/drivers/v4l2_camera.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::drivers::d4xx {

constexpr uint32_t kY8i = v4l2::fourcc('Y', '8', 'I', ' ');  // left IR low byte, right IR high byte
constexpr uint32_t kRgb24 = v4l2::fourcc('R', 'G', 'B', '3');
constexpr const char* kDefaultCardMatch = "RealSense";

// ---- transport seam ------------------------------------------------------------------
struct NodeBuffer {
  int index = -1;
  const uint8_t* data = nullptr;
  size_t bytes_used = 0;
  uint32_t sequence = 0;
  uint32_t flags = 0;  // v4l2_buffer.flags (timestamp source, error)
  int64_t tv_sec = 0;
  int64_t tv_usec = 0;
};

struct NodeRequest {
  bool metadata = false;       // a V4L2_BUF_TYPE_META_CAPTURE node
  v4l2::FormatRequest format;  // video nodes
  int buffers = 4;
};

struct NodeFormat {
  uint32_t fourcc = 0;  // pixel format, or the metadata format (kMetaFmtUvc / kMetaFmtD4xx)
  int width = 0;
  int height = 0;
  double fps = 0;
  int stride = 0;  // bytes per row (video)
  size_t buffer_bytes = 0;
};

enum class NodeWait { kReady, kTimeout, kError };

class Node {
 public:
  virtual ~Node() = default;
  // "" or a message naming the path and what failed.
  virtual std::string open(const std::string& path, const NodeRequest& r) = 0;
  virtual void close() = 0;
  virtual bool is_open() const = 0;
  virtual const NodeFormat& format() const = 0;
  // Until a buffer can be dequeued (poll on the descriptor).
  virtual NodeWait wait(int timeout_ms) = 0;
  // Non-blocking; false when no buffer is ready.
  virtual bool dequeue(NodeBuffer& b) = 0;
  virtual bool requeue(const NodeBuffer& b) = 0;
};
using NodeFactory = std::function<std::unique_ptr<Node>()>;
std::unique_ptr<Node> make_v4l2_node();  // the kernel's (reports "not built" without V4L2)

// ---- finding a D4xx's nodes -----------------------------------------------------------
struct ProbedNode {
  std::string path;  // /dev/videoN
  int minor = -1;    // N
  std::string card;
  std::string bus_info;
  bool metadata = false;  // a metadata capture node
  std::vector<uint32_t> formats;
};
struct NodeSet {
  std::string bus_info;
  std::string card;
  std::string color, color_meta, depth, depth_meta, infrared, infrared_meta;
};
// Groups the nodes of each camera whose card contains `card_match` (by USB
// bus); a metadata node belongs to the video node just before it (uvcvideo
// registers each streaming interface's metadata node right after its video
// node). Depth: the node offering Z16; infrared: Y8I or GREY without Z16;
// colour: YUYV without Z16. One entry per camera found.
std::vector<NodeSet> group_d4xx_nodes(const std::vector<ProbedNode>& nodes, const std::string& card_match);
std::vector<ProbedNode> probe_v4l2_nodes(std::string* error = nullptr);  // the kernel's /dev/video*

// ---- the device clock ------------------------------------------------------------------
// 32-bit microsecond stamps (PTS, sensor timestamp) onto one 64-bit line:
// each is unwrapped to the value nearest the last PTS seen, so wraps (every
// 71.6 min) and the small order differences between streams both hold.
class DeviceClock {
 public:
  explicit DeviceClock(const ClockSyncOptions& o = ClockSyncOptions{}) : sync_(o) {}
  // One observation (UVC header PTS, host time of the header's arrival).
  void observe(uint32_t pts_us, int64_t host_ns);
  bool valid() const { return sync_.valid(); }
  int64_t unwrap_ns(uint32_t device_us) const;
  int64_t to_host_ns(uint32_t device_us) const { return sync_.to_host_ns(unwrap_ns(device_us)); }
  const ClockSync& sync() const { return sync_; }
  uint64_t observations() const { return observations_; }
  void publish_to(SharedDeviceClock* shared) { shared_ = shared; }

 private:
  ClockSync sync_;
  bool have_ = false;
  uint32_t last_us_ = 0;
  int64_t last_unwrapped_us_ = 0;
  uint64_t observations_ = 0;
  SharedDeviceClock* shared_ = nullptr;
};

// ---- one stream: frame + metadata ---------------------------------------------------------
enum class StreamKind { kColor, kDepth, kInfrared };
const char* stream_name(StreamKind k);

enum class StampSource {
  kHardware,           // sensor timestamp mapped through the device clock
  kKernelNoMetadata,   // no metadata buffer for this frame
  kKernelCorrupt,      // its metadata did not parse
  kKernelNoTimestamp,  // metadata without a valid sensor timestamp (or the clock not yet valid)
};

struct StreamCounters {
  uint64_t frames = 0;
  uint64_t dropped = 0;  // sequence gaps (frames the kernel or camera lost)
  uint64_t restarts = 0;
  uint64_t errors = 0;  // buffers flagged bad, wrong size, requeue failures
  uint64_t timeouts = 0;
  uint64_t hardware_stamps = 0;
  uint64_t metadata_missing = 0;  // frames stamped from the kernel: no metadata buffer
  uint64_t metadata_corrupt = 0;  //   ... metadata rejected by the parser
  uint64_t metadata_no_timestamp = 0;
  uint64_t metadata_orphans = 0;    // metadata buffers whose frame never came
  uint64_t frame_counter_gaps = 0;  // md_capture_timing.frame_counter jumps (camera-side drops)
};

struct StreamFrame {
  int64_t t_ns = 0;          // mid-exposure, host clock
  int64_t t_device_ns = -1;  // mid-exposure, device clock unwrapped (-1 without metadata)
  int64_t t_buffer_ns = 0;   // the kernel's buffer stamp
  int64_t t_recv_ns = 0;
  uint32_t seq = 0;
  uint32_t frame_counter = 0;
  int32_t exposure_us = 0;
  StampSource source = StampSource::kKernelNoMetadata;
  ParseStatus metadata_status = ParseStatus::kEmpty;
};

// A frame buffer and its metadata, paired by sequence number. Metadata
// buffers are parsed when dequeued and kept by sequence for a few frames
// (they arrive just before their frame; a late one is waited for up to
// metadata_wait_ms).
class Stream {
 public:
  static constexpr int kPendingMeta = 8;
  Stream(StreamKind kind, std::unique_ptr<Node> video, std::unique_ptr<Node> meta);
  StreamKind kind() const { return kind_; }
  Node& video() { return *video_; }
  bool has_metadata() const { return meta_ != nullptr && meta_->is_open(); }
  // The metadata node's format ('D4XX', or 'UVCH' which carries no sensor timestamps); 0 without one.
  uint32_t metadata_format() const { return has_metadata() ? meta_->format().fourcc : 0; }

  // Waits for a frame and stamps it; the caller converts b's bytes, then
  // release(b) hands the buffer back to the driver. `clock` is fed when
  // `feeds_clock` (the lead stream).
  enum class Result { kFrame, kTimeout, kError };
  Result next(int timeout_ms, int metadata_wait_ms, DeviceClock& clock, bool feeds_clock, int64_t readout_ns,
              NodeBuffer& b, StreamFrame& out);
  void release(const NodeBuffer& b);
  void count_error() { ++c_.errors; }
  const StreamCounters& counters() const { return c_; }

  // The pure part of grab(), public for tests: drains the metadata node into
  // the pending table, then stamps `b` (a dequeued frame buffer).
  void drain_metadata();
  void stamp(const NodeBuffer& b, DeviceClock& clock, bool feeds_clock, int64_t readout_ns, int64_t t_recv_ns,
             StreamFrame& out);
  bool pending_has(uint32_t seq) const;

 private:
  struct Pending {
    bool used = false;
    uint32_t seq = 0;
    ParseStatus status = ParseStatus::kEmpty;
    FrameMetadata md;
  };
  StreamKind kind_;
  std::unique_ptr<Node> video_;
  std::unique_ptr<Node> meta_;
  std::array<Pending, kPendingMeta> pending_{};
  v4l2::SequenceTracker seq_;
  bool have_counter_ = false;
  uint32_t last_counter_ = 0;
  StreamCounters c_;
};

// ---- the camera ------------------------------------------------------------------------------
struct StreamOptions {
  bool enabled = false;
  std::string video_device;  // /dev/videoN
  std::string meta_device;   // "" = no metadata: kernel stamps
  v4l2::FormatRequest request;
};

struct Options {
  StreamOptions color;     // YUYV (or RGB3) -> Rgb8
  StreamOptions depth;     // Z16 -> DepthU16 (registered to the image camera when depth_camera.present)
  StreamOptions infrared;  // GREY (Infrared 1) or Y8I (Infrared 1 + 2) -> Gray8
  bool infrared_is_image = false;  // the rig's camera is Infrared 1 (depth is in its frame already)
  int buffers = 4;
  int metadata_wait_ms = 2;
  int64_t readout_ns = 0;  // for kernel (end-of-frame) fallback stamps
  double depth_unit_m = 0.001;
  double rig_depth_scale_m = 0.001;
  DepthCamera depth_camera;       // rig.depth_camera: registration of depth to colour
  CameraIntrinsics image_camera;  // rig.rgb
  int64_t pair_tolerance_ns = 0;  // depth/IR to image by device time; 0 = half a frame period
  ClockSyncOptions clock;
  SharedDeviceClock* shared_clock = nullptr;  // published for the IMU driver
};

struct Counters {
  StreamCounters color, depth, infrared;
  uint64_t sets = 0;           // frames delivered
  uint64_t unpaired = 0;       // image frames delivered without a depth partner
  uint64_t depth_skipped = 0;  // depth frames older than any image partner
  uint64_t clock_jumps = 0;
};

struct Frame {
  StreamFrame image_meta;
  const ImageBuffer* image = nullptr;  // Rgb8 (colour) or Gray8 (Infrared 1)
  const ImageBuffer* depth = nullptr;  // nullptr when not paired / not enabled
  const ImageBuffer* ir1 = nullptr;    // infrared enabled (and not the image)
  const ImageBuffer* ir2 = nullptr;    // with Y8I
  StreamFrame depth_meta;
};

class Camera {
 public:
  explicit Camera(NodeFactory factory = make_v4l2_node);
  ~Camera();
  Camera(const Camera&) = delete;
  Camera& operator=(const Camera&) = delete;

  // Opens every enabled stream and its metadata node, sizes every buffer.
  // "" or every problem, one per line, naming the node.
  std::string open(const Options& o);
  void close();
  bool is_open() const { return image_ != nullptr; }

  // Waits up to timeout_ms for the next image frame, then its depth (and IR)
  // partner by device time. No allocation.
  enum class Result { kFrame, kTimeout, kError };
  Result grab(int timeout_ms, Frame& out);
  Counters counters() const;
  const DeviceClock& clock() const { return clock_; }
  std::string report() const;  // one line per stream: counters and stamp sources

 private:
  bool convert(StreamKind kind, const NodeBuffer& b, const NodeFormat& f, ImageBuffer& dst, ImageBuffer* ir2);
  Stream::Result grab_partner(Stream& s, int timeout_ms, const StreamFrame& lead, ImageBuffer& dst,
                              ImageBuffer* ir2, StreamFrame& meta, bool& paired);

  NodeFactory factory_;
  Options opt_;
  std::unique_ptr<Stream> color_, depth_, infrared_;
  Stream* image_ = nullptr;  // the lead stream (colour, or infrared)
  DeviceClock clock_;
  ImageBuffer image_buf_, depth_buf_, ir1_buf_, ir2_buf_;
  // A partner frame newer than its lead waits here for the next lead.
  bool depth_held_ = false, ir_held_ = false;
  StreamFrame depth_held_meta_, ir_held_meta_;
  std::unique_ptr<DepthRegistration> registration_;
  std::vector<uint16_t> depth_scratch_;
  int64_t period_ns_ = 33'333'333;
  uint64_t sets_ = 0, unpaired_ = 0, depth_skipped_ = 0;
};

}  // namespace kestrel::drivers::d4xx

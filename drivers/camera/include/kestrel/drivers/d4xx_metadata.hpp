// RealSense D4xx per-frame metadata as the uvcvideo metadata node delivers it
// (V4L2_BUF_TYPE_META_CAPTURE, format 'UVCH' or 'D4XX'): a pure parser and
// its inverse, the encoder the tests and fuzz seeds build fixtures with.
//
// One metadata buffer holds one or more records (linux/uvcvideo.h):
//   u64 ns        host CLOCK_MONOTONIC when uvcvideo decoded the payload header
//   u16 sof       USB frame number at that moment
//   the UVC payload header as the camera sent it (UVC 1.5, 2.4.3.3):
//     u8  bLength        header length, including these two bytes
//     u8  bmHeaderInfo   FID EOF PTS SCR RES STI ERR EOH (bits 0..7)
//     u32 dwPresentationTime            when PTS: the frame's device time, us
//     u32 scrSourceClock + u16 SOF      when SCR
//     vendor bytes up to bLength: on a D4xx, Intel's metadata blocks
// so a record is 10 + bLength bytes. Multi-byte fields are little-endian.
//
// The D4xx blocks (as librealsense documents them, src/metadata.h): each is
//   u32 md_type_id, u32 md_size, body
// where md_size is the whole block including those 8 bytes (the kernel's
// V4L2_META_FMT_D4XX page: "Size in bytes, include ID"; librealsense's
// validity check compares md_size with sizeof(md_capture_timing), header
// included, though a comment there says otherwise).
// The kernel passes these vendor bytes only with the 'D4XX' metadata format,
// which uvcvideo offers for the D4xx models in its device table; with 'UVCH'
// it cuts the header after PTS and SCR (kNoD4xxBlocks below).
// md_capture_timing (0x80000001) carries the frame's hardware sensor
// timestamp: the middle of the exposure in microseconds of the camera's own
// clock, the clock the D4xx's HID IMU stamps its samples with.
//
// Every length is checked against the bytes there are; nothing is read past
// `size`. No allocation (the real-time camera thread calls it per frame).
#pragma once

#include <cstddef>
#include <cstdint>

namespace kestrel::drivers::d4xx {

// V4L2 metadata formats: linux/videodev2.h V4L2_META_FMT_UVC and V4L2_META_FMT_D4XX
// (same layout; the second tells a D4xx-aware kernel to pass the vendor bytes).
constexpr uint32_t kMetaFmtUvc = 0x48435655;   // 'UVCH'
constexpr uint32_t kMetaFmtD4xx = 0x58583444;  // 'D4XX'

// md_type ids (librealsense src/metadata.h).
enum class BlockId : uint32_t {
  kDepthControl = 0x80000000,
  kCaptureTiming = 0x80000001,
  kConfiguration = 0x80000002,
  kIntelStat = 0x80000003,
  kFisheyeControl = 0x80000004,
  kRgbControl = 0x80000005,
  kCaptureStats = 0x00000003,
};

// Sizes of the blocks' wire layouts, header included.
constexpr size_t kBlockHeaderBytes = 8;
constexpr size_t kCaptureTimingBytes = 40;  // header + 8 x u32
constexpr size_t kConfigurationBytes = 40;  // header + version, flags, hw, sku, cookie, format, w, h, fps,
                                            // trigger, calibration count, 6 reserved
constexpr size_t kDepthControlBytes = 60;   // header + 13 x u32
constexpr size_t kRgbControlBytes = 72;     // header + 16 x u32
constexpr size_t kRecordPrefixBytes = 10;   // ns + sof before the payload header
constexpr size_t kUvcHeaderMaxBytes = 255;

// md_capture_timing.flags: which fields the firmware filled.
constexpr uint32_t kTimingFrameCounterValid = 1u << 0;
constexpr uint32_t kTimingSensorTimestampValid = 1u << 1;
constexpr uint32_t kTimingReadoutValid = 1u << 2;
constexpr uint32_t kTimingExposureValid = 1u << 3;
constexpr uint32_t kTimingFrameIntervalValid = 1u << 4;
constexpr uint32_t kTimingPipeLatencyValid = 1u << 5;
// md_depth_control.flags bit 1 / md_rgb_control.flags bit 10: the manual exposure field is valid.
constexpr uint32_t kDepthControlExposureValid = 1u << 1;
constexpr uint32_t kRgbControlManualExposureValid = 1u << 10;

struct CaptureTiming {
  bool present = false;
  uint32_t version = 0;
  uint32_t flags = 0;
  uint32_t frame_counter = 0;
  uint32_t sensor_timestamp_us = 0;  // mid-exposure, device clock (wraps every 2^32 us = 71.6 min)
  uint32_t readout_time_us = 0;
  uint32_t exposure_time_us = 0;
  uint32_t frame_interval_us = 0;
  uint32_t pipe_latency_us = 0;
};

struct Configuration {
  bool present = false;
  uint32_t flags = 0;
  uint8_t hw_type = 0;
  uint8_t sku_id = 0;
  uint16_t format = 0;
  uint16_t width = 0;
  uint16_t height = 0;
  uint16_t fps = 0;
  uint16_t calibration_count = 0;
};

// The exposure the firmware reports in its control block (depth: us; RGB: 100 us units).
struct ControlExposure {
  bool present = false;
  bool rgb = false;
  uint32_t flags = 0;
  uint32_t exposure_us = 0;  // converted to us
  uint32_t laser_power = 0;  // depth only
};

struct FrameMetadata {
  int64_t host_ns = 0;  // uvc_meta_buf.ns (CLOCK_MONOTONIC)
  uint16_t usb_sof = 0;
  uint8_t header_length = 0;  // bLength
  uint8_t header_info = 0;    // bmHeaderInfo
  bool has_pts = false;
  bool has_scr = false;
  uint32_t pts_us = 0;  // dwPresentationTime: D4xx, device clock us at readout/transmit start
  uint32_t scr_stc = 0;
  uint16_t scr_sof = 0;
  CaptureTiming timing;
  Configuration configuration;
  ControlExposure control;
  int records = 0;         // records in the buffer
  int blocks = 0;          // D4xx blocks walked in the record used
  int unknown_blocks = 0;  // ids this parser does not read (skipped by their size)

  // The hardware sensor timestamp, when the firmware says it is valid.
  bool has_sensor_timestamp() const {
    return timing.present && (timing.flags & kTimingSensorTimestampValid) != 0;
  }
  // Exposure in us from capture timing, else the control block; 0 unknown.
  uint32_t exposure_us() const;
};

enum class ParseStatus {
  kOk,
  kEmpty,            // no bytes (a metadata buffer the driver returned empty)
  kTruncatedRecord,  // fewer bytes than the 10-byte prefix + bLength
  kBadHeaderLength,  // bLength < 2, or too short for the PTS / SCR its flags announce
  kBadBlock,         // a D4xx block whose size is < 8 or runs past the header
  kBadBlockSize,     // a known block too short for its fields
  kNoD4xxBlocks,     // a valid UVC header with no vendor bytes (a non-D4xx camera, or a kernel
                     // that does not pass them)
};
const char* parse_status_name(ParseStatus s);

// Parses a whole metadata buffer (bytesused bytes). Every record must parse;
// the first with D4xx blocks is the one described (else the first). On an
// error `out` holds what was read before it.
ParseStatus parse_metadata_buffer(const uint8_t* data, size_t size, FrameMetadata& out);

// One record at `data`; `consumed` = its size when kOk or kNoD4xxBlocks.
ParseStatus parse_record(const uint8_t* data, size_t size, FrameMetadata& out, size_t& consumed);

// The D4xx blocks alone (the vendor bytes of a payload header).
ParseStatus parse_blocks(const uint8_t* data, size_t size, FrameMetadata& out);

// ---- the inverse: fixtures for tests, fake device nodes and fuzz seeds ------------
struct EncodeOptions {
  bool pts = true;
  bool scr = true;
  bool capture_timing = true;
  bool configuration = true;
  bool depth_control = false;  // else an RGB control block, when `control` is on
  bool control = true;
};
// Writes one record; returns its size, or 0 when `capacity` is too small.
size_t encode_record(const FrameMetadata& m, const EncodeOptions& o, uint8_t* out, size_t capacity);

}  // namespace kestrel::drivers::d4xx

// Recorded sensor data as one stream of records, whatever the file format.
//
// Replay, eval, sim export and convert all read through LogSource, so a new
// format is one new reader and nothing else changes. Readers run outside the
// real-time threads (the replay feeder copies their output into the rings), so
// they may allocate.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/msgs.hpp"

namespace kestrel::drivers {

// An image as stored in a log: pixels packed row after row (stride = width * bpp).
struct LogImage {
  int64_t t_ns = 0;
  int64_t t_recv_ns = 0;
  uint32_t seq = 0;
  int32_t exposure_us = 0;
  int width = 0;
  int height = 0;
  PixelFormat format = PixelFormat::kGray8;
  std::vector<uint8_t> pixels;

  ImageView view() const {
    return ImageView{width, height, width * bytes_per_pixel(format), format, pixels.data()};
  }
};

enum class RecordType : uint16_t {
  kImu = 1,
  kRgb = 2,
  kDepth = 3,
  kGroundTruth = 4,
  kEvent = 5,
  // The right image of a stereo pair (Rig::stereo), paired with the kRgb
  // record of the same time (klog type 6, the image payload).
  kRight = 6,
};

// One record; only the member named by `type` is meaningful.
struct LogRecord {
  RecordType type = RecordType::kImu;
  uint64_t offset = 0;  // byte offset (klog) or line number (text formats) it came from
  ImuSample imu;
  LogImage image;  // kRgb, kDepth or kRight
  GroundTruthPose gt;
  Event event;
};

// Something wrong in the input, reported with where it is. Readers never
// throw on bad data after open(): they record a problem and carry on.
struct LogProblem {
  std::string where;  // "file:line" or "file@byte-offset"
  std::string kind;   // short machine-readable tag: "truncated", "bad-crc", "bad-length", "missing-file", ...
  std::string detail;
};

class LogSource {
 public:
  virtual ~LogSource() = default;
  virtual const Rig& rig() const = 0;
  // Next record in time order as the format stores it; false at the end.
  virtual bool next(LogRecord& out) = 0;
  // Back to the first record (for two-pass tools such as eval and bench).
  virtual void rewind() = 0;
  virtual const std::vector<LogProblem>& problems() const = 0;
  virtual std::string format_name() const = 0;
};

}  // namespace kestrel::drivers

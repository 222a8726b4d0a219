// The Kestrel log (.klog): single file, append-only, versioned, CRC-checked
// records. The byte layout is specified in docs/log-format.md.
#pragma once

#include <cstdint>
#include <cstdio>
#include <string>

#include "kestrel/drivers/log_source.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::drivers {

constexpr uint32_t kKlogVersion = 1;

// Writes records in the order it is given them. Not thread-safe: the logger
// thread owns it. Each record is written with one fwrite and flushed, so a
// crash loses at most the record being written.
class KlogWriter {
 public:
  KlogWriter() = default;
  ~KlogWriter();
  KlogWriter(const KlogWriter&) = delete;
  KlogWriter& operator=(const KlogWriter&) = delete;

  // Creates/truncates `path` and writes the file header with the rig.
  // Throws std::runtime_error naming the path on failure.
  void open(const std::string& path, const Rig& rig);
  void close();
  bool is_open() const { return file_ != nullptr; }

  void write_imu(const ImuSample& s);
  void write_image(RecordType type, const LogImage& img);   // kRgb or kDepth
  void write_image(RecordType type, int64_t t_ns, int64_t t_recv_ns, uint32_t seq, int32_t exposure_us,
                   const ImageView& view);
  void write_ground_truth(const GroundTruthPose& gt);
  void write_event(const Event& e);

  // Flush policy: by default every record is flushed to the OS (fflush);
  // set_fsync_every(n) additionally fsyncs every n records.
  void set_fsync_every(uint32_t n) { fsync_every_ = n; }
  uint64_t records_written() const { return records_; }
  uint64_t bytes_written() const { return bytes_; }

 private:
  void write_record(RecordType type, const uint8_t* payload, uint32_t size);
  std::FILE* file_ = nullptr;
  std::string path_;
  uint64_t records_ = 0;
  uint64_t bytes_ = 0;
  uint32_t fsync_every_ = 0;
  std::string scratch_;
};

}  // namespace kestrel::drivers

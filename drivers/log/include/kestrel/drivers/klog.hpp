// The Kestrel log (.klog): single file, append-only, versioned, CRC-checked
// records. The byte layout is specified in docs/log-format.md.
#pragma once

#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/drivers/camera_time_shift.hpp"
#include "kestrel/drivers/klog_image_codec.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::drivers {

// 2: image pixels may be compressed (docs/log-format.md). Version 1 files
// (raw images) still read, and the writer can still produce them.
constexpr uint32_t kKlogVersion = 2;

// The compression every writer uses unless told otherwise (the config's
// `record:` default; docs/log-format.md says what it was chosen on).
inline klog::ImageCompression default_image_compression() { return klog::ImageCompression{}; }

// Writes records in the order it is given them. Not thread-safe: the logger
// thread owns it. Each record is written with one fwrite and flushed, so a
// crash loses at most the record being written. Images are compressed in
// write_image, on the calling (the logger's) thread.
class KlogWriter {
 public:
  struct Options {
    klog::ImageCompression compression = default_image_compression();
    // 1 writes the old layout (raw images only; compression must be off):
    // for tests and for readers that predate version 2.
    uint32_t version = kKlogVersion;
  };

  KlogWriter() = default;
  ~KlogWriter();
  KlogWriter(const KlogWriter&) = delete;
  KlogWriter& operator=(const KlogWriter&) = delete;

  // Creates/truncates `path` and writes the file header with the rig.
  // Throws std::runtime_error naming the path on failure.
  // Throws std::invalid_argument for an unknown version or compression in a version 1 file.
  void open(const std::string& path, const Rig& rig);
  void open(const std::string& path, const Rig& rig, const Options& options);
  void close();
  bool is_open() const { return file_ != nullptr; }

  void write_imu(const ImuSample& s);
  void write_image(RecordType type, const LogImage& img);  // kRgb or kDepth
  void write_image(RecordType type, int64_t t_ns, int64_t t_recv_ns, uint32_t seq, int32_t exposure_us,
                   const ImageView& view);
  void write_ground_truth(const GroundTruthPose& gt);
  void write_event(const Event& e);

  // Changes the compression of the images that follow (a version 2 file can
  // mix codecs record by record). Throws std::invalid_argument on a version 1 file.
  void set_compression(const klog::ImageCompression& c);

  // Flush policy: by default every record is flushed to the OS (fflush);
  // set_fsync_every(n) additionally fsyncs every n records.
  void set_fsync_every(uint32_t n) { fsync_every_ = n; }
  uint64_t records_written() const { return records_; }
  uint64_t bytes_written() const { return bytes_; }
  // Image pixel bytes given and written (their ratio is the compression's).
  uint64_t image_bytes_raw() const { return image_raw_; }
  uint64_t image_bytes_stored() const { return image_stored_; }
  const Options& options() const { return options_; }

 private:
  void write_record(RecordType type, const uint8_t* payload, uint32_t size);
  // Records are assembled in scratch_ (header slot, then payload) so that
  // each one leaves in a single fwrite.
  void begin_record();
  void finish_record(RecordType type);
  std::FILE* file_ = nullptr;
  std::string path_;
  uint64_t records_ = 0;
  uint64_t bytes_ = 0;
  uint32_t fsync_every_ = 0;
  uint64_t image_raw_ = 0;
  uint64_t image_stored_ = 0;
  Options options_;
  klog::ImageEncoder encoder_;
  std::string scratch_;
};

// Reads a .klog file one record at a time (one payload in memory, buffers
// reused). Damage after the file header never throws: each problem becomes a
// LogProblem "file@offset" and the reader resynchronises on the next sync
// marker whose record passes its CRC, so every intact record is replayed.
class KlogReader final : public LogSource {
 public:
  struct Options {
    // A damaged file header normally makes open fail because the rig is lost.
    // With salvage on, the reader reports "bad-header", uses a default Rig and
    // still recovers the records.
    bool salvage_bad_header = false;
  };

  // Throws std::runtime_error naming the path when the file cannot be opened,
  // is not a klog, has a damaged header (unless salvaging) or a newer version.
  explicit KlogReader(const std::string& path);
  KlogReader(const std::string& path, const Options& options);
  // Reads from a copy of an in-memory image of a file; `name` stands in for
  // the path in problems (tests and the fuzz target).
  static std::unique_ptr<KlogReader> from_memory(const uint8_t* data, size_t size, const std::string& name,
                                                 const Options& options);
  ~KlogReader() override;
  KlogReader(const KlogReader&) = delete;
  KlogReader& operator=(const KlogReader&) = delete;

  const Rig& rig() const override { return rig_; }
  // Camera stamps come out on the IMU's clock (the rig's
  // time_offset_cam_imu_ns added; the file keeps them as recorded).
  bool next(LogRecord& out) override;
  void rewind() override;
  const std::vector<LogProblem>& problems() const override { return problems_; }
  std::string format_name() const override { return "klog"; }

  uint32_t version() const { return version_; }
  uint64_t file_size() const { return size_; }
  uint64_t data_offset() const { return data_start_; }  // first byte after the file header

 private:
  struct RecordHeader {
    uint32_t sync = 0;
    uint16_t type = 0;
    uint16_t flags = 0;
    uint32_t length = 0;
    uint32_t crc = 0;
  };
  KlogReader(std::string name, std::vector<uint8_t> memory, const Options& options);
  void open_header(const Options& options);
  bool read_at(uint64_t offset, void* dst, size_t n);
  bool read_header_at(uint64_t offset, RecordHeader& h);
  // Reads the payload of a header that fits the file and checks its CRC.
  bool load_payload(uint64_t offset, const RecordHeader& h);
  // The offset of the next record at or after `from` that passes its CRC
  // (payload left in payload_), or size_ when there is none.
  uint64_t resync(uint64_t from, RecordHeader& h);
  bool decode(uint64_t offset, const RecordHeader& h, LogRecord& out, std::string& why);
  bool next_as_stored(LogRecord& out);
  void problem(uint64_t offset, const char* kind, std::string detail);

  std::string name_;
  int fd_ = -1;
  std::vector<uint8_t> memory_;  // in-memory source when fd_ < 0
  uint64_t size_ = 0;
  uint64_t data_start_ = 0;
  uint64_t pos_ = 0;
  uint64_t reported_until_ = 0;  // problems before this offset were already reported (rewind)
  uint32_t version_ = 0;
  Rig rig_;
  std::vector<LogProblem> problems_;
  std::vector<uint8_t> payload_;
  // Read-ahead window for headers and small payloads.
  std::vector<uint8_t> window_;
  uint64_t window_offset_ = 0;
  size_t window_size_ = 0;
  // A record found by resync, already loaded, to be returned next.
  bool pending_ = false;
  RecordHeader pending_header_;
  // Non-zero camera-IMU offset: records re-sorted after the shift.
  CameraTimeShift shift_;
  klog::ImageDecoder decoder_;
  LogRecord scratch_;
  bool stored_done_ = false;
};

}  // namespace kestrel::drivers

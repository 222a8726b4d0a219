// KlogLogger: records to a .klog from real-time threads without making them
// wait for the disk.
//
// Producers (driver threads) call log_*(): a copy into a preallocated ring
// slot or into the image staging buffer, no lock, no allocation, no I/O; when
// a ring or the staging buffer is full the record is dropped and counted,
// never waited for. A non-real-time logger thread drains the rings, oldest
// time stamp first, into a KlogWriter (one fwrite + fflush per record).
//
// Images are staged in one byte ring (each frame takes its own size, not the
// largest frame's), so the staging memory is what rides out a disk stall:
// buffer_bytes / (bytes per second of images) seconds. docs/drivers/README.md
// ("Recording") has the sizing and the measured stalls.
//
// Thread contract: each stream has at most one producer thread at a time
// (IMU; images — RGB and depth share one ring, so one camera thread; ground
// truth; events). stop() is called once the producers are done.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/msgs.hpp"
#include "kestrel/rt/spsc_ring.hpp"
#include "kestrel/rt/thread_setup.hpp"

namespace kestrel::drivers {

class KlogLogger {
 public:
  // Ring depths: 10 s of 400 Hz IMU; image messages for 8 s of 30 Hz RGB-D
  // (the byte staging buffer is the tighter bound).
  static constexpr size_t kImuRingSize = 4096;
  static constexpr size_t kImageRingSize = 512;
  static constexpr size_t kGroundTruthRingSize = 1024;
  static constexpr size_t kEventRingSize = 256;
  static constexpr size_t kEventTextBytes = 120;  // longer event texts are cut

  struct Options {
    size_t max_image_bytes = 640 * 480 * 3;  // larger frames are dropped and counted
    // Image staging memory. 0: 64 x max_image_bytes (VGA RGB: 59 MB, ~1.3 s
    // of VGA RGB-D at 30 Hz). Size it with staging_bytes_for().
    size_t buffer_bytes = 0;
    uint32_t idle_sleep_us = 1000;  // logger poll period when the rings are empty
    uint32_t fsync_every = 0;       // see KlogWriter::set_fsync_every
    // Image compression, done on the logger thread (the config's `record:`
    // section; docs/log-format.md).
    klog::ImageCompression compression = default_image_compression();
    // The logger thread's scheduling (the config's `threads: kst-log:`).
    // SCHED_OTHER by default: it does blocking disk I/O and must never hold
    // a CPU the sensor threads need.
    rt::ThreadSpec thread{"kst-log", 0, -1, 0};
  };

  struct Stats {
    uint64_t imu_drops = 0;
    uint64_t image_drops = 0;  // ring full, staging buffer full, or frame larger than max_image_bytes
    uint64_t ground_truth_drops = 0;
    uint64_t event_drops = 0;
    uint64_t records_written = 0;
    uint64_t bytes_written = 0;
    uint64_t records_lost_to_write_errors = 0;
    size_t staging_bytes = 0;         // the image staging buffer
    size_t staging_peak_bytes = 0;    // most of it ever in use: how close a stall came to dropping
    uint64_t image_bytes_raw = 0;     // pixels given to the writer
    uint64_t image_bytes_stored = 0;  // what they took in the file (compressed)
    int64_t thread_cpu_ns = 0;        // the logger thread's CPU time; set by stop()
  };

  // Staging memory that holds `seconds` of camera_hz frames of rgb_bytes +
  // depth_bytes each, e.g. a disk stall of that length.
  static size_t staging_bytes_for(double seconds, double camera_hz, size_t rgb_bytes, size_t depth_bytes);

  // Creates the file, writes the header, allocates every buffer and starts the
  // logger thread. Throws std::runtime_error naming the path on failure.
  KlogLogger(const std::string& path, const Rig& rig);
  KlogLogger(const std::string& path, const Rig& rig, const Options& options);
  ~KlogLogger();
  KlogLogger(const KlogLogger&) = delete;
  KlogLogger& operator=(const KlogLogger&) = delete;

  // ---- producer side: real-time safe; false = dropped (counted) -------------
  bool log_imu(const ImuSample& s) noexcept;
  bool log_image(RecordType type, int64_t t_ns, int64_t t_recv_ns, uint32_t seq, int32_t exposure_us,
                 const ImageView& view) noexcept;
  bool log_ground_truth(const GroundTruthPose& gt) noexcept;
  bool log_event(int64_t t_ns, EventCode code, const char* text) noexcept;

  // Drains what was pushed, closes the file and joins the thread. Idempotent.
  void stop();
  // Counters; exact after stop(), approximate while running.
  Stats stats() const;
  // What the logger thread asked for and was granted (a refused FIFO/pin runs anyway).
  const rt::ThreadSpec& thread_spec() const { return thread_spec_; }
  const rt::ThreadSetupReport& thread_report() const { return thread_report_; }
  const klog::ImageCompression& compression() const { return options_.compression; }
  // The first write error ("" if none); read after stop().
  const std::string& error() const { return error_; }

 private:
  struct ImageMsg {
    RecordType type = RecordType::kRgb;
    int64_t t_ns = 0;
    int64_t t_recv_ns = 0;
    uint32_t seq = 0;
    int32_t exposure_us = 0;
    int width = 0;
    int height = 0;
    PixelFormat format = PixelFormat::kGray8;
    uint64_t begin = 0;  // staging position of the pixels (monotonic byte count; index = begin % size)
    uint64_t end = 0;    // released up to here once written
  };
  struct EventMsg {
    int64_t t_ns = 0;
    EventCode code = EventCode::kInfo;
    uint32_t length = 0;
    char text[kEventTextBytes] = {};
  };

  void run();
  // Writes the oldest pending record; false when all rings are empty.
  bool write_one();
  template <class F>
  void guarded(F&& write);

  Options options_;
  KlogWriter writer_;
  std::unique_ptr<rt::SpscRing<ImuSample, kImuRingSize>> imu_;
  std::unique_ptr<rt::SpscRing<ImageMsg, kImageRingSize>> images_;
  std::unique_ptr<rt::SpscRing<GroundTruthPose, kGroundTruthRingSize>> gt_;
  std::unique_ptr<rt::SpscRing<EventMsg, kEventRingSize>> events_;
  // Image staging byte ring: the camera thread writes at stage_write_, the
  // logger thread releases up to stage_read_ (both monotonic byte counts).
  // A frame never wraps: when it does not fit before the end, the tail is
  // skipped and counted as used until the frame is released.
  std::unique_ptr<uint8_t[]> stage_;
  size_t stage_size_ = 0;
  uint64_t stage_write_ = 0;             // camera thread only
  std::atomic<uint64_t> stage_read_{0};  // written by the logger thread
  std::atomic<uint64_t> stage_peak_{0};
  std::atomic<uint64_t> image_rejects_{0};  // no staging space or too large (ring-full drops are in the ring)
  std::atomic<uint64_t> records_written_{0};
  std::atomic<uint64_t> bytes_written_{0};
  std::atomic<uint64_t> lost_{0};
  std::atomic<uint64_t> image_raw_{0};
  std::atomic<uint64_t> image_stored_{0};
  std::atomic<int64_t> thread_cpu_ns_{0};
  std::atomic<bool> stop_{false};
  std::string error_;
  rt::ThreadSpec thread_spec_{};
  rt::ThreadSetupReport thread_report_{};
  std::thread thread_;
};

}  // namespace kestrel::drivers

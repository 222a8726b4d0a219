#include "kestrel/drivers/klog_logger.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <ctime>
#include <stdexcept>

namespace kestrel::drivers {

KlogLogger::KlogLogger(const std::string& path, const Rig& rig) : KlogLogger(path, rig, Options{}) {}

KlogLogger::KlogLogger(const std::string& path, const Rig& rig, const Options& options) : options_(options) {
  KlogWriter::Options wo;
  wo.compression = options.compression;
  writer_.open(path, rig, wo);
  writer_.set_fsync_every(options.fsync_every);
  // Rings hold their storage inline (hundreds of KB), so they live on the heap, allocated here once.
  imu_ = std::make_unique<rt::SpscRing<ImuSample, kImuRingSize>>();
  images_ = std::make_unique<rt::SpscRing<ImageMsg, kImageRingSize>>();
  gt_ = std::make_unique<rt::SpscRing<GroundTruthPose, kGroundTruthRingSize>>();
  events_ = std::make_unique<rt::SpscRing<EventMsg, kEventRingSize>>();
  stage_size_ = options.buffer_bytes > 0 ? options.buffer_bytes : 64 * options.max_image_bytes;
  stage_size_ = std::max(stage_size_, options.max_image_bytes);
  stage_.reset(new uint8_t[stage_size_]);
  // Fault the pages in now, not on the first frames (a page fault per 4 KiB
  // of a VGA frame is ~200 faults in the camera thread).
  std::memset(stage_.get(), 0, stage_size_);
  thread_spec_ = options.thread;
  thread_ = rt::start_thread(
      thread_spec_, [this] { run(); }, &thread_report_);
}

KlogLogger::~KlogLogger() { stop(); }

bool KlogLogger::log_imu(const ImuSample& s) noexcept { return imu_->try_push(s); }

bool KlogLogger::log_ground_truth(const GroundTruthPose& gt) noexcept { return gt_->try_push(gt); }

bool KlogLogger::log_event(int64_t t_ns, EventCode code, const char* text) noexcept {
  EventMsg m;
  m.t_ns = t_ns;
  m.code = code;
  const size_t n = text ? strnlen(text, kEventTextBytes) : 0;
  std::memcpy(m.text, text ? text : "", n);
  m.length = static_cast<uint32_t>(n);
  return events_->try_push(m);
}

bool KlogLogger::log_image(RecordType type, int64_t t_ns, int64_t t_recv_ns, uint32_t seq,
                           int32_t exposure_us, const ImageView& view) noexcept {
  const size_t row =
      static_cast<size_t>(std::max(view.width, 0)) * static_cast<size_t>(bytes_per_pixel(view.format));
  const size_t bytes = row * static_cast<size_t>(std::max(view.height, 0));
  if ((type != RecordType::kRgb && type != RecordType::kDepth && type != RecordType::kRight) ||
      bytes > options_.max_image_bytes ||
      (bytes > 0 && (!view.data || static_cast<size_t>(view.stride_bytes) < row))) {
    image_rejects_.fetch_add(1, std::memory_order_relaxed);
    return false;
  }
  // Reserve `bytes` contiguous bytes of the staging ring; a frame that does
  // not fit before the end starts at the beginning, the tail stays unused.
  const uint64_t read = stage_read_.load(std::memory_order_acquire);
  uint64_t begin = stage_write_;
  const size_t at = static_cast<size_t>(begin % stage_size_);
  if (at + bytes > stage_size_) begin += stage_size_ - at;
  const uint64_t end = begin + bytes;
  if (end - read > stage_size_) {
    image_rejects_.fetch_add(1, std::memory_order_relaxed);
    return false;
  }
  uint8_t* dst = stage_.get() + static_cast<size_t>(begin % stage_size_);
  for (int y = 0; y < view.height; ++y) {
    std::memcpy(dst + row * static_cast<size_t>(y), view.data + static_cast<size_t>(y) * view.stride_bytes,
                row);
  }
  ImageMsg m;
  m.type = type;
  m.t_ns = t_ns;
  m.t_recv_ns = t_recv_ns;
  m.seq = seq;
  m.exposure_us = exposure_us;
  m.width = view.width;
  m.height = view.height;
  m.format = view.format;
  m.begin = begin;
  m.end = end;
  // Nothing to undo on a full ring: the space counts as used only once pushed.
  if (!images_->try_push(m)) return false;
  stage_write_ = end;
  const uint64_t used = end - read;
  if (used > stage_peak_.load(std::memory_order_relaxed)) stage_peak_.store(used, std::memory_order_relaxed);
  return true;
}

template <class F>
void KlogLogger::guarded(F&& write) {
  // After a write failure (disk full, I/O error) the rings keep draining so
  // producers never back up; what could not be written is counted.
  if (!error_.empty()) {
    lost_.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  try {
    write();
    records_written_.store(writer_.records_written(), std::memory_order_relaxed);
    bytes_written_.store(writer_.bytes_written(), std::memory_order_relaxed);
    image_raw_.store(writer_.image_bytes_raw(), std::memory_order_relaxed);
    image_stored_.store(writer_.image_bytes_stored(), std::memory_order_relaxed);
  } catch (const std::exception& e) {
    error_ = e.what();
    lost_.fetch_add(1, std::memory_order_relaxed);
  }
}

bool KlogLogger::write_one() {
  ImuSample* imu = imu_->front();
  ImageMsg* img = images_->front();
  GroundTruthPose* gt = gt_->front();
  EventMsg* ev = events_->front();
  int best = -1;
  int64_t t = 0;
  auto consider = [&](int which, const void* p, int64_t tp) {
    if (p && (best < 0 || tp < t)) {
      best = which;
      t = tp;
    }
  };
  consider(0, imu, imu ? imu->t_ns : 0);
  consider(1, img, img ? img->t_ns : 0);
  consider(2, gt, gt ? gt->t_ns : 0);
  consider(3, ev, ev ? ev->t_ns : 0);
  switch (best) {
    case 0:
      guarded([&] { writer_.write_imu(*imu); });
      imu_->pop();
      return true;
    case 1: {
      const uint8_t* px = stage_.get() + static_cast<size_t>(img->begin % stage_size_);
      guarded([&] {
        const int bpp = bytes_per_pixel(img->format);
        writer_.write_image(img->type, img->t_ns, img->t_recv_ns, img->seq, img->exposure_us,
                            ImageView{img->width, img->height, img->width * bpp, img->format, px});
      });
      stage_read_.store(img->end, std::memory_order_release);
      images_->pop();
      return true;
    }
    case 2:
      guarded([&] { writer_.write_ground_truth(*gt); });
      gt_->pop();
      return true;
    case 3:
      guarded([&] { writer_.write_event(Event{ev->t_ns, ev->code, std::string(ev->text, ev->length)}); });
      events_->pop();
      return true;
    default:
      return false;
  }
}

void KlogLogger::run() {
  for (;;) {
    // Read stop_ before draining: everything pushed before stop() is then seen.
    const bool stopping = stop_.load(std::memory_order_acquire);
    bool any = false;
    while (write_one()) any = true;
    if (stopping) break;
    if (!any) std::this_thread::sleep_for(std::chrono::microseconds(options_.idle_sleep_us));
  }
  writer_.close();
  timespec cpu{};
  if (clock_gettime(CLOCK_THREAD_CPUTIME_ID, &cpu) == 0)
    thread_cpu_ns_.store(int64_t{cpu.tv_sec} * 1'000'000'000 + cpu.tv_nsec, std::memory_order_relaxed);
}

void KlogLogger::stop() {
  stop_.store(true, std::memory_order_release);
  if (thread_.joinable()) thread_.join();
}

KlogLogger::Stats KlogLogger::stats() const {
  Stats s;
  s.imu_drops = imu_->drops();
  s.image_drops = images_->drops() + image_rejects_.load(std::memory_order_relaxed);
  s.ground_truth_drops = gt_->drops();
  s.event_drops = events_->drops();
  s.records_written = records_written_.load(std::memory_order_relaxed);
  s.bytes_written = bytes_written_.load(std::memory_order_relaxed);
  s.records_lost_to_write_errors = lost_.load(std::memory_order_relaxed);
  s.staging_bytes = stage_size_;
  s.staging_peak_bytes = static_cast<size_t>(stage_peak_.load(std::memory_order_relaxed));
  s.image_bytes_raw = image_raw_.load(std::memory_order_relaxed);
  s.image_bytes_stored = image_stored_.load(std::memory_order_relaxed);
  s.thread_cpu_ns = thread_cpu_ns_.load(std::memory_order_relaxed);
  return s;
}

size_t KlogLogger::staging_bytes_for(double seconds, double camera_hz, size_t rgb_bytes, size_t depth_bytes) {
  const double frames = std::ceil(std::max(seconds, 0.0) * std::max(camera_hz, 0.0));
  // One frame more: a frame that does not fit before the end of the ring
  // wastes up to one frame of space.
  return static_cast<size_t>(frames + 1.0) * (rgb_bytes + depth_bytes);
}

}  // namespace kestrel::drivers

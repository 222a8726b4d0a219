#include "kestrel/drivers/replay_source.hpp"

#include <cstring>
#include <stdexcept>

#include "kestrel/rt/clock.hpp"

namespace kestrel::drivers {

SensorRings::SensorRings(std::size_t max_image_bytes_in)
    : images([max_image_bytes_in](ImageBuffer& b) { b.pixels.reserve(max_image_bytes_in); }),
      max_image_bytes(max_image_bytes_in) {}

ReplayPace parse_replay_pace(const std::string& name) {
  if (name == "realtime") return ReplayPace::kRealtime;
  if (name == "fast") return ReplayPace::kFast;
  if (name == "lockstep") return ReplayPace::kLockstep;
  throw std::invalid_argument("unknown pace '" + name + "' (expected realtime, fast or lockstep)");
}

const char* to_string(ReplayPace pace) {
  switch (pace) {
    case ReplayPace::kRealtime:
      return "realtime";
    case ReplayPace::kFast:
      return "fast";
    case ReplayPace::kLockstep:
      return "lockstep";
  }
  return "?";
}

ReplaySource::ReplaySource(LogSource& log, SensorRings& rings, ReplayPace pace)
    : log_(log), rings_(rings), pace_(pace) {}

template <class Ring, class T>
bool ReplaySource::push(Ring& ring, rt::Doorbell* bell, const T& value, uint64_t& dropped) {
  for (;;) {
    if (ring.try_push(value)) {
      if (bell != nullptr) bell->ring();
      return true;
    }
    if (pace_ != ReplayPace::kFast) break;
    // Back-pressure: in fast pace the point is to drain the log, so sleep
    // until the consumer pops (it rings space_bell) instead of dropping. The
    // bound only lets `stop` be seen without a ring.
    if (stop_ != nullptr && stop_->load(std::memory_order_relaxed)) return false;
    rings_.space_bell.wait_for_ns(kFullRingWaitNs);
  }
  // Realtime (and a lockstep caller that forgot to drain): drop, as a live
  // driver must. SpscRing counted it already.
  ++dropped;
  return false;
}

void ReplaySource::finish() {
  emit_pending();
  finished_.store(true, std::memory_order_release);
  // Consumers that sleep until the next record must also wake for "no more".
  if (rings_.imu_bell != nullptr) rings_.imu_bell->ring();
  if (rings_.frame_bell != nullptr) rings_.frame_bell->ring();
}

void ReplaySource::wait_until_due(int64_t t_ns) {
  if (pace_ != ReplayPace::kRealtime) return;
  if (wall0_ns_ < 0) {
    wall0_ns_ = rt::now_ns();
    log0_ns_ = t_ns;
    return;
  }
  const int64_t due = wall0_ns_ + (t_ns - log0_ns_);
  if (due > rt::now_ns()) rt::sleep_until_ns(due);
}

bool ReplaySource::copy_image(const LogImage& img, uint32_t& handle) {
  const std::size_t bytes = img.pixels.size();
  if (bytes > rings_.max_image_bytes) {
    ++stats_.images_too_large;
    return false;
  }
  handle = rings_.images.acquire();
  if (handle == rt::kInvalidHandle) return false;
  ImageBuffer* b = rings_.images.get(handle);
  b->t_ns = img.t_ns;
  b->t_recv_ns = img.t_recv_ns;
  b->seq = img.seq;
  b->exposure_us = img.exposure_us;
  b->width = img.width;
  b->height = img.height;
  b->format = img.format;
  b->pixels.resize(bytes);  // within the reserved capacity: no allocation
  if (bytes > 0) std::memcpy(b->pixels.data(), img.pixels.data(), bytes);
  return true;
}

void ReplaySource::emit_pending() {
  if (!have_pending_) return;
  have_pending_ = false;
  pending_.t_recv_ns = rt::now_ns();
  if (push(rings_.frames, rings_.frame_bell, pending_, stats_.frames_dropped)) {
    ++stats_.frames_pushed;
    return;
  }
  // Not delivered: give the pixels back.
  if (pending_.rgb_handle != rt::kInvalidHandle) rings_.images.release(pending_.rgb_handle);
  if (pending_.depth_handle != rt::kInvalidHandle) rings_.images.release(pending_.depth_handle);
  if (pending_.right_handle != rt::kInvalidHandle) rings_.images.release(pending_.right_handle);
}

bool ReplaySource::step() {
  if (finished_.load(std::memory_order_relaxed)) return false;
  if (!log_.next(rec_)) {
    finish();
    return false;
  }
  switch (rec_.type) {
    case RecordType::kImu: {
      emit_pending();  // a depth image, if any, follows its colour image directly
      wait_until_due(rec_.imu.t_ns);
      ImuSample s = rec_.imu;
      // A live driver stamps arrival on the host clock; so does replay, which
      // is what the latency figures measure from.
      s.t_recv_ns = rt::now_ns();
      if (push(rings_.imu, rings_.imu_bell, s, stats_.imu_dropped)) ++stats_.imu_pushed;
      if (stats_.first_t_ns < 0) stats_.first_t_ns = s.t_ns;
      stats_.last_t_ns = s.t_ns;
      break;
    }
    case RecordType::kRgb: {
      emit_pending();
      wait_until_due(rec_.image.t_ns);
      uint32_t h = rt::kInvalidHandle;
      if (!copy_image(rec_.image, h)) {
        ++stats_.frames_dropped;
        break;
      }
      pending_ = RgbdFrameMsg{};
      pending_.t_ns = rec_.image.t_ns;
      pending_.seq = rec_.image.seq;
      pending_.exposure_us = rec_.image.exposure_us;
      pending_.rgb_handle = h;
      pending_.depth_handle = rt::kInvalidHandle;
      pending_.right_handle = rt::kInvalidHandle;
      have_pending_ = true;
      if (stats_.first_t_ns < 0) stats_.first_t_ns = rec_.image.t_ns;
      stats_.last_t_ns = rec_.image.t_ns;
      break;
    }
    case RecordType::kDepth: {
      const bool pairs = have_pending_ && pending_.depth_handle == rt::kInvalidHandle &&
                         std::llabs(rec_.image.t_ns - pending_.t_ns) <= kDepthPairingNs;
      if (!pairs) {
        emit_pending();
        ++stats_.depth_unpaired;
        break;
      }
      uint32_t h = rt::kInvalidHandle;
      if (copy_image(rec_.image, h)) pending_.depth_handle = h;
      emit_pending();
      break;
    }
    case RecordType::kRight: {
      // Waits for nothing: a frame goes out at the next IMU or image record,
      // so a right image stamped later than that (or whose left image is
      // missing) is counted and dropped, and the frame is tracked without depth.
      const bool pairs = have_pending_ && pending_.right_handle == rt::kInvalidHandle &&
                         std::llabs(rec_.image.t_ns - pending_.t_ns) <= kRightPairingNs;
      if (!pairs) {
        ++stats_.right_unpaired;
        break;
      }
      uint32_t h = rt::kInvalidHandle;
      if (copy_image(rec_.image, h)) pending_.right_handle = h;
      break;
    }
    case RecordType::kGroundTruth:
      ++stats_.ground_truth;
      if (gt_ring_ != nullptr) (void)gt_ring_->try_push(rec_.gt);
      break;
    case RecordType::kEvent:
      ++stats_.events;
      break;
  }
  return true;
}

void ReplaySource::run(const std::atomic<bool>& stop) {
  stop_ = &stop;
  while (!stop.load(std::memory_order_relaxed) && step()) {
  }
  if (!finished()) finish();
}

}  // namespace kestrel::drivers

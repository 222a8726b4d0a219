// The rings between the sensor side (live drivers or log replay) and the
// estimator threads. Live drivers and the replay source fill exactly these, so
// a replayed flight exercises the same hand-off as a real one.
//
// Full policy: a producer never waits on a full ring in real time (the push
// fails and the ring's drop counter says so); only `--pace fast` replay waits,
// because there the goal is to drain the log, not to model the sensors.
#pragma once

#include <cstdint>
#include <vector>

#include "kestrel/drivers/log_source.hpp"
#include "kestrel/msgs.hpp"
#include "kestrel/rt/doorbell.hpp"
#include "kestrel/rt/object_pool.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::drivers {

// Pixels of one image: the log's image type, so replay copies field for
// field. Each pool buffer is reserved once at start-up (SensorRings) and only
// resized within that capacity afterwards, so steady state never allocates.
using ImageBuffer = LogImage;

constexpr std::size_t kImuRingCapacity = 4096;  // > 10 s at 400 Hz
constexpr std::size_t kFrameRingCapacity = 16;  // ~0.5 s at 30 Hz
// Every frame in the ring holds up to two images, plus those being filled and
// those being processed.
constexpr std::size_t kImagePoolCapacity = 2 * kFrameRingCapacity + 8;

using ImagePool = rt::ObjectPool<ImageBuffer, kImagePoolCapacity>;

struct SensorRings {
  // Sizes every image buffer for `max_image_bytes` (the largest image the rig
  // produces). Call before any thread starts.
  explicit SensorRings(std::size_t max_image_bytes);

  rt::SpscRing<ImuSample, kImuRingCapacity> imu;
  rt::SpscRing<RgbdFrameMsg, kFrameRingCapacity> frames;
  ImagePool images;
  std::size_t max_image_bytes = 0;

  // Consumers sleep on a doorbell instead of polling (issue 45): a producer
  // rings the bell of the ring it pushed into. Set before any producer starts;
  // null = nobody sleeps on that ring. Two rings may share one bell (a consumer
  // of both); a bell has one sleeper.
  rt::Doorbell* imu_bell = nullptr;
  rt::Doorbell* frame_bell = nullptr;
  // Rung by the consumer after it pops; only a producer that waits on a full
  // ring (`--pace fast` replay) sleeps on it.
  rt::Doorbell space_bell;

  // try_push, then wake the ring's consumer. False: full (the ring counted it).
  bool push_imu(const ImuSample& s) noexcept {
    if (!imu.try_push(s)) return false;
    if (imu_bell != nullptr) imu_bell->ring();
    return true;
  }
  bool push_frame(const RgbdFrameMsg& m) noexcept {
    if (!frames.try_push(m)) return false;
    if (frame_bell != nullptr) frame_bell->ring();
    return true;
  }
};

}  // namespace kestrel::drivers

// One device clock, one mapping, shared between driver threads.
//
// A RealSense D4xx stamps its frames (UVC metadata) and its IMU samples (HID,
// read through IIO) with the same microsecond counter. Mapping each stream
// onto the host clock with its own ClockSync would give two lines whose
// offsets differ by the two transports' latency floors; mapping both through
// one line puts frames and IMU in one clock, which is what hardware timestamp
// sync means (docs/realsense.md, "Time").
//
// The thread that owns the ClockSync (the D4xx camera thread) publishes its
// line here after each observation; any other thread (the IMU's) maps its
// device stamps with the latest line. Publication is a seqlock mailbox
// (rt/mailbox.hpp): no lock, no allocation, the writer never waits.
#pragma once

#include <cmath>
#include <cstdint>

#include "kestrel/drivers/clock_sync.hpp"
#include "kestrel/rt/mailbox.hpp"

namespace kestrel::drivers {

// host = h0 + (d - d0) * (1 + skew), exactly ClockSync's line.
struct ClockLine {
  bool valid = false;
  int64_t d0_ns = 0;
  int64_t h0_ns = 0;
  double skew = 0.0;
  uint64_t jumps = 0;  // resets of the owner's ClockSync so far (a reader may want to know)
  uint64_t observations = 0;

  int64_t to_host_ns(int64_t device_ns) const {
    const int64_t dd = device_ns - d0_ns;
    return h0_ns + dd + static_cast<int64_t>(std::llround(static_cast<double>(dd) * skew));
  }
  // A 32-bit microsecond stamp of the same device (a D4xx HID IMU sample) on
  // this line's unwrapped device time: the value nearest d0, so the reader
  // needs no wrap state of its own (valid within +-35 min of the last
  // publication, which comes every frame).
  int64_t unwrap_us32_ns(uint32_t device_us) const {
    const int64_t d0_us = d0_ns / 1000;
    const auto delta = static_cast<int32_t>(device_us - static_cast<uint32_t>(d0_us));
    return (d0_us + delta) * 1000;
  }
  static ClockLine of(const ClockSync& s, int64_t d_ref_ns, uint64_t observations) {
    ClockLine l;
    l.valid = s.valid();
    l.d0_ns = d_ref_ns;
    l.h0_ns = s.to_host_ns(d_ref_ns);
    l.skew = s.skew();
    l.jumps = s.jumps();
    l.observations = observations;
    return l;
  }
};

class SharedDeviceClock {
 public:
  // From the owning thread only.
  void publish(const ClockLine& l) { box_.publish(l); }
  // Any thread; false until the owner has published a valid line.
  bool read(ClockLine& out) const {
    if (!box_.read(out)) return false;
    return out.valid;
  }

 private:
  rt::Mailbox<ClockLine> box_;
};

}  // namespace kestrel::drivers

// The flight controller's clock, learnt with MAVLink TIMESYNC (#111), so that
// ODOMETRY's time_usec is in the autopilot's time base once it answers.
//
// We ask (tc1 = 0, ts1 = our clock); PX4 and ArduPilot answer with tc1 =
// their clock and ts1 echoed. One exchange gives offset = tc1 - (ts1 + now)/2
// (the autopilot's clock minus ours, assuming a symmetric link) and the round
// trip now - ts1; answers with a round trip above max_rtt are not used (a
// queued link says nothing about the clocks). The offset is a running
// average; after `converge_samples` answers it is used. An answer
// `reset_jump` away from it, `reset_after` times in a row, means the autopilot
// restarted: the estimate starts again.
//
// The autopilot asks too (PX4 does, to map our stamps onto its clock): we
// answer with our clock in the same time base as the stamps we send (the
// autopilot's once converged), so its own mapping stays consistent: it sees an
// offset of ~0 after the switch. Times are int64 ns; no allocation.
#pragma once

#include <cstdint>

#include "kestrel/drivers/mavlink/mavlink_v2.hpp"

namespace kestrel::mavlink {

struct TimeSyncOptions {
  int64_t max_rtt_ns = 10'000'000;
  int converge_samples = 5;
  double alpha = 0.1;  // weight of a new sample in the running average once converged
  int64_t reset_jump_ns = 50'000'000;
  int reset_after = 3;
  // Trust short exchanges more (the flight controller's IMU link): the offset starts from the
  // converging sample with the shortest round trip instead of their mean, and each later sample
  // weighs alpha * (shortest recent round trip / its round trip). A sample's error is bounded by half
  // its round trip, and a slow exchange is usually a queued, one-sided one. Off: the mean, then alpha.
  bool prefer_short_round_trips = false;
};

struct TimeSyncStats {
  uint64_t requests_sent = 0;
  uint64_t requests_answered = 0;  // the autopilot's requests we answered
  uint64_t responses_used = 0;
  uint64_t responses_rejected = 0;  // round trip too long, or not an answer to ours
  uint64_t resets = 0;
  int64_t last_rtt_ns = -1;
};

class TimeSync {
 public:
  explicit TimeSync(const TimeSyncOptions& o = {}) : opt_(o) {}
  // The request to send now (remembers its stamp).
  TimesyncMsg request(int64_t now_ns);
  // A TIMESYNC from the autopilot (sysid/compid its sender, ours for the
  // target check). Returns true and fills *reply when it is a request to
  // answer; a response to one of ours updates the offset.
  bool on_message(const TimesyncMsg& m, uint8_t from_sysid, uint8_t from_compid, uint8_t our_sysid,
                  uint8_t our_compid, int64_t now_ns, TimesyncMsg* reply);
  bool converged() const { return samples_ >= opt_.converge_samples; }
  int64_t offset_ns() const { return static_cast<int64_t>(offset_ns_); }  // autopilot - ours
  // A time of our clock in the time base we speak: the autopilot's once converged.
  int64_t to_link_time_ns(int64_t our_ns) const { return converged() ? our_ns + offset_ns() : our_ns; }
  const TimeSyncStats& stats() const { return stats_; }

 private:
  TimeSyncOptions opt_;
  TimeSyncStats stats_;
  static constexpr int kPending = 8;
  int64_t pending_[kPending] = {};  // ts1 of our recent requests
  int next_pending_ = 0;
  double offset_ns_ = 0.0;
  int samples_ = 0;
  int far_in_a_row_ = 0;
  static constexpr int kRttWindow = 8;
  int64_t rtts_[kRttWindow] = {};  // the last round trips used (prefer_short_round_trips)
  int next_rtt_ = 0;
  int64_t best_rtt_converging_ = 0;
};

}  // namespace kestrel::mavlink

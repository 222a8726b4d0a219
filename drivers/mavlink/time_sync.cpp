#include "kestrel/drivers/mavlink/time_sync.hpp"

#include <cmath>

namespace kestrel::mavlink {

TimesyncMsg TimeSync::request(int64_t now_ns) {
  TimesyncMsg m;
  m.tc1 = 0;
  m.ts1 = now_ns;
  pending_[next_pending_] = now_ns;
  next_pending_ = (next_pending_ + 1) % kPending;
  ++stats_.requests_sent;
  return m;
}

bool TimeSync::on_message(const TimesyncMsg& m, uint8_t from_sysid, uint8_t from_compid, uint8_t our_sysid,
                          uint8_t our_compid, int64_t now_ns, TimesyncMsg* reply) {
  // target 0 is a broadcast (and what senders without the extension leave).
  const bool for_us = (m.target_system == 0 || m.target_system == our_sysid) &&
                      (m.target_component == 0 || m.target_component == our_compid);
  if (!for_us) return false;
  if (m.tc1 == 0) {
    reply->tc1 = to_link_time_ns(now_ns);
    reply->ts1 = m.ts1;
    reply->target_system = from_sysid;
    reply->target_component = from_compid;
    ++stats_.requests_answered;
    return true;
  }
  bool ours = false;
  for (int64_t p : pending_) ours = ours || (p != 0 && p == m.ts1);
  const int64_t rtt = now_ns - m.ts1;
  if (!ours || rtt < 0 || rtt > opt_.max_rtt_ns) {
    ++stats_.responses_rejected;
    return false;
  }
  stats_.last_rtt_ns = rtt;
  ++stats_.responses_used;
  // Autopilot time at the midpoint of the exchange minus ours.
  const double sample =
      static_cast<double>(m.tc1) - (static_cast<double>(m.ts1) + static_cast<double>(now_ns)) / 2.0;
  if (samples_ > 0 && std::abs(sample - offset_ns_) > static_cast<double>(opt_.reset_jump_ns)) {
    if (++far_in_a_row_ < opt_.reset_after) return false;
    samples_ = 0;  // the autopilot's clock jumped (a reboot): start again
    ++stats_.resets;
  }
  far_in_a_row_ = 0;
  ++samples_;
  if (opt_.prefer_short_round_trips) {
    if (samples_ == 1) {
      for (int64_t& r : rtts_) r = 0;
      next_rtt_ = 0;
    }
    rtts_[next_rtt_] = rtt + 1;  // + 1 ns: 0 marks an empty slot
    next_rtt_ = (next_rtt_ + 1) % kRttWindow;
    if (samples_ <= opt_.converge_samples) {
      // The shortest exchange so far sets the offset.
      if (samples_ == 1 || rtt < best_rtt_converging_) {
        best_rtt_converging_ = rtt;
        offset_ns_ = sample;
      }
      return false;
    }
    int64_t shortest = rtts_[0];
    for (int64_t r : rtts_)
      if (r != 0 && (shortest == 0 || r < shortest)) shortest = r;
    // A 1 us floor: on a loopback link every round trip is a few us and should count alike.
    const double trust = (static_cast<double>(shortest) + 1000.0) / (static_cast<double>(rtt + 1) + 1000.0);
    offset_ns_ += opt_.alpha * trust * (sample - offset_ns_);
    return false;
  }
  // The mean of the first samples, then a running average.
  const double w = samples_ <= opt_.converge_samples ? 1.0 / samples_ : opt_.alpha;
  offset_ns_ = samples_ == 1 ? sample : offset_ns_ + w * (sample - offset_ns_);
  return false;
}

}  // namespace kestrel::mavlink

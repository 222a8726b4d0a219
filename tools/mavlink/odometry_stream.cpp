#include "kestrel/mavlink/odometry_stream.hpp"

#include <stdexcept>

#include "kestrel/drivers/mavlink/serial_link.hpp"
#include "kestrel/drivers/mavlink/udp_sender.hpp"

namespace kestrel::mavlink {
namespace {

std::unique_ptr<Link> open_link(const OdometryStreamOptions& o) {
  if (!o.endpoint.empty() && !o.serial_device.empty()) {
    throw std::invalid_argument("MAVLink: both a UDP endpoint (" + o.endpoint + ") and a serial port (" +
                                o.serial_device + ") given; one link at a time");
  }
  if (!o.serial_device.empty()) return std::make_unique<SerialLink>(o.serial_device, o.serial_baud);
  return std::make_unique<UdpSender>(o.endpoint);
}

int64_t period_ns(double rate_hz) { return rate_hz > 0 ? static_cast<int64_t>(1e9 / rate_hz) : 0; }

}  // namespace

uint8_t mav_state_of(core::TrackingQuality q) {
  switch (q) {
    case core::TrackingQuality::kUninitialized:
      return kMavStateStandby;
    case core::TrackingQuality::kImuOnly:
    case core::TrackingQuality::kVisionOnly:
    case core::TrackingQuality::kTracking:
      return kMavStateActive;
    case core::TrackingQuality::kLost:
      return kMavStateCritical;
  }
  return kMavStateStandby;
}

OdometryStream::OdometryStream(const OdometryStreamOptions& opt) : OdometryStream(open_link(opt), opt) {}

OdometryStream::OdometryStream(std::unique_ptr<Link> link, const OdometryStreamOptions& opt)
    : opt_(opt), link_(std::move(link)), sync_(opt.timesync_options) {
  if (opt_.signing) {
    signing_ = std::make_unique<MavlinkSigning>(opt_.signing_key, opt_.signing_link_id);
    decoder_.set_signing(signing_.get());
  }
}

bool OdometryStream::send(std::size_t n) noexcept { return link_->send(frame_, n); }

void OdometryStream::service(int64_t now_ns) noexcept {
  for (;;) {
    const std::size_t got = link_->receive(rx_, sizeof rx_);
    if (got == 0) break;
    decoder_.feed(rx_, got, [&](const MavlinkFrame& f) {
      if (f.msgid == kMsgIdHeartbeat) {
        ++stats_.autopilot_heartbeats;
      } else if (f.msgid == kMsgIdTimesync && opt_.timesync) {
        TimesyncMsg reply;
        if (sync_.on_message(unpack_timesync(f.payload), f.sysid, f.compid, opt_.sysid, opt_.compid, now_ns,
                             &reply))
          send(encode_timesync(reply, seq_++, opt_.sysid, opt_.compid, frame_, signing_.get()));
      }
    });
  }
  if (opt_.heartbeat_rate_hz > 0 && now_ns >= next_heartbeat_ns_) {
    next_heartbeat_ns_ = now_ns + period_ns(opt_.heartbeat_rate_hz);
    HeartbeatMsg h;
    h.system_status = status_;
    if (send(encode_heartbeat(h, seq_++, opt_.sysid, opt_.compid, frame_, signing_.get())))
      ++stats_.heartbeats_sent;
  }
  if (opt_.timesync && opt_.timesync_rate_hz > 0 && now_ns >= next_timesync_ns_) {
    const double rate = sync_.converged() ? opt_.timesync_rate_hz : 10.0 * opt_.timesync_rate_hz;
    next_timesync_ns_ = now_ns + period_ns(rate);
    send(encode_timesync(sync_.request(now_ns), seq_++, opt_.sysid, opt_.compid, frame_, signing_.get()));
  }
}

bool OdometryStream::publish(const core::PoseSample& in) noexcept {
  status_ = mav_state_of(in.quality);
  OdometryMsg m;
  if (!to_odometry(in, opt_.adapter, m)) {
    ++skipped_;
    return false;
  }
  const int64_t period = period_ns(opt_.odometry_rate_hz);
  if (period > 0 && last_odometry_t_ns_ >= 0 && in.t_ns - last_odometry_t_ns_ < period * 9 / 10) {
    ++stats_.rate_skipped;
    return false;
  }
  if (opt_.stamps_on_host_clock && in.t_ns > 0)
    m.time_usec = static_cast<uint64_t>(sync_.to_link_time_ns(in.t_ns) / 1000);
  if (!send(encode_odometry(m, seq_++, opt_.sysid, opt_.compid, frame_, signing_.get()))) return false;
  last_odometry_t_ns_ = in.t_ns;
  ++stats_.odometry_sent;
  return true;
}

}  // namespace kestrel::mavlink

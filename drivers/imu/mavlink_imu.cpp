#include "kestrel/drivers/mavlink_imu.hpp"

#include <poll.h>

#include <cerrno>
#include <cmath>
#include <cstdio>
#include <stdexcept>

#include "kestrel/drivers/mavlink/serial_link.hpp"
#include "kestrel/drivers/mavlink/udp_sender.hpp"

namespace kestrel::drivers {
namespace {

namespace ml = kestrel::mavlink;

constexpr double kStandardGravityMps2 = 9.80665;       // SCALED_IMU's mG
constexpr int64_t kHeartbeatPeriodNs = 1'000'000'000;  // MAVLink's convention: 1 Hz

std::unique_ptr<ml::Link> open_link(const MavlinkImuConfig& c) {
  if (!c.udp.empty() && !c.serial_device.empty()) {
    throw std::invalid_argument("MAVLink IMU: both a UDP endpoint (" + c.udp + ") and a serial port (" +
                                c.serial_device + ") given; one link at a time");
  }
  if (!c.serial_device.empty()) return std::make_unique<ml::SerialLink>(c.serial_device, c.serial_baud);
  if (c.udp.empty())
    throw std::invalid_argument("MAVLink IMU: no link (drivers.imu.mavlink.udp or serial_device)");
  return std::make_unique<ml::UdpSender>(c.udp);
}

}  // namespace

const char* to_string(MavlinkImuMessage m) {
  switch (m) {
    case MavlinkImuMessage::kHighres:
      return "highres_imu";
    case MavlinkImuMessage::kScaled:
      return "scaled_imu";
    case MavlinkImuMessage::kRaw:
      return "raw_imu";
  }
  return "?";
}

MavlinkImuDriver::MavlinkImuDriver(const MavlinkImuConfig& c, const HostClock& clock)
    : MavlinkImuDriver(open_link(c), c, clock) {}

MavlinkImuDriver::MavlinkImuDriver(std::unique_ptr<ml::Link> link, const MavlinkImuConfig& c,
                                   const HostClock& clock)
    : cfg_(c), clock_(clock), link_(std::move(link)), sync_(c.timesync) {
  if (!(cfg_.rate_hz > 0)) throw std::invalid_argument("MAVLink IMU: rate_hz must be > 0");
  if (cfg_.message == MavlinkImuMessage::kRaw &&
      !(cfg_.raw_acc_mps2_per_lsb > 0 && cfg_.raw_gyro_rad_s_per_lsb > 0)) {
    throw std::invalid_argument(
        "MAVLink IMU: raw_imu needs raw_acc_mps2_per_lsb and raw_gyro_rad_s_per_lsb > 0");
  }
  msgid_ = cfg_.message == MavlinkImuMessage::kHighres  ? ml::kMsgIdHighresImu
           : cfg_.message == MavlinkImuMessage::kScaled ? ml::kMsgIdScaledImu
                                                        : ml::kMsgIdRawImu;
  period_ns_ = static_cast<int64_t>(1e9 / cfg_.rate_hz);
  if (cfg_.signing) {
    signing_ = std::make_unique<ml::MavlinkSigning>(cfg_.key, cfg_.link_id, cfg_.signing_clock_unix_ns);
    decoder_.set_signing(signing_.get());
  }
}

bool MavlinkImuDriver::from_autopilot(const ml::MavlinkFrame& f) const noexcept {
  return (cfg_.target_sysid == 0 || f.sysid == cfg_.target_sysid) &&
         (cfg_.target_compid == 0 || f.compid == cfg_.target_compid);
}

void MavlinkImuDriver::send_due(int64_t now_ns) noexcept {
  ml::MavlinkSigning* sign = signing_.get();
  if (now_ns >= next_heartbeat_ns_) {
    next_heartbeat_ns_ = now_ns + kHeartbeatPeriodNs;
    ml::HeartbeatMsg h;
    h.system_status = ml::kMavStateActive;
    send(ml::encode_heartbeat(h, tx_seq_++, cfg_.sysid, cfg_.compid, tx_, sign));
  }
  if (cfg_.timesync_rate_hz > 0 && now_ns >= next_timesync_ns_) {
    const double rate = sync_.converged() ? cfg_.timesync_rate_hz : 10.0 * cfg_.timesync_rate_hz;
    next_timesync_ns_ = now_ns + static_cast<int64_t>(1e9 / rate);
    ml::TimesyncMsg t = sync_.request(now_ns);
    t.target_system = cfg_.target_sysid;
    t.target_component = cfg_.target_compid;
    send(ml::encode_timesync(t, tx_seq_++, cfg_.sysid, cfg_.compid, tx_, sign));
  }
  if (interval_state_ == kAsking && now_ns >= next_command_ns_) {
    next_command_ns_ = now_ns + cfg_.command_retry_ns;
    ml::CommandLongMsg m;
    m.command = ml::kMavCmdSetMessageInterval;
    m.target_system = cfg_.target_sysid;
    m.target_component = cfg_.target_compid;
    m.param[0] = static_cast<float>(msgid_);
    m.param[1] = static_cast<float>(1e6 / cfg_.rate_hz);  // interval, us
    m.confirmation = static_cast<uint8_t>(c_.commands_sent > 255 ? 255 : c_.commands_sent);
    send(ml::encode_command_long(m, tx_seq_++, cfg_.sysid, cfg_.compid, tx_, sign));
    ++c_.commands_sent;
  }
}

void MavlinkImuDriver::step(ImuSink& sink, int64_t max_wait_ns) noexcept {
  int64_t now = clock_.now_ns();
  send_due(now);
  int64_t due = now + max_wait_ns;
  if (cfg_.timesync_rate_hz > 0 && next_timesync_ns_ < due) due = next_timesync_ns_;
  if (interval_state_ == kAsking && next_command_ns_ < due) due = next_command_ns_;
  if (next_heartbeat_ns_ < due) due = next_heartbeat_ns_;
  const int64_t wait = due > now ? due - now : 0;
  pollfd p{link_->fd(), POLLIN, 0};
  const timespec ts{static_cast<time_t>(wait / 1'000'000'000), static_cast<long>(wait % 1'000'000'000)};
  const int r = ::ppoll(&p, 1, &ts, nullptr);
  if (r < 0 && errno != EINTR) ++c_.poll_errors;
  if (r <= 0) return;
  std::size_t total = 0;
  for (;;) {
    const std::size_t got = link_->receive(rx_, sizeof rx_);
    if (got == 0) break;
    total += got;
    const int64_t t_recv = clock_.now_ns();
    decoder_.feed(rx_, got, [&](const ml::MavlinkFrame& f) { on_frame(f, t_recv, sink); });
  }
  if (total == 0 && (p.revents & (POLLERR | POLLHUP | POLLNVAL)) != 0) {
    // The device is gone (a USB serial adapter unplugged): the descriptor stays readable, so wait out the
    // period instead of spinning on it.
    ++c_.link_errors;
    ::ppoll(nullptr, 0, &ts, nullptr);
  }
}

void MavlinkImuDriver::on_frame(const ml::MavlinkFrame& f, int64_t t_recv_ns, ImuSink& sink) noexcept {
  if (f.msgid == ml::kMsgIdTimesync) {
    ml::TimesyncMsg reply;
    if (from_autopilot(f) && sync_.on_message(ml::unpack_timesync(f.payload), f.sysid, f.compid, cfg_.sysid,
                                              cfg_.compid, t_recv_ns, &reply))
      send(ml::encode_timesync(reply, tx_seq_++, cfg_.sysid, cfg_.compid, tx_, signing_.get()));
    return;
  }
  if (f.msgid == ml::kMsgIdCommandAck && from_autopilot(f)) {
    const ml::CommandAckMsg a = ml::unpack_command_ack(f.payload);
    const bool for_us = (a.target_system == 0 || a.target_system == cfg_.sysid) &&
                        (a.target_component == 0 || a.target_component == cfg_.compid);
    if (a.command == ml::kMavCmdSetMessageInterval && for_us && interval_state_ == kAsking) {
      interval_state_ = a.result == ml::kMavResultAccepted ? kAccepted : kRefused;
      if (interval_state_ == kRefused) ++c_.command_refused;
    }
    return;
  }
  if (f.msgid != msgid_ || !from_autopilot(f)) {
    ++c_.other_messages;
    return;
  }
  ++c_.imu_messages;
  double acc[3], gyro[3];
  float temp_c = 0;
  int64_t t_dev_ns = 0;
  if (msgid_ == ml::kMsgIdHighresImu) {
    const ml::HighresImuMsg m = ml::unpack_highres_imu(f.payload);
    t_dev_ns = static_cast<int64_t>(m.time_usec * 1000);
    acc[0] = m.xacc, acc[1] = m.yacc, acc[2] = m.zacc;
    gyro[0] = m.xgyro, gyro[1] = m.ygyro, gyro[2] = m.zgyro;
    temp_c = m.temperature;
  } else if (msgid_ == ml::kMsgIdScaledImu) {
    const ml::ScaledImuMsg m = ml::unpack_scaled_imu(f.payload);
    t_dev_ns = static_cast<int64_t>(m.time_boot_ms) * 1'000'000;
    const double a = 1e-3 * kStandardGravityMps2, g = 1e-3;
    acc[0] = a * m.xacc, acc[1] = a * m.yacc, acc[2] = a * m.zacc;
    gyro[0] = g * m.xgyro, gyro[1] = g * m.ygyro, gyro[2] = g * m.zgyro;
    temp_c = 0.01f * m.temperature;
  } else {
    const ml::RawImuMsg m = ml::unpack_raw_imu(f.payload);
    t_dev_ns = static_cast<int64_t>(m.time_usec * 1000);
    const double a = cfg_.raw_acc_mps2_per_lsb, g = cfg_.raw_gyro_rad_s_per_lsb;
    acc[0] = a * m.xacc, acc[1] = a * m.yacc, acc[2] = a * m.zacc;
    gyro[0] = g * m.xgyro, gyro[1] = g * m.ygyro, gyro[2] = g * m.zgyro;
    temp_c = 0.01f * m.temperature;
  }
  on_imu(t_dev_ns, acc, gyro, temp_c, t_recv_ns, sink);
}

void MavlinkImuDriver::on_imu(int64_t t_dev_ns, const double acc[3], const double gyro[3], float temp_c,
                              int64_t t_recv_ns, ImuSink& sink) noexcept {
  for (int i = 0; i < 3; ++i) {
    if (!std::isfinite(acc[i]) || !std::isfinite(gyro[i])) {
      ++c_.nonfinite;
      gap_pending_ = true;
      return;
    }
  }
  if (!sync_.converged()) {
    ++c_.before_sync;
    return;
  }
  if (last_dev_ns_ >= 0 && t_dev_ns <= last_dev_ns_) {
    ++c_.out_of_order;
    return;
  }
  const int64_t t_host = t_dev_ns - sync_.offset_ns();
  if (t_host > t_recv_ns + cfg_.timesync.max_rtt_ns / 2 || t_recv_ns - t_host > cfg_.max_latency_ns) {
    ++c_.stamp_outliers;
    gap_pending_ = true;
    return;
  }
  if (last_host_ns_ >= 0 && t_host <= last_host_ns_) {
    ++c_.out_of_order;  // the offset estimate moved back by more than a period
    return;
  }
  ImuSample s;
  s.t_ns = t_host;
  s.t_recv_ns = t_recv_ns;
  s.seq = seq_out_++;
  if (last_dev_ns_ >= 0 &&
      static_cast<double>(t_dev_ns - last_dev_ns_) > cfg_.gap_periods * static_cast<double>(period_ns_)) {
    ++c_.gaps;
    gap_pending_ = true;
  }
  // A frame refused since the last sample (checksum, signature) may have been a sample.
  const uint64_t refused = decoder_.stats().bad_crc + decoder_.stats().unauthenticated;
  if (refused != refused_seen_) gap_pending_ = true;
  refused_seen_ = refused;
  if (gap_pending_) s.flags |= kImuGapBefore;
  gap_pending_ = false;
  s.acc_mps2 = Vec3d{acc[0], acc[1], acc[2]};
  s.gyro_rps = Vec3d{gyro[0], gyro[1], gyro[2]};
  s.temp_c = temp_c;
  last_dev_ns_ = t_dev_ns;
  last_host_ns_ = t_host;
  if (sink.push(s)) {
    ++c_.samples;
  } else {
    ++c_.sink_drops;
  }
}

std::string MavlinkImuDriver::report() const {
  const auto& d = decoder_.stats();
  char b[640];
  std::snprintf(
      b, sizeof b,
      "mavlink imu (%s, %s): %llu samples, %llu sink drops, %llu before clock sync, %llu out of order, "
      "%llu gaps, %llu non-finite, %llu stamp outliers, %llu other messages, %llu crc failures, "
      "%llu unknown ids, %llu unauthenticated, %llu link errors; interval %s after %llu requests; "
      "clock offset %.3f ms (%s, last rtt %.3f ms)\n",
      link_->endpoint().c_str(), to_string(cfg_.message), (unsigned long long)c_.samples,
      (unsigned long long)c_.sink_drops, (unsigned long long)c_.before_sync,
      (unsigned long long)c_.out_of_order, (unsigned long long)c_.gaps, (unsigned long long)c_.nonfinite,
      (unsigned long long)c_.stamp_outliers, (unsigned long long)c_.other_messages,
      (unsigned long long)d.bad_crc, (unsigned long long)d.unknown_msgid,
      (unsigned long long)d.unauthenticated, (unsigned long long)c_.link_errors,
      interval_state_ == kAccepted  ? "accepted"
      : interval_state_ == kRefused ? "refused"
                                    : "unanswered",
      (unsigned long long)c_.commands_sent, 1e-6 * static_cast<double>(sync_.offset_ns()),
      sync_.converged() ? "converged" : "not converged",
      1e-6 * static_cast<double>(sync_.stats().last_rtt_ns));
  return b;
}

}  // namespace kestrel::drivers

// A simulated autopilot for the flight controller's IMU driver tests: a thread
// on a loopback UDP socket (or a pty's master side: a serial port) that behaves like PX4 / ArduPilot towards
// a companion computer. It answers TIMESYNC requests in its own clock (the host clock plus `offset_ns`),
// answers MAV_CMD_SET_MESSAGE_INTERVAL with a COMMAND_ACK and then streams the given IMU samples as
// HIGHRES_IMU, SCALED_IMU or RAW_IMU, each sent when its time comes (plus a link latency). With a key it
// signs everything and accepts only what verifies. Faults are injected at given sample indexes. Test code: it
// may allocate.
#pragma once

#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <cmath>
#include <cstring>
#include <memory>
#include <mutex>
#include <set>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "kestrel/drivers/mavlink/mavlink_decoder.hpp"
#include "kestrel/drivers/mavlink/mavlink_signing.hpp"
#include "kestrel/drivers/mavlink/mavlink_v2.hpp"
#include "kestrel/drivers/mavlink_imu.hpp"
#include "kestrel/rt/clock.hpp"

namespace kestrel::test {

struct SimImuSample {
  int64_t t_rel_ns = 0;  // from the start of the stream
  double acc_mps2[3] = {};
  double gyro_rps[3] = {};
};

struct SimAutopilotOptions {
  bool serial = false;                 // a pty instead of UDP: endpoint() is the slave's path
  int64_t offset_ns = 0;               // autopilot clock - host clock
  int64_t latency_ns = 300'000;        // from the sample's time to its send
  int64_t start_lead_ns = 50'000'000;  // the stream starts this long after the command
  drivers::MavlinkImuMessage message = drivers::MavlinkImuMessage::kHighres;
  double raw_acc_mps2_per_lsb = 0.0024;  // RAW_IMU's counts
  double raw_gyro_rad_s_per_lsb = 0.001;
  bool signing = false;
  mavlink::SigningKey key;
  uint8_t link_id = 7;
  // Faults, by sample index.
  std::set<int> nan_at, repeat_time_at, skip_at, corrupt_at, unknown_before, unsigned_at, wrong_key_at;
  std::set<int> future_at;  // stamped 5 s ahead: a wrong clock
};

class SimAutopilot {
 public:
  SimAutopilot(const SimAutopilotOptions& o, std::vector<SimImuSample> samples)
      : o_(o), samples_(std::move(samples)) {
    if (o_.serial) {
      fd_ = ::posix_openpt(O_RDWR | O_NOCTTY | O_CLOEXEC);
      if (fd_ < 0 || ::grantpt(fd_) != 0 || ::unlockpt(fd_) != 0 || ::ptsname(fd_) == nullptr)
        throw std::runtime_error("sim autopilot: no pty");
      slave_ = ::ptsname(fd_);
      have_peer_ = true;
    } else {
      fd_ = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
      sockaddr_in a{};
      a.sin_family = AF_INET;
      a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
      if (fd_ < 0 || ::bind(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0)
        throw std::runtime_error("sim autopilot: cannot bind a loopback UDP socket");
      socklen_t len = sizeof a;
      ::getsockname(fd_, reinterpret_cast<sockaddr*>(&a), &len);
      port_ = ntohs(a.sin_port);
    }
    if (o_.signing) {
      verify_ = std::make_unique<mavlink::MavlinkSigning>(o_.key, o_.link_id);
      sign_ = std::make_unique<mavlink::MavlinkSigning>(o_.key, o_.link_id);
      decoder_.set_signing(verify_.get());
      mavlink::SigningKey other = o_.key;
      other.bytes[0] ^= 0x5A;
      wrong_ = std::make_unique<mavlink::MavlinkSigning>(other, o_.link_id);
    }
    thread_ = std::thread([this] { run(); });
  }
  ~SimAutopilot() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
    ::close(fd_);
  }
  uint16_t port() const { return port_; }
  std::string endpoint() const { return o_.serial ? slave_ : "127.0.0.1:" + std::to_string(port_); }

  // The autopilot time of sample i (valid once streaming started).
  int64_t t_ap_ns(std::size_t i) const { return stream_ap0_ns_.load() + samples_[i].t_rel_ns; }
  // Its true host time.
  int64_t t_host_ns(std::size_t i) const { return t_ap_ns(i) - o_.offset_ns; }
  // The time_usec / time_boot_ms the wire carried, back in ns on the host clock.
  int64_t t_host_on_wire_ns(std::size_t i) const {
    const int64_t ap = t_ap_ns(i);
    const int64_t wire =
        o_.message == drivers::MavlinkImuMessage::kScaled ? ap / 1'000'000 * 1'000'000 : ap / 1000 * 1000;
    return wire - o_.offset_ns;
  }
  bool streaming() const { return stream_ap0_ns_.load() != 0; }
  bool done() const { return next_.load() >= samples_.size(); }
  int commands() const { return commands_.load(); }
  int timesync_answers() const { return timesync_answers_.load(); }
  int frames_in() const { return frames_in_.load(); }
  float requested_msgid() const { return requested_msgid_.load(); }
  float requested_interval_us() const { return requested_interval_us_.load(); }
  uint64_t unauthenticated_in() const {
    std::lock_guard<std::mutex> l(m_);
    return decoder_.stats().unauthenticated;
  }

 private:
  int64_t ap_now() const { return rt::now_ns() + o_.offset_ns; }

  void send(std::size_t n) {
    if (o_.serial)
      (void)!::write(fd_, tx_, n);
    else if (have_peer_)
      ::sendto(fd_, tx_, n, 0, reinterpret_cast<const sockaddr*>(&peer_), sizeof peer_);
  }

  void send_sample(std::size_t i) {
    namespace ml = mavlink;
    SimImuSample s = samples_[i];
    const int ii = static_cast<int>(i);
    if (o_.nan_at.count(ii)) s.acc_mps2[1] = std::nan("");
    int64_t ap = t_ap_ns(i);
    if (o_.repeat_time_at.count(ii) && i > 0) ap = t_ap_ns(i - 1);
    if (o_.future_at.count(ii)) ap += 5'000'000'000;
    ml::MavlinkSigning* sign = sign_.get();
    if (o_.unsigned_at.count(ii)) sign = nullptr;
    if (o_.wrong_key_at.count(ii)) sign = wrong_.get();
    if (o_.unknown_before.count(ii)) {
      // A message this build does not know (id 9999), with a checksum we cannot check.
      const uint8_t payload[4] = {1, 2, 3, 4};
      send(ml::frame_v2(9999, 0, payload, 4, seq_++, 1, 1, tx_, sign));
    }
    std::size_t n = 0;
    if (o_.message == drivers::MavlinkImuMessage::kHighres) {
      ml::HighresImuMsg m;
      m.time_usec = static_cast<uint64_t>(ap / 1000);
      m.xacc = static_cast<float>(s.acc_mps2[0]), m.yacc = static_cast<float>(s.acc_mps2[1]);
      m.zacc = static_cast<float>(s.acc_mps2[2]);
      m.xgyro = static_cast<float>(s.gyro_rps[0]), m.ygyro = static_cast<float>(s.gyro_rps[1]);
      m.zgyro = static_cast<float>(s.gyro_rps[2]);
      m.temperature = 35.5f;
      m.fields_updated = 0x3F;
      n = ml::encode_highres_imu(m, seq_++, 1, 1, tx_, sign);
    } else if (o_.message == drivers::MavlinkImuMessage::kScaled) {
      ml::ScaledImuMsg m;
      m.time_boot_ms = static_cast<uint32_t>(ap / 1'000'000);
      auto mg = [](double v) { return static_cast<int16_t>(std::lround(v / (1e-3 * 9.80665))); };
      auto mrad = [](double v) { return static_cast<int16_t>(std::lround(v / 1e-3)); };
      m.xacc = mg(s.acc_mps2[0]), m.yacc = mg(s.acc_mps2[1]), m.zacc = mg(s.acc_mps2[2]);
      m.xgyro = mrad(s.gyro_rps[0]), m.ygyro = mrad(s.gyro_rps[1]), m.zgyro = mrad(s.gyro_rps[2]);
      m.temperature = 3550;
      n = ml::encode_scaled_imu(m, seq_++, 1, 1, tx_, sign);
    } else {
      ml::RawImuMsg m;
      m.time_usec = static_cast<uint64_t>(ap / 1000);
      auto ca = [&](double v) { return static_cast<int16_t>(std::lround(v / o_.raw_acc_mps2_per_lsb)); };
      auto cg = [&](double v) { return static_cast<int16_t>(std::lround(v / o_.raw_gyro_rad_s_per_lsb)); };
      m.xacc = ca(s.acc_mps2[0]), m.yacc = ca(s.acc_mps2[1]), m.zacc = ca(s.acc_mps2[2]);
      m.xgyro = cg(s.gyro_rps[0]), m.ygyro = cg(s.gyro_rps[1]), m.zgyro = cg(s.gyro_rps[2]);
      m.temperature = 3550;
      n = ml::encode_raw_imu(m, seq_++, 1, 1, tx_, sign);
    }
    if (o_.corrupt_at.count(ii)) tx_[12] ^= 0x10;  // a payload bit: the checksum fails
    send(n);
  }

  void on_frame(const mavlink::MavlinkFrame& f) {
    namespace ml = mavlink;
    ++frames_in_;
    if (f.msgid == ml::kMsgIdTimesync) {
      const ml::TimesyncMsg t = ml::unpack_timesync(f.payload);
      if (t.tc1 != 0) return;
      ml::TimesyncMsg r;
      r.tc1 = ap_now();
      r.ts1 = t.ts1;
      r.target_system = f.sysid;
      r.target_component = f.compid;
      send(ml::encode_timesync(r, seq_++, 1, 1, tx_, sign_.get()));
      ++timesync_answers_;
    } else if (f.msgid == ml::kMsgIdCommandLong) {
      const ml::CommandLongMsg c = ml::unpack_command_long(f.payload);
      if (c.command != ml::kMavCmdSetMessageInterval) return;
      ++commands_;
      requested_msgid_ = c.param[0];
      requested_interval_us_ = c.param[1];
      ml::CommandAckMsg a;
      a.command = c.command;
      a.result = ml::kMavResultAccepted;
      a.target_system = f.sysid;
      a.target_component = f.compid;
      send(ml::encode_command_ack(a, seq_++, 1, 1, tx_, sign_.get()));
      if (stream_ap0_ns_.load() == 0) stream_ap0_ns_ = ap_now() + o_.start_lead_ns;
    }
  }

  void run() {
    uint8_t rx[2048];
    while (!stop_) {
      const int64_t now = rt::now_ns();
      int64_t wait = 10'000'000;
      if (streaming()) {
        while (next_ < samples_.size() && t_host_ns(next_) + o_.latency_ns <= rt::now_ns()) {
          if (!o_.skip_at.count(static_cast<int>(next_.load()))) send_sample(next_);
          ++next_;
        }
        if (next_ < samples_.size()) wait = std::max<int64_t>(0, t_host_ns(next_) + o_.latency_ns - now);
        if (wait > 10'000'000) wait = 10'000'000;
      }
      pollfd p{fd_, POLLIN, 0};
      const timespec ts{0, static_cast<long>(wait)};
      if (::ppoll(&p, 1, &ts, nullptr) <= 0) continue;
      sockaddr_in from{};
      socklen_t len = sizeof from;
      const ssize_t r =
          o_.serial ? ::read(fd_, rx, sizeof rx)
                    : ::recvfrom(fd_, rx, sizeof rx, MSG_DONTWAIT, reinterpret_cast<sockaddr*>(&from), &len);
      if (r <= 0) {
        // A pty master reads EIO while no slave is open: do not spin on it.
        if (o_.serial) std::this_thread::sleep_for(std::chrono::milliseconds(5));
        continue;
      }
      if (!o_.serial) peer_ = from;
      have_peer_ = true;
      std::lock_guard<std::mutex> l(m_);
      decoder_.feed(rx, static_cast<std::size_t>(r), [&](const mavlink::MavlinkFrame& f) { on_frame(f); });
    }
  }

  SimAutopilotOptions o_;
  std::vector<SimImuSample> samples_;
  int fd_ = -1;
  uint16_t port_ = 0;
  std::string slave_;
  sockaddr_in peer_{};
  bool have_peer_ = false;
  std::unique_ptr<mavlink::MavlinkSigning> sign_, verify_, wrong_;
  mutable std::mutex m_;
  mavlink::MavlinkDecoder decoder_;
  uint8_t tx_[mavlink::kMaxFrameBytes] = {};
  uint8_t seq_ = 0;
  std::atomic<bool> stop_{false};
  std::atomic<int64_t> stream_ap0_ns_{0};
  std::atomic<std::size_t> next_{0};
  std::atomic<int> commands_{0}, timesync_answers_{0}, frames_in_{0};
  std::atomic<float> requested_msgid_{0}, requested_interval_us_{0};
  std::thread thread_;
};

}  // namespace kestrel::test

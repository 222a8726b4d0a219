// The flight controller's IMU over MAVLink (`drivers.imu.type: mavlink`,
// docs/px4.md "The flight controller's IMU").
//
// Transport: drivers/mavlink's UDP or serial link. Protocol: ask for the IMU
// message at the configured rate with COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL
// (again every second until a COMMAND_ACK says accepted or refused), TIMESYNC
// requests (10x as often until the clock offset is known), HEARTBEAT at 1 Hz.
// Parser: HIGHRES_IMU (SI units), SCALED_IMU (mG, mrad/s) or RAW_IMU (counts
// times the configured scale) -> ImuSample in B = the autopilot's body frame
// (FRD on PX4 and ArduPilot; the rig's T_CB says where the camera sits in it).
//
// Time: the autopilot's sample time (time_usec, or time_boot_ms) is mapped onto
// the host clock with TimeSync's offset (autopilot - host). Samples before the
// offset is known are dropped and counted. A mapped stamp later than the
// moment the sample arrived (beyond half the TIMESYNC round-trip gate, the
// offset's own error bound) or older than max_latency is an outlier: dropped,
// counted, and the next sample carries kImuGapBefore, as it does after a
// time jump, a NaN, or a frame refused for its checksum or signature.
//
// Real time: step() blocks on the link's descriptor (ppoll) until bytes arrive
// or the next request is due; fixed buffers, no allocation, no lock.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "kestrel/drivers/bmx055.hpp"
#include "kestrel/drivers/clock_sync.hpp"
#include "kestrel/drivers/mavlink/link.hpp"
#include "kestrel/drivers/mavlink/mavlink_decoder.hpp"
#include "kestrel/drivers/mavlink/mavlink_signing.hpp"
#include "kestrel/drivers/mavlink/time_sync.hpp"

namespace kestrel::drivers {

enum class MavlinkImuMessage : uint8_t { kHighres, kScaled, kRaw };
const char* to_string(MavlinkImuMessage m);

struct MavlinkImuConfig {
  std::string udp;            // the autopilot's HOST:PORT ...
  std::string serial_device;  // ... or its serial port (one of the two)
  int serial_baud = 921600;
  MavlinkImuMessage message = MavlinkImuMessage::kHighres;
  double rate_hz = 200;  // asked for with SET_MESSAGE_INTERVAL
  uint8_t sysid = 1;     // ours (a companion shares the vehicle's system id)
  // Ours: MAV_COMP_ID_ONBOARD_COMPUTER, not the ODOMETRY link's 197, so a router in front of both
  // links sends each one the answers meant for it.
  uint8_t compid = 191;
  uint8_t target_sysid = 1;         // the autopilot's; 0 = any
  uint8_t target_compid = 1;        // MAV_COMP_ID_AUTOPILOT1; 0 = any
  double raw_acc_mps2_per_lsb = 0;  // RAW_IMU only (required then): the board's scale
  double raw_gyro_rad_s_per_lsb = 0;
  double timesync_rate_hz = 1;
  mavlink::TimeSyncOptions timesync = [] {
    mavlink::TimeSyncOptions o;
    o.prefer_short_round_trips = true;  // the stamps of every sample depend on it
    return o;
  }();
  // A sample mapped this far before its arrival means a wrong offset, not a slow link: a late sample
  // with a right stamp is good data (a loaded test machine delays whole bursts by 100+ ms).
  int64_t max_latency_ns = 1'000'000'000;
  double gap_periods = 2.5;  // a sample this many periods after the last flags a gap
  int64_t command_retry_ns = 1'000'000'000;
  bool signing = false;  // sign what we send, accept only what verifies
  mavlink::SigningKey key;
  uint8_t link_id = 0;
  int64_t (*signing_clock_unix_ns)() = &mavlink::realtime_ns;  // the wall clock (tests and fuzzing fix it)
};

struct MavlinkImuCounters {
  uint64_t samples = 0;          // pushed
  uint64_t sink_drops = 0;       // the ring was full
  uint64_t imu_messages = 0;     // of the configured kind, from the autopilot
  uint64_t other_messages = 0;   // checked frames we do not use (other ids, other senders)
  uint64_t before_sync = 0;      // IMU messages before the clock offset was known
  uint64_t out_of_order = 0;     // autopilot or host stamp not after the last one
  uint64_t gaps = 0;             // time jumps of more than gap_periods
  uint64_t nonfinite = 0;        // NaN / Inf in a value
  uint64_t stamp_outliers = 0;   // mapped stamp in the future or older than max_latency
  uint64_t commands_sent = 0;    // SET_MESSAGE_INTERVAL
  uint64_t command_refused = 0;  // a COMMAND_ACK other than accepted
  uint64_t poll_errors = 0;
  uint64_t link_errors = 0;  // the descriptor reports an error or hang-up and gives no bytes
  // The decoder's (crc failures, unknown message ids, bytes skipped, unauthenticated) are in decoder_stats().
};

class MavlinkImuDriver {
 public:
  // Opens the config's UDP endpoint or serial port (throws std::invalid_argument naming it).
  MavlinkImuDriver(const MavlinkImuConfig& c, const HostClock& clock);
  // Over a link made elsewhere (tests).
  MavlinkImuDriver(std::unique_ptr<mavlink::Link> link, const MavlinkImuConfig& c, const HostClock& clock);

  // Sends what is due, then waits on the link (at most max_wait_ns, or until
  // the next send is due) and handles what arrived.
  void step(ImuSink& sink, int64_t max_wait_ns) noexcept;

  const MavlinkImuCounters& counters() const { return c_; }
  const mavlink::MavlinkDecoderStats& decoder_stats() const { return decoder_.stats(); }
  const mavlink::TimeSync& time_sync() const { return sync_; }
  const mavlink::LinkStats& link_stats() const { return link_->stats(); }
  const mavlink::SigningStats* signing_stats() const { return signing_ ? &signing_->stats() : nullptr; }
  bool interval_accepted() const { return interval_state_ == kAccepted; }
  const std::string& endpoint() const { return link_->endpoint(); }
  // Counters in one line for the end-of-run report.
  std::string report() const;

 private:
  enum IntervalState { kAsking, kAccepted, kRefused };
  void send_due(int64_t now_ns) noexcept;
  void on_frame(const mavlink::MavlinkFrame& f, int64_t t_recv_ns, ImuSink& sink) noexcept;
  void on_imu(int64_t t_dev_ns, const double acc[3], const double gyro[3], float temp_c, int64_t t_recv_ns,
              ImuSink& sink) noexcept;
  bool from_autopilot(const mavlink::MavlinkFrame& f) const noexcept;
  void send(std::size_t n) noexcept { link_->send(tx_, n); }

  MavlinkImuConfig cfg_;
  const HostClock& clock_;
  std::unique_ptr<mavlink::Link> link_;
  std::unique_ptr<mavlink::MavlinkSigning> signing_;
  mavlink::MavlinkDecoder decoder_;
  mavlink::TimeSync sync_;
  MavlinkImuCounters c_;
  uint32_t msgid_ = 0;
  int64_t period_ns_ = 0;
  IntervalState interval_state_ = kAsking;
  int64_t next_command_ns_ = 0, next_timesync_ns_ = 0, next_heartbeat_ns_ = 0;
  int64_t last_dev_ns_ = -1, last_host_ns_ = -1;
  bool gap_pending_ = false;
  uint64_t refused_seen_ = 0;
  uint32_t seq_out_ = 0;
  uint8_t tx_seq_ = 0;
  uint8_t tx_[mavlink::kMaxFrameBytes] = {};
  uint8_t rx_[2048] = {};
};

}  // namespace kestrel::drivers

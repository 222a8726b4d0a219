// The flight-controller link as the pipeline's output thread uses it:
// ODOMETRY per pose (adapter + encoder), HEARTBEAT at 1 Hz as an onboard
// controller with the visual-inertial-odometry component id, and TIMESYNC
// (answering the autopilot's requests, asking for its clock and stamping
// time_usec in it once known), over UDP or a serial port. No allocation after
// construction; call from one thread. docs/px4.md.
#pragma once

#include <memory>
#include <string>

#include "kestrel/drivers/mavlink/link.hpp"
#include "kestrel/drivers/mavlink/mavlink_decoder.hpp"
#include "kestrel/drivers/mavlink/time_sync.hpp"
#include "kestrel/mavlink/odometry_adapter.hpp"

namespace kestrel::mavlink {

struct OdometryStreamOptions {
  std::string endpoint;       // UDP HOST:PORT ...
  std::string serial_device;  // ... or a serial port (one of the two)
  int serial_baud = 921600;
  uint8_t sysid = 1;  // MAVLink convention: a companion computer shares the vehicle's system id
  uint8_t compid = kMavCompIdVisualInertialOdometry;
  OdometryAdapterOptions adapter;
  // ODOMETRY at most this often (a pose sooner than 0.9 period after the last
  // one sent is skipped); 0: every pose.
  double odometry_rate_hz = 0.0;
  double heartbeat_rate_hz = 1.0;  // 0: none
  bool timesync = true;            // answer the autopilot's TIMESYNC, and ask for its clock
  double timesync_rate_hz = 1.0;   // our requests (10x as often until the offset is known)
  TimeSyncOptions timesync_options;
  // Pose times are CLOCK_MONOTONIC (live): put them on the autopilot's clock
  // once TIMESYNC knows it. Replay's are the log's: sent as they are.
  bool stamps_on_host_clock = true;
  // MAVLink 2 signing (drivers/mavlink/mavlink_signing.hpp): every frame we
  // send is signed, and only frames that verify are read.
  bool signing = false;
  SigningKey signing_key;
  uint8_t signing_link_id = 0;
};

struct OdometryStreamStats {
  uint64_t odometry_sent = 0;
  uint64_t rate_skipped = 0;
  uint64_t heartbeats_sent = 0;
  uint64_t autopilot_heartbeats = 0;  // HEARTBEATs received
};

class OdometryStream {
 public:
  // Opens the UDP endpoint or the serial port of `opt` (throws
  // std::invalid_argument naming it when it cannot).
  explicit OdometryStream(const OdometryStreamOptions& opt);
  // Over a link made elsewhere (tests).
  OdometryStream(std::unique_ptr<Link> link, const OdometryStreamOptions& opt);
  // Converts, encodes and sends one pose (after service()); false when
  // nothing was sent: uninitialised, skipped by the rate, or the send failed.
  bool publish(const core::PoseSample& in) noexcept;
  // Reads what the autopilot sent, answers TIMESYNC requests, sends the
  // heartbeat and our TIMESYNC requests when due. Call it often (every output
  // drain); now_ns: CLOCK_MONOTONIC.
  void service(int64_t now_ns) noexcept;

  const LinkStats& stats() const { return link_->stats(); }
  const OdometryStreamStats& stream_stats() const { return stats_; }
  const TimeSync& time_sync() const { return sync_; }
  const MavlinkDecoderStats& decoder_stats() const { return decoder_.stats(); }
  const SigningStats* signing_stats() const { return signing_ ? &signing_->stats() : nullptr; }
  uint64_t not_initialised() const { return skipped_; }
  const std::string& endpoint() const { return link_->endpoint(); }

 private:
  bool send(std::size_t n) noexcept;

  OdometryStreamOptions opt_;
  std::unique_ptr<Link> link_;
  std::unique_ptr<MavlinkSigning> signing_;
  MavlinkDecoder decoder_;
  TimeSync sync_;
  OdometryStreamStats stats_;
  uint8_t frame_[kMaxFrameBytes] = {};
  uint8_t rx_[512] = {};
  uint8_t seq_ = 0;
  uint64_t skipped_ = 0;
  int64_t last_odometry_t_ns_ = -1;
  int64_t next_heartbeat_ns_ = -1;
  int64_t next_timesync_ns_ = -1;
  uint8_t status_ = kMavStateStandby;
};

// MAV_STATE for the heartbeat from the estimator's quality.
uint8_t mav_state_of(core::TrackingQuality q);

}  // namespace kestrel::mavlink

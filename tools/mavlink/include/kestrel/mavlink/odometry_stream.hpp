// ODOMETRY to a UDP endpoint: adapter + encoder + sender, one call per pose.
#pragma once

#include <memory>
#include <string>

#include "kestrel/mavlink/odometry_adapter.hpp"
#include "kestrel/mavlink/udp_sender.hpp"

namespace kestrel::mavlink {

struct OdometryStreamOptions {
  std::string endpoint;  // HOST:PORT
  uint8_t sysid = 1;     // MAVLink convention: a companion computer shares the vehicle's system id
  uint8_t compid = 197;  // MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
  OdometryAdapterOptions adapter;
};

class OdometryStream {
 public:
  explicit OdometryStream(const OdometryStreamOptions& opt);
  // Converts, encodes and sends; false when nothing was sent (uninitialised,
  // or the send failed: counted in stats()).
  bool publish(const OdometryInput& in) noexcept;
  const UdpSenderStats& stats() const { return sender_.stats(); }
  uint64_t not_initialised() const { return skipped_; }
  const std::string& endpoint() const { return sender_.endpoint(); }

 private:
  OdometryStreamOptions opt_;
  UdpSender sender_;
  uint8_t seq_ = 0;
  uint64_t skipped_ = 0;
};

}  // namespace kestrel::mavlink

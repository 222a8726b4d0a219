#include "kestrel/mavlink/odometry_stream.hpp"

namespace kestrel::mavlink {

OdometryStream::OdometryStream(const OdometryStreamOptions& opt) : opt_(opt), sender_(opt.endpoint) {}

bool OdometryStream::publish(const OdometryInput& in) noexcept {
  OdometryMsg m;
  if (!to_odometry(in, opt_.adapter, m)) {
    ++skipped_;
    return false;
  }
  uint8_t frame[kMaxFrameBytes];
  const std::size_t n = encode_odometry(m, seq_++, opt_.sysid, opt_.compid, frame);
  return sender_.send(frame, n);
}

}  // namespace kestrel::mavlink

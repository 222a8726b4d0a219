#include "kestrel/drivers/mavlink/mavlink_decoder.hpp"

#include <cstring>

namespace kestrel::mavlink {

void MavlinkDecoder::resync(std::size_t from) {
  std::size_t i = from;
  while (i < n_ && buf_[i] != kStxV2) ++i;
  stats_.bytes_skipped += i;
  std::memmove(buf_, buf_ + i, n_ - i);
  n_ -= i;
}

bool MavlinkDecoder::scan() {
  for (;;) {
    if (n_ == 0) return false;
    if (buf_[0] != kStxV2) {
      resync(0);
      continue;
    }
    if (n_ < kHeaderV2Bytes) return false;
    const uint8_t len = buf_[1];
    const uint8_t incompat = buf_[2];
    if ((incompat & ~0x01u) != 0) {  // only MAVLINK_IFLAG_SIGNED is defined
      ++stats_.bad_header;
      resync(1);
      continue;
    }
    const bool is_signed = (incompat & 0x01u) != 0;
    const std::size_t need = kHeaderV2Bytes + len + kChecksumBytes + (is_signed ? kSignatureBlockBytes : 0);
    if (n_ < need) return false;
    const uint32_t msgid = static_cast<uint32_t>(buf_[7]) | static_cast<uint32_t>(buf_[8]) << 8 |
                           static_cast<uint32_t>(buf_[9]) << 16;
    uint8_t crc_extra = 0;
    std::size_t full_len = 0;
    if (!message_spec(msgid, &crc_extra, &full_len)) {
      // Unchecked, so possibly a false start byte: skipping by its length
      // could swallow real frames; the bytes after the start byte are
      // scanned again instead.
      ++stats_.unknown_msgid;
      resync(1);
      continue;
    }
    uint16_t crc = crc_x25(buf_ + 1, kHeaderV2Bytes - 1 + len);
    crc = crc_x25_accumulate(crc_extra, crc);
    const std::size_t c = kHeaderV2Bytes + len;
    if (buf_[c] != (crc & 0xFF) || buf_[c + 1] != (crc >> 8)) {
      ++stats_.bad_crc;
      resync(1);
      continue;
    }
    if (signing_ != nullptr && signing_->verify(buf_, need) != SignatureCheck::kOk) {
      // A real frame (its checksum holds), so it is skipped whole.
      ++stats_.unauthenticated;
      std::memmove(buf_, buf_ + need, n_ - need);
      n_ -= need;
      continue;
    }
    frame_.msgid = msgid;
    frame_.seq = buf_[4];
    frame_.sysid = buf_[5];
    frame_.compid = buf_[6];
    frame_.payload_len = len;
    frame_.is_signed = is_signed;
    // A longer payload than this build's message is a newer sender's
    // extension: keep what we know.
    const std::size_t keep = len < full_len ? len : full_len;
    std::memcpy(frame_.payload, buf_ + kHeaderV2Bytes, keep);
    std::memset(frame_.payload + keep, 0, sizeof frame_.payload - keep);
    ++stats_.frames;
    std::memmove(buf_, buf_ + need, n_ - need);
    n_ -= need;
    return true;
  }
}

}  // namespace kestrel::mavlink

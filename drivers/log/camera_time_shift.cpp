#include "kestrel/drivers/camera_time_shift.hpp"

#include <algorithm>
#include <cstdlib>

namespace kestrel::drivers {
namespace {

// A depth image this close after its colour image belongs to the same frame
// (ReplaySource pairs them within the same bound).
constexpr int64_t kDepthFollowsNs = 20'000'000;

int rank_of(RecordType t) {
  switch (t) {
    case RecordType::kImu:
      return 0;
    case RecordType::kRgb:
      return 1;
    case RecordType::kDepth:
      return 2;
    case RecordType::kGroundTruth:
      return 3;
    case RecordType::kEvent:
      return 4;
    case RecordType::kRight:
      return 5;
  }
  return 6;
}

}  // namespace

int64_t record_time_ns(const LogRecord& r) {
  switch (r.type) {
    case RecordType::kImu:
      return r.imu.t_ns;
    case RecordType::kRgb:
    case RecordType::kDepth:
    case RecordType::kRight:
      return r.image.t_ns;
    case RecordType::kGroundTruth:
      return r.gt.t_ns;
    case RecordType::kEvent:
      return r.event.t_ns;
  }
  return 0;
}

void CameraTimeShift::clear() {
  held_.clear();
  newest_raw_ns_ = INT64_MIN;
  last_was_rgb_ = false;
}

void CameraTimeShift::push(LogRecord&& r) {
  const int64_t raw = record_time_ns(r);
  newest_raw_ns_ = std::max(newest_raw_ns_, raw);
  int64_t key = raw;
  int rank = rank_of(r.type);
  if (r.type == RecordType::kRgb || r.type == RecordType::kDepth) {
    key = raw + offset_ns_;
    r.image.t_ns = key;
    // Depth stays right behind its colour image even when its own stamp
    // differs a little, so nothing is sorted in between the pair.
    if (r.type == RecordType::kDepth && last_was_rgb_ &&
        std::llabs(raw - last_rgb_raw_ns_) <= kDepthFollowsNs)
      key = last_rgb_key_ns_;
  }
  last_was_rgb_ = r.type == RecordType::kRgb;
  if (last_was_rgb_) {
    last_rgb_raw_ns_ = raw;
    last_rgb_key_ns_ = key;
  }
  // Mostly in order already: search from the back, stable for equal keys.
  auto it = held_.end();
  while (it != held_.begin()) {
    auto prev = std::prev(it);
    if (prev->key_ns < key || (prev->key_ns == key && prev->rank <= rank)) break;
    it = prev;
  }
  held_.insert(it, Held{key, rank, std::move(r)});
}

bool CameraTimeShift::pop(LogRecord& out, bool source_done) {
  if (held_.empty()) return false;
  // Records still unread have raw stamps >= newest_raw_ns_ (the file's order),
  // so their keys are >= newest_raw_ns_ + min(0, offset); strictly below that
  // nothing can overtake the head.
  const int64_t horizon = newest_raw_ns_ + std::min<int64_t>(0, offset_ns_);
  if (!source_done && held_.front().key_ns >= horizon) return false;
  out = std::move(held_.front().rec);
  held_.pop_front();
  return true;
}

}  // namespace kestrel::drivers

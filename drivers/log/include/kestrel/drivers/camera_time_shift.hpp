// Camera stamps onto the IMU's clock, for readers that stream records in the
// order a file stores them (KlogReader). The rig's time_offset_cam_imu_ns is
// added to every colour and depth stamp (t_imu = t_cam + offset,
// docs/frames.md), and because that moves images past the IMU samples around
// them, records are held back until nothing still unread can come before them
// (about |offset| of records). Folder readers shift their whole tables instead.
#pragma once

#include <cstdint>
#include <deque>

#include "kestrel/drivers/log_source.hpp"

namespace kestrel::drivers {

// A stamp of the camera's clock on the IMU's: the one place the sign is applied.
inline int64_t camera_stamp_on_imu_clock(const Rig& rig, int64_t t_cam_ns) {
  return t_cam_ns + rig.time_offset_cam_imu_ns;
}

// A record's own stamp (sample, image, ground-truth or event time), as stored.
int64_t record_time_ns(const LogRecord& r);

// The rig to write beside records read from a LogSource: their camera stamps
// already carry the offset, so a file written from them has none left.
inline Rig rig_for_shifted_records(Rig rig) {
  rig.time_offset_cam_imu_ns = 0;
  return rig;
}

class CameraTimeShift {
 public:
  explicit CameraTimeShift(int64_t offset_ns = 0) : offset_ns_(offset_ns) {}
  int64_t offset_ns() const { return offset_ns_; }
  // Forgets everything held (rewind).
  void clear();
  // The next record as the file stores it; camera stamps are shifted here.
  void push(LogRecord&& r);
  // The next record in time order, once no later push can precede it; with
  // `source_done` everything held is released. False: push more (or done).
  bool pop(LogRecord& out, bool source_done);
  std::size_t held() const { return held_.size(); }

 private:
  struct Held {
    int64_t key_ns{};
    int rank{};  // at equal times: IMU, colour, depth, ground truth, event (the folder readers' order)
    LogRecord rec;
  };
  int64_t offset_ns_;
  std::deque<Held> held_;
  int64_t newest_raw_ns_ = INT64_MIN;
  bool last_was_rgb_ = false;
  int64_t last_rgb_raw_ns_ = 0, last_rgb_key_ns_ = 0;
};

}  // namespace kestrel::drivers

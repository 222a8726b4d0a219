// Internal to kestrel_drivers_datasets: the LogSource the folder readers
// (EuRoC, TUM, ETH3D, OpenLORIS, rosbag) fill with per-stream tables, merged
// in time order, images loaded only when replayed. Their line splitting and
// number parsing is the text layer's (kestrel/drivers/text.hpp).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/text.hpp"

namespace kestrel::drivers::text {

struct ImageEntry {
  int64_t t_ns = 0;
  int64_t t_recv_ns = 0;
  uint32_t seq = 0;
  std::string path;
  std::string where;  // "file:line" of the row that listed it
  uint64_t line = 0;
};

template <typename T>
struct Row {
  T value;
  uint64_t line = 0;
};

// Holds every stream's table (small: images stay on disk until next()).
class StreamLogSource final : public LogSource {
 public:
  const Rig& rig() const override { return rig_; }
  bool next(LogRecord& out) override;
  void rewind() override;
  const std::vector<LogProblem>& problems() const override { return problems_; }

  std::string format_name() const override { return "folder"; }

  // Filled by the reader that owns this table set.
  void problem(std::string where, std::string kind, std::string detail) {
    problems_.push_back(LogProblem{std::move(where), std::move(kind), std::move(detail)});
  }
  // Puts the camera stamps on the IMU's clock (rig_'s time_offset_cam_imu_ns:
  // set rig_ first), then stable-sorts each stream by time; rows out of order
  // are reported (and kept).
  void order_streams(const std::string& imu_file, const std::string& gt_file);

  Rig rig_;
  std::vector<LogProblem> problems_;
  std::vector<Row<ImuSample>> imu_;
  std::vector<ImageEntry> rgb_;
  std::vector<ImageEntry> depth_;
  std::vector<ImageEntry> right_;  // a stereo pair's right camera (RecordType::kRight)
  std::vector<Row<GroundTruthPose>> gt_;
  std::vector<Row<Event>> events_;

 private:
  bool load_image(const ImageEntry& e, RecordType type, LogImage& img);
  size_t i_imu_ = 0, i_rgb_ = 0, i_depth_ = 0, i_right_ = 0, i_gt_ = 0, i_ev_ = 0;
  size_t images_reported_until_ = 0;  // image decode failures are reported once across rewinds
  size_t images_seen_ = 0;
};

}  // namespace kestrel::drivers::text

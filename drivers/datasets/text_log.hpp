// Internal to kestrel_drivers: what the folder readers (EuRoC, TUM) share —
// line splitting and exact number parsing, and a LogSource that merges
// per-stream tables in time order and loads images only when replayed.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/drivers/log_source.hpp"

namespace kestrel::drivers::text {

// Lines of a text file without their end-of-line (CRLF tolerated). False when
// the file cannot be read.
bool read_lines(const std::string& path, std::vector<std::string>& lines);
std::string trim(const std::string& s);
std::vector<std::string> split(const std::string& s, char sep);     // fields trimmed
std::vector<std::string> split_ws(const std::string& s);
bool parse_i64(const std::string& s, int64_t& v);
// Any number strtod accepts, including nan/inf (callers decide about those).
bool parse_f64(const std::string& s, double& v);
// "1305031102.175304" -> 1305031102175304000, exactly (no double rounding).
bool parse_seconds_ns(const std::string& s, int64_t& t_ns);
std::string seconds_from_ns(int64_t t_ns);   // "1305031102.175304000"
std::string fmt17(double v);                 // %.17g
std::string file_name(const std::string& path);
bool is_file(const std::string& path);
bool is_dir(const std::string& path);

struct ImageEntry {
  int64_t t_ns = 0;
  int64_t t_recv_ns = 0;
  uint32_t seq = 0;
  std::string path;
  std::string where;   // "file:line" of the row that listed it
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
  // Stable-sorts each stream by time; rows out of order are reported (and kept).
  void order_streams(const std::string& imu_file, const std::string& gt_file);

  Rig rig_;
  std::vector<LogProblem> problems_;
  std::vector<Row<ImuSample>> imu_;
  std::vector<ImageEntry> rgb_;
  std::vector<ImageEntry> depth_;
  std::vector<Row<GroundTruthPose>> gt_;
  std::vector<Row<Event>> events_;

 private:
  bool load_image(const ImageEntry& e, RecordType type, LogImage& img);
  size_t i_imu_ = 0, i_rgb_ = 0, i_depth_ = 0, i_gt_ = 0, i_ev_ = 0;
  size_t images_reported_until_ = 0;   // image decode failures are reported once across rewinds
  size_t images_seen_ = 0;
};

}  // namespace kestrel::drivers::text

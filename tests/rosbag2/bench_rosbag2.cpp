// Writer and reader throughput of rosbag2 on a VGA sim flight (docs/ros2.md):
// `kestrel sim --scenario figure8 --duration 10` (640x480, 30 Hz), records held
// in memory so only the writer / reader is timed. Prints MB/s of .mcap and
// colour frames per second for each chunk compression.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <filesystem>

#include "db3_fixture.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/rosbag2.hpp"
#include "run_command.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

class MemorySource : public drivers::LogSource {
 public:
  explicit MemorySource(drivers::LogSource& s) : rig_(s.rig()) {
    drivers::LogRecord r;
    while (s.next(r)) recs_.push_back(r);
  }
  const Rig& rig() const override { return rig_; }
  bool next(drivers::LogRecord& out) override {
    if (pos_ >= recs_.size()) return false;
    out = recs_[pos_++];
    return true;
  }
  void rewind() override { pos_ = 0; }
  const std::vector<drivers::LogProblem>& problems() const override { return problems_; }
  std::string format_name() const override { return "memory"; }

 private:
  Rig rig_;
  std::vector<drivers::LogRecord> recs_;
  std::vector<drivers::LogProblem> problems_;
  size_t pos_ = 0;
};

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

TEST(Rosbag2Bench, WriterAndReaderThroughputOnAVgaFlight) {
  const std::string dir = temp_dir("rosbag2_bench");
  const std::string klog = dir + "/fig8.klog";
  const CmdResult r = run_kestrel("sim --scenario figure8 --duration 10 --out " + klog);
  ASSERT_EQ(r.code, 0) << r.out;
  drivers::KlogReader kr(klog);
  MemorySource mem(kr);
  for (const auto& [comp, name] :
       std::vector<std::pair<std::string, std::string>>{{"zstd", "zstd"}, {"lz4", "lz4"}, {"", "none"}}) {
    const std::string bag = dir + "/bag_" + name;
    drivers::Rosbag2WriteOptions wo;
    wo.mcap.compression = comp;
    auto t0 = std::chrono::steady_clock::now();
    const drivers::Rosbag2Stats st = drivers::export_rosbag2(mem, bag, wo);
    const double tw = seconds_since(t0);
    t0 = std::chrono::steady_clock::now();
    drivers::Rosbag2Reader rd(bag);
    drivers::LogRecord rec;
    size_t frames = 0, n = 0;
    while (rd.next(rec)) n++, frames += rec.type == drivers::RecordType::kRgb;
    const double tr = seconds_since(t0);
    EXPECT_EQ(frames, st.rgb);
    const double mb = static_cast<double>(st.bytes) / 1e6;
    std::printf(
        "rosbag2 %-5s: %.1f MB .mcap, %zu frames; write %.2f s = %.0f MB/s, %.0f frames/s; "
        "read %.2f s = %.0f MB/s, %.0f frames/s\n",
        name.c_str(), mb, st.rgb, tw, mb / tw, st.rgb / tw, tr, mb / tr, frames / tr);
    if (!comp.empty()) continue;
    // The same messages in rosbag2's sqlite3 storage (written by libsqlite3, db3_fixture.hpp).
    const std::string sq = dir + "/bag_db3";
    write_db3_from_mcap(bag + "/bag_none_0.mcap", sq, "bag_db3_0.db3");
    const double db_mb = static_cast<double>(std::filesystem::file_size(sq + "/bag_db3_0.db3")) / 1e6;
    t0 = std::chrono::steady_clock::now();
    drivers::Rosbag2Reader db(sq);
    size_t db_frames = 0;
    while (db.next(rec)) db_frames += rec.type == drivers::RecordType::kRgb;
    const double td = seconds_since(t0);
    EXPECT_EQ(db_frames, st.rgb);
    std::printf("rosbag2 db3  : %.1f MB .db3, %zu frames; read %.2f s = %.0f MB/s, %.0f frames/s\n", db_mb,
                db_frames, td, db_mb / td, db_frames / td);
  }
}

}  // namespace
}  // namespace kestrel::test

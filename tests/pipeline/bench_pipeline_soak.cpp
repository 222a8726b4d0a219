// Soak (label bench, not in the default run): 30 simulated minutes in fast
// pace through the real harness, peak RSS sampled once a simulated minute.
// Asserts RSS flat after warm-up: the last sample within 5 % (and 8 MB) of
// the sample at minute 2. The curve is printed as `SOAK-RSS t_min rss_mb`.
//
// The log is never on disk whole: a simulator thread renders into a bounded
// queue that a LogSource reads, so 30 minutes need a few MB, not gigabytes.
#include <malloc.h>
#include <sys/resource.h>

#include <condition_variable>
#include <deque>
#include <fstream>
#include <mutex>
#include <thread>

#include "pipeline_fixture.hpp"

namespace kestrel::pipeline_test {
namespace {

double peak_rss_mb() {
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  return static_cast<double>(ru.ru_maxrss) / 1024.0;
}

// The simulator on its own thread, its records handed over through a bounded
// queue: a LogSource of any length in constant memory.
class StreamingSimSource final : public drivers::LogSource {
 public:
  explicit StreamingSimSource(const tools::SimOptions& o)
      : sink_(*this), thread_([this, o] {
          try {
            tools::run_simulation(o, sink_);
          } catch (const std::exception& e) {
            std::fprintf(stderr, "simulation failed: %s\n", e.what());
          }
          std::lock_guard<std::mutex> l(m_);
          done_ = true;
          cv_.notify_all();
        }) {
    std::unique_lock<std::mutex> l(m_);
    cv_.wait(l, [this] { return have_rig_ || done_; });
  }
  ~StreamingSimSource() override {
    {
      std::lock_guard<std::mutex> l(m_);
      abandoned_ = true;
      q_.clear();
      cv_.notify_all();
    }
    thread_.join();
  }
  const Rig& rig() const override { return rig_; }
  bool next(drivers::LogRecord& out) override {
    std::unique_lock<std::mutex> l(m_);
    cv_.wait(l, [this] { return !q_.empty() || done_; });
    if (q_.empty()) return false;
    out = std::move(q_.front());
    q_.pop_front();
    cv_.notify_all();
    return true;
  }
  void rewind() override { throw std::logic_error("a streamed simulation cannot rewind"); }
  const std::vector<drivers::LogProblem>& problems() const override { return problems_; }
  std::string format_name() const override { return "sim-stream"; }

 private:
  class Sink final : public tools::SimSink {
   public:
    explicit Sink(StreamingSimSource& s) : s_(s) {}
    void begin(const Rig& rig) override {
      std::lock_guard<std::mutex> l(s_.m_);
      s_.rig_ = rig;
      s_.have_rig_ = true;
      s_.cv_.notify_all();
    }
    void imu(const ImuSample& x) override {
      drivers::LogRecord r;
      r.type = drivers::RecordType::kImu;
      r.imu = x;
      s_.push(std::move(r));
    }
    void image(drivers::RecordType type, int64_t t_ns, uint32_t seq, const ImageView& v) override {
      drivers::LogRecord r;
      r.type = type;
      r.image.t_ns = r.image.t_recv_ns = t_ns;
      r.image.seq = seq;
      r.image.width = v.width;
      r.image.height = v.height;
      r.image.format = v.format;
      r.image.pixels.assign(v.data, v.data + static_cast<size_t>(v.height) * v.stride_bytes);
      s_.push(std::move(r));
    }
    void ground_truth(const GroundTruthPose& gt) override {
      drivers::LogRecord r;
      r.type = drivers::RecordType::kGroundTruth;
      r.gt = gt;
      s_.push(std::move(r));
    }
    void event(const Event&) override {}
    void end() override {}

   private:
    StreamingSimSource& s_;
  };

  void push(drivers::LogRecord&& r) {
    std::unique_lock<std::mutex> l(m_);
    cv_.wait(l, [this] { return q_.size() < kCapacity || abandoned_; });
    if (abandoned_) throw std::runtime_error("consumer gone");
    q_.push_back(std::move(r));
    cv_.notify_all();
  }

  static constexpr size_t kCapacity = 256;
  std::mutex m_;
  std::condition_variable cv_;
  std::deque<drivers::LogRecord> q_;
  Rig rig_;
  bool have_rig_ = false, done_ = false, abandoned_ = false;
  std::vector<drivers::LogProblem> problems_;
  Sink sink_;
  std::thread thread_;
};

TEST(PipelineSoak, ThirtyMinutesFastPaceRssFlat) {
  const char* m = std::getenv("KESTREL_SOAK_MINUTES");
  const double minutes = m != nullptr ? std::atof(m) : 30.0;
  tools::SimOptions o = small_sim(minutes * 60.0, 31);
  o.threads = 1;
  o.gt_rate_hz = 10;

  std::vector<size_t> poses_at;                 // poses kept in the trajectory at each sample
  std::vector<std::pair<double, double>> rss;   // (minute, current RSS)
  std::vector<std::pair<double, double>> peak;  // (minute, peak RSS)
  int64_t t0 = -1, next = 0;
  size_t poses = 0;
  cli::ReplayOptions ro;
  ro.pace = drivers::ReplayPace::kFast;
  ro.estimator = backend();
  ro.open_source = [&o] { return std::make_unique<StreamingSimSource>(o); };
  ro.on_pose = [&](const core::PoseSample& p) {
    ++poses;
    if (t0 < 0) t0 = p.t_ns;
    if (p.t_ns - t0 >= next) {
      const double min = 1e-9 * static_cast<double>(p.t_ns - t0) / 60.0;
      rss.emplace_back(min, test::rss_mb());
      poses_at.push_back(poses);
      peak.emplace_back(min, peak_rss_mb());
      // glibc's own count beside RSS: bytes in use growing means a container
      // or a leak; RSS growing while they stay flat means the allocator's
      // arenas fragment (the map threads allocate, by design).
      const struct mallinfo2 mi = mallinfo2();
      std::printf(
          "SOAK-RSS %5.1f min  rss %7.1f MB  peak %7.1f MB  poses %zu  heap in use %7.2f MB  free in arenas "
          "%7.2f MB"
          "  mmapped %6.2f MB\n",
          min, rss.back().second, peak.back().second, poses, static_cast<double>(mi.uordblks) / 1048576.0,
          static_cast<double>(mi.fordblks) / 1048576.0, static_cast<double>(mi.hblkhd) / 1048576.0);
      std::fflush(stdout);
      next += 60'000'000'000;
    }
  };
  const cli::ReplayReport r = cli::run_replay(ro);
  std::printf("%s", cli::replay_summary(r).c_str());
  ASSERT_GE(rss.size(), 4u) << "the soak ended early";
  // Warm-up: the first two minutes (keyframes, buffers, the trajectory vector's growth).
  size_t base = 0;
  while (base < rss.size() && rss[base].first < 2.0) ++base;
  ASSERT_LT(base, rss.size());
  const double rss_base = rss[base].second, rss_last = rss.back().second;
  const double peak_base = peak[base].second, peak_last = peak.back().second;
  std::printf(
      "SOAK | %.0f min | rss %.1f -> %.1f MB | peak %.1f -> %.1f MB | rt factor %.1f | steady allocs %lld\n",
      minutes, rss_base, rss_last, peak_base, peak_last, r.realtime_factor,
      static_cast<long long>(r.steady_allocs));
  // The containers that grow by design are the report's two trajectories,
  // odometry and (with the map threads) map frame: one TimedPose per pose
  // each, reserved up front, their pages touched as they fill. Everything
  // above them is a leak, a growing container or the allocator's arenas
  // fragmenting (the SOAK-RSS lines' "heap in use" tells which).
  const double odom_mb = static_cast<double>(poses_at.back() - poses_at[base]) *
                         static_cast<double>(sizeof(tools::TimedPose)) / (1024.0 * 1024.0);
  const double map_share = r.trajectory.empty() ? 0.0
                                                : static_cast<double>(r.map_trajectory.size()) /
                                                      static_cast<double>(r.trajectory.size());
  const double trajectory_mb = odom_mb * (1.0 + map_share);
  std::printf(
      "SOAK | growth after warm-up %.2f MB, of which the trajectories %.2f MB (odometry %.2f, map frame "
      "%.2f)\n",
      rss_last - rss_base, trajectory_mb, odom_mb, odom_mb * map_share);
  EXPECT_LT(rss_last - rss_base - trajectory_mb, 1.5) << "RSS grows beyond the trajectory";
  EXPECT_LT(peak_last - peak_base - trajectory_mb, 1.5) << "peak RSS grows beyond the trajectory";
  EXPECT_EQ(r.steady_allocs, 0);
  EXPECT_EQ(r.counters.count("rings.output_drops"), 0u);
}

}  // namespace
}  // namespace kestrel::pipeline_test

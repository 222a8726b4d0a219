#include "kestrel/replay_runner.hpp"

#include <sys/resource.h>
#include <time.h>

#include <atomic>
#include <cstdio>
#include <memory>
#include <stdexcept>
#include <thread>

#include "kestrel/json_writer.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/spsc_ring.hpp"
#include "kestrel/rt/thread_setup.hpp"

namespace kestrel::cli {
namespace {

// One pose of the estimator's output as it crosses from the estimator thread
// to the writer: plain data, so the ring slot is all the memory it needs.
struct OutPose {
  int64_t t_ns;
  double p[3];
  double q[4];   // w x y z
};

constexpr std::size_t kOutRingCapacity = 16384;

double thread_cpu_s() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

double process_cpu_s() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

double peak_rss_mb() {
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  return static_cast<double>(ru.ru_maxrss) / 1024.0;   // ru_maxrss is in KiB on Linux
}

std::size_t max_image_bytes_for(const Rig& rig) {
  // Three bytes a pixel covers colour and (two-byte) depth alike. A rig without
  // a size (some public datasets) gets VGA; bigger images are counted and dropped.
  const std::size_t w = rig.rgb.width > 0 ? static_cast<std::size_t>(rig.rgb.width) : 640;
  const std::size_t h = rig.rgb.height > 0 ? static_cast<std::size_t>(rig.rgb.height) : 480;
  return w * h * 3;
}

// The estimator side of the harness. In lockstep it is called from the
// feeder's thread after every step; otherwise it is the estimator thread.
class EstimatorStage {
 public:
  EstimatorStage(core::Estimator& est, drivers::SensorRings& rings, rt::SpscRing<OutPose, kOutRingCapacity>& out,
                 const ReplayOptions& opt, ReplayReport& report)
      : est_(est), rings_(rings), out_(out), opt_(opt), report_(report) {}

  // Processes what the rings hold. `feeder_done` lets a frame go ahead of the
  // IMU samples that would normally follow it.
  void drain(bool feeder_done, bool lockstep) {
    for (;;) {
      ImuSample* s = rings_.imu.front();
      RgbdFrameMsg* f = rings_.frames.front();
      if (s != nullptr && (f == nullptr || s->t_ns <= f->t_ns)) {
        on_imu(*s);
        rings_.imu.pop();
        continue;
      }
      if (f != nullptr) {
        // A frame waits for the IMU up to its time, so the estimator sees
        // the two streams merged in time order.
        if (s != nullptr || lockstep || feeder_done || last_imu_t_ns_ >= f->t_ns) {
          on_frame(*f);
          rings_.frames.pop();
          continue;
        }
      }
      return;
    }
  }

  void finish() {
    if (counting_) report_.steady_allocs = static_cast<int64_t>(rt::alloc_count_this_thread() - allocs_at_warmup_);
  }

 private:
  void maybe_start_steady_state(int64_t t_ns) {
    if (first_t_ns_ < 0) first_t_ns_ = t_ns;
    if (!counting_ && t_ns - first_t_ns_ >= opt_.warmup_ns) {
      counting_ = true;
      allocs_at_warmup_ = rt::alloc_count_this_thread();
    }
  }

  void emit(const core::EstimatorOutput& o) {
    OutPose p{};
    p.t_ns = o.state.t_ns;
    for (int i = 0; i < 3; ++i) p.p[i] = o.state.p_WB[i];
    p.q[0] = o.state.q_WB.w();
    p.q[1] = o.state.q_WB.x();
    p.q[2] = o.state.q_WB.y();
    p.q[3] = o.state.q_WB.z();
    if (!out_.try_push(p)) ++report_.output_ring_drops;
    last_out_t_ns_ = p.t_ns;
  }

  void on_imu(const ImuSample& s) {
    maybe_start_steady_state(s.t_ns);
    last_imu_t_ns_ = s.t_ns;
    // In realtime pace the sample waited in the ring only as long as a live
    // one would, so latency counts from the push. In fast and lockstep pace
    // the feeder runs ahead on purpose; there only the estimator's own time
    // from taking the sample to its pose means anything.
    const int64_t t_start = opt_.pace == drivers::ReplayPace::kRealtime ? s.t_recv_ns : rt::now_ns();
    if (!est_.add_imu(s)) return;
    if (counting_) report_.imu_to_output.record(rt::now_ns() - t_start);
    // Without a camera the trajectory is sampled from the IMU-rate output.
    const bool camera_silent = last_frame_t_ns_ < 0 || s.t_ns - last_frame_t_ns_ > 1'000'000'000;
    if (camera_silent && (last_out_t_ns_ < 0 || s.t_ns - last_out_t_ns_ >= opt_.imu_only_output_period_ns)) {
      emit(est_.output());
    }
  }

  void on_frame(const RgbdFrameMsg& m) {
    maybe_start_steady_state(m.t_ns);
    last_frame_t_ns_ = m.t_ns;
    core::RgbdFrame f;
    f.t_ns = m.t_ns;
    f.seq = m.seq;
    if (const drivers::ImageBuffer* b = rings_.images.get(m.rgb_handle)) f.rgb = b->view();
    if (const drivers::ImageBuffer* b = rings_.images.get(m.depth_handle)) f.depth = b->view();
    const int64_t t0 = rt::now_ns();
    est_.add_frame(f);
    const int64_t t1 = rt::now_ns();
    if (counting_) {
      report_.tracking.record(t1 - t0);
      ++report_.steady_frames;
    }
    if (m.rgb_handle != rt::kInvalidHandle) rings_.images.release(m.rgb_handle);
    if (m.depth_handle != rt::kInvalidHandle) rings_.images.release(m.depth_handle);
    if (est_.output().quality != core::TrackingQuality::kUninitialized) emit(est_.output());
  }

  core::Estimator& est_;
  drivers::SensorRings& rings_;
  rt::SpscRing<OutPose, kOutRingCapacity>& out_;
  const ReplayOptions& opt_;
  ReplayReport& report_;
  int64_t first_t_ns_ = -1;
  int64_t last_imu_t_ns_ = -1;
  int64_t last_frame_t_ns_ = -1;
  int64_t last_out_t_ns_ = -1;
  bool counting_ = false;
  uint64_t allocs_at_warmup_ = 0;
};

void drain_output(rt::SpscRing<OutPose, kOutRingCapacity>& out, tools::Trajectory& traj) {
  while (OutPose* p = out.front()) {
    tools::TimedPose tp;
    tp.t_ns = p->t_ns;
    tp.p = Eigen::Vector3d(p->p[0], p->p[1], p->p[2]);
    tp.q = Eigen::Quaterniond(p->q[0], p->q[1], p->q[2], p->q[3]);
    traj.push_back(tp);
    out.pop();
  }
}

// Thread table of the replay harness (docs/threads.md). Priorities are asked
// for and fall back to SCHED_OTHER without privileges; the report says which.
constexpr rt::ThreadSpec kFeederThread{"kst-replay", 0, -1, 0};
constexpr rt::ThreadSpec kEstimatorThread{"kst-estimator", 0, -1, 0};

}  // namespace

ReplayReport run_replay(const ReplayOptions& opt) {
  ReplayReport report;
  std::unique_ptr<drivers::LogSource> log = drivers::open_log(opt.path, opt.format);
  report.log_path = opt.path;
  report.log_format = log->format_name();
  report.pace = opt.pace;
  report.alloc_counting = rt::alloc_hook_linked();

  // Everything sized here, before any thread starts.
  auto rings = std::make_unique<drivers::SensorRings>(max_image_bytes_for(log->rig()));
  auto out = std::make_unique<rt::SpscRing<OutPose, kOutRingCapacity>>();
  std::unique_ptr<core::Estimator> estimator_ptr = core::make_estimator(opt.estimator, log->rig());
  core::Estimator& estimator = *estimator_ptr;
  report.estimator = estimator.name();
  report.trajectory.reserve(1 << 16);

  drivers::ReplaySource source(*log, *rings, opt.pace);
  EstimatorStage stage(estimator, *rings, *out, opt, report);

  const int64_t wall0 = rt::now_ns();
  const double cpu0 = process_cpu_s();
  if (opt.pace == drivers::ReplayPace::kLockstep) {
    // One thread, strictly alternating: the same log and config give the same
    // trajectory bit for bit.
    while (source.step()) {
      stage.drain(false, true);
      drain_output(*out, report.trajectory);
    }
    stage.drain(true, true);
    stage.finish();
    report.estimator_cpu_s = thread_cpu_s();
    drain_output(*out, report.trajectory);
  } else {
    std::atomic<bool> stop{false};
    std::atomic<bool> estimator_done{false};
    double est_cpu = 0;
    std::thread feeder = rt::start_thread(kFeederThread, [&] { source.run(stop); });
    std::thread est_thread = rt::start_thread(kEstimatorThread, [&] {
      for (;;) {
        const bool done = source.finished();
        stage.drain(done, false);
        if (done && rings->imu.empty() && rings->frames.empty()) break;
        // Busy-yield: the lowest latency a non-RT process can get without a
        // wake-up primitive; a live build blocks on the driver's eventfd.
        std::this_thread::yield();
      }
      stage.finish();
      est_cpu = thread_cpu_s();
      estimator_done.store(true, std::memory_order_release);
    });
    while (!estimator_done.load(std::memory_order_acquire)) {
      drain_output(*out, report.trajectory);
      rt::sleep_for_ns(1'000'000);
    }
    feeder.join();
    est_thread.join();
    drain_output(*out, report.trajectory);
    report.estimator_cpu_s = est_cpu;
  }
  const int64_t wall1 = rt::now_ns();

  report.replay = source.stats();
  report.estimator_counters = estimator.counters();
  report.imu_ring_drops = rings->imu.drops();
  report.frame_ring_drops = rings->frames.drops();
  report.image_pool_exhausted = rings->images.failed_acquires();
  report.problems = log->problems();
  report.wall_s = 1e-9 * static_cast<double>(wall1 - wall0);
  report.cpu_s = process_cpu_s() - cpu0;
  if (report.replay.first_t_ns >= 0)
    report.log_duration_s = 1e-9 * static_cast<double>(report.replay.last_t_ns - report.replay.first_t_ns);
  report.realtime_factor = report.wall_s > 0 ? report.log_duration_s / report.wall_s : 0;
  report.peak_rss_mb = peak_rss_mb();
  return report;
}

namespace {
void histogram_json(JsonWriter& j, const std::string& name, const rt::LatencyHistogram& h) {
  j.key(name).begin_object();
  j.kv("count", static_cast<uint64_t>(h.count()));
  if (h.count() == 0) {
    j.key("p50_ms").null().key("p90_ms").null().key("p99_ms").null().key("max_ms").null();
  } else {
    j.kv("p50_ms", 1e-6 * static_cast<double>(h.percentile(50)));
    j.kv("p90_ms", 1e-6 * static_cast<double>(h.percentile(90)));
    j.kv("p99_ms", 1e-6 * static_cast<double>(h.percentile(99)));
    j.kv("max_ms", 1e-6 * static_cast<double>(h.max()));
  }
  j.end_object();
}
}  // namespace

std::string replay_metrics_json(const ReplayReport& r) {
  JsonWriter j;
  j.begin_object();
  j.kv("estimator", r.estimator).kv("log", r.log_path).kv("log_format", r.log_format);
  j.kv("pace", drivers::to_string(r.pace));
  j.kv("log_duration_s", r.log_duration_s).kv("wall_s", r.wall_s).kv("realtime_factor", r.realtime_factor);
  j.kv("cpu_s", r.cpu_s).kv("estimator_cpu_s", r.estimator_cpu_s).kv("peak_rss_mb", r.peak_rss_mb);
  j.kv("poses_out", static_cast<uint64_t>(r.trajectory.size()));
  j.key("latency").begin_object();
  histogram_json(j, "imu_to_output", r.imu_to_output);
  histogram_json(j, "tracking", r.tracking);
  j.end_object();
  j.key("records").begin_object();
  j.kv("imu", r.replay.imu_pushed).kv("frames", r.replay.frames_pushed);
  j.kv("ground_truth", r.replay.ground_truth).kv("events", r.replay.events);
  j.end_object();
  j.key("drops").begin_object();
  j.kv("imu_ring", r.imu_ring_drops).kv("frame_ring", r.frame_ring_drops);
  j.kv("output_ring", r.output_ring_drops).kv("image_pool_exhausted", r.image_pool_exhausted);
  j.kv("images_too_large", r.replay.images_too_large).kv("depth_unpaired", r.replay.depth_unpaired);
  j.end_object();
  const auto& c = r.estimator_counters;
  j.key("estimator_counters").begin_object();
  j.kv("imu_in", c.imu_in).kv("imu_used", c.imu_used).kv("frames_in", c.frames_in);
  j.kv("frames_used", c.frames_used).kv("resets", c.resets);
  j.kv("imu_non_finite", c.imu_rejects.non_finite).kv("imu_saturated", c.imu_rejects.saturated);
  j.kv("imu_out_of_order", c.imu_rejects.out_of_order).kv("imu_gaps", c.imu_rejects.gaps);
  j.end_object();
  j.key("allocations").begin_object();
  j.kv("counting", r.alloc_counting);
  if (r.alloc_counting) {
    j.kv("estimator_thread_steady", r.steady_allocs);
  } else {
    j.key("estimator_thread_steady").null();
  }
  j.kv("steady_frames", r.steady_frames);
  if (r.alloc_counting && r.steady_frames > 0) {
    j.kv("per_frame", static_cast<double>(r.steady_allocs) / static_cast<double>(r.steady_frames));
  } else {
    j.key("per_frame").null();
  }
  j.end_object();
  j.key("problems").begin_array();
  for (const auto& p : r.problems) {
    j.begin_object().kv("where", p.where).kv("kind", p.kind).kv("detail", p.detail).end_object();
  }
  j.end_array();
  j.end_object();
  return j.str() + "\n";
}

std::string replay_summary(const ReplayReport& r) {
  char buf[512];
  std::string s;
  std::snprintf(buf, sizeof buf, "estimator: %s (pace %s)\nlog: %s [%s], %.2f s of data\n", r.estimator.c_str(),
                drivers::to_string(r.pace), r.log_path.c_str(), r.log_format.c_str(), r.log_duration_s);
  s += buf;
  std::snprintf(buf, sizeof buf,
                "records: %llu IMU, %llu frames; poses out: %zu\nwall %.3f s, real-time factor %.1fx, cpu %.3f s, "
                "peak RSS %.1f MB\n",
                static_cast<unsigned long long>(r.replay.imu_pushed),
                static_cast<unsigned long long>(r.replay.frames_pushed), r.trajectory.size(), r.wall_s,
                r.realtime_factor, r.cpu_s, r.peak_rss_mb);
  s += buf;
  if (r.imu_to_output.count() > 0) {
    std::snprintf(buf, sizeof buf, "imu->output latency: p50 %.3f ms, p99 %.3f ms, max %.3f ms\n",
                  1e-6 * static_cast<double>(r.imu_to_output.percentile(50)),
                  1e-6 * static_cast<double>(r.imu_to_output.percentile(99)),
                  1e-6 * static_cast<double>(r.imu_to_output.max()));
    s += buf;
  }
  const auto& c = r.estimator_counters.imu_rejects;
  std::snprintf(buf, sizeof buf,
                "drops: imu ring %llu, frame ring %llu, output %llu; imu rejected: %llu non-finite, %llu saturated, "
                "%llu out of order, %llu gaps\n",
                static_cast<unsigned long long>(r.imu_ring_drops), static_cast<unsigned long long>(r.frame_ring_drops),
                static_cast<unsigned long long>(r.output_ring_drops), static_cast<unsigned long long>(c.non_finite),
                static_cast<unsigned long long>(c.saturated), static_cast<unsigned long long>(c.out_of_order),
                static_cast<unsigned long long>(c.gaps));
  s += buf;
  if (r.alloc_counting) {
    std::snprintf(buf, sizeof buf, "estimator-thread heap allocations after warm-up: %lld\n",
                  static_cast<long long>(r.steady_allocs));
    s += buf;
  }
  if (!r.problems.empty()) {
    std::snprintf(buf, sizeof buf, "log problems: %zu (first: %s %s %s)\n", r.problems.size(),
                  r.problems.front().where.c_str(), r.problems.front().kind.c_str(),
                  r.problems.front().detail.c_str());
    s += buf;
  }
  return s;
}

}  // namespace kestrel::cli

// Timing budgets of the whole pipeline (docs/timing.md): simulated flights at
// VGA replayed at realtime pace through the real harness (feeder thread,
// rings, estimator thread, output thread), with the budgets asserted:
//   IMU-to-pose latency p99 < 2 ms, tracking p99 < one frame period,
//   optimizer p99 < 100 ms (backends with one), no ring overflow, no heap
//   allocation on the estimator thread after warm-up;
// and the same pipeline squeezed onto one core (OneCoreVgaEmbeddedProfile).
// The margins are for a noisy 2-core CI machine; exact figures come from
// `kestrel bench` and the JSON of `kestrel replay --metrics-out`.
// A VGA log costs ~47 MB per second of flight in the temp folder and renders
// at ~1.5x real time on two threads: 30 s of hover keeps the test near a
// minute. KESTREL_TIMING_WIDTH=160 (or 320) measures at a smaller image,
// KESTREL_TIMING_SECONDS changes the length (the sample counts scale with it).
#include <sched.h>

#include <cstdlib>

#include "kestrel/rt/alloc_counter.hpp"
#include "pipeline_fixture.hpp"

namespace kestrel::pipeline_test {
namespace {

int env_int(const char* name, int def) {
  const char* v = std::getenv(name);
  return v != nullptr && *v != '\0' ? std::atoi(v) : def;
}

// Renders the flight both tests replay (two render threads, into `dir`) and
// says what it cost.
tools::SimSummary render(tools::SimOptions& o, const std::string& dir, const std::string& name) {
  o.height = *o.width * 3 / 4;
  o.threads = 2;
  o.out_path = dir + "/" + name;
  const tools::SimSummary sim = tools::run_simulation(o);
  std::printf("log: %.0f s, %dx%d, %llu frames, %.0f MB, rendered in %.1f s\n", sim.duration_s, *o.width,
              *o.height, static_cast<unsigned long long>(sim.frames),
              1e-6 * static_cast<double>(sim.output_bytes), sim.wall_s);
  return sim;
}

// Realtime pace through the real harness, statistics after 2 s of warm-up.
cli::ReplayOptions realtime_replay(const tools::SimOptions& o, const std::string& estimator) {
  cli::ReplayOptions ro;
  ro.path = o.out_path;
  ro.pace = drivers::ReplayPace::kRealtime;
  ro.estimator = estimator;
  ro.warmup_ns = 2'000'000'000;
  return ro;
}

TEST(PipelineTiming, RealtimeBudgetsAtVga) {
  ASSERT_TRUE(rt::alloc_hook_linked())
      << "the allocation hook is not linked: steady_allocs cannot be checked";
  const std::string dir = test::temp_dir("pipeline_timing");
  tools::SimOptions o = small_sim(env_int("KESTREL_TIMING_SECONDS", 30), 21);
  o.width = env_int("KESTREL_TIMING_WIDTH", 640);
  const tools::SimSummary sim = render(o, dir, "hover.klog");

  cli::ReplayOptions ro = realtime_replay(o, backend());
  uint64_t imu_poses_seen = 0;
  int64_t last_imu_pose_t_ns = -1;
  bool imu_poses_in_order = true;
  ro.on_imu_pose = [&](const core::PoseSample& p) {
    ++imu_poses_seen;
    imu_poses_in_order = imu_poses_in_order && p.t_ns > last_imu_pose_t_ns;
    last_imu_pose_t_ns = p.t_ns;
  };
  const cli::ReplayReport r = cli::run_replay(ro);
  std::filesystem::remove_all(dir);
  std::printf("%s", cli::replay_summary(r).c_str());

  const double frame_period_ms = 1000.0 / 30.0;
  const double imu_p99_ms = 1e-6 * static_cast<double>(r.imu_to_output.percentile(99));
  const double trk_p99_ms = 1e-6 * static_cast<double>(r.tracking.percentile(99));
  std::printf(
      "TIMING | backend %s | %dx%d | imu->pose p50 %.3f p99 %.3f max %.3f ms | tracking p50 %.2f p99 %.2f "
      "max "
      "%.2f ms | steady allocs %lld over %llu frames | drops imu %llu frame %llu out %llu | rt factor %.2f\n",
      r.estimator.c_str(), *o.width, *o.height, 1e-6 * static_cast<double>(r.imu_to_output.percentile(50)),
      imu_p99_ms, 1e-6 * static_cast<double>(r.imu_to_output.max()),
      1e-6 * static_cast<double>(r.tracking.percentile(50)), trk_p99_ms,
      1e-6 * static_cast<double>(r.tracking.max()), static_cast<long long>(r.steady_allocs),
      static_cast<unsigned long long>(r.steady_frames),
      static_cast<unsigned long long>(r.counters.count("rings.imu_drops")),
      static_cast<unsigned long long>(r.counters.count("rings.frame_drops")),
      static_cast<unsigned long long>(r.counters.count("rings.output_drops")), r.realtime_factor);
  std::printf("TIMING | propagation thread: %s\n", r.propagator_thread.c_str());
  std::printf(
      "TIMING | estimator thread's own view of the IMU samples (waits behind tracking): p50 %.3f p99 %.3f "
      "max %.3f ms\n",
      1e-6 * static_cast<double>(r.estimator_imu_latency.percentile(50)),
      1e-6 * static_cast<double>(r.estimator_imu_latency.percentile(99)),
      1e-6 * static_cast<double>(r.estimator_imu_latency.max()));

  const double seconds = sim.duration_s - 2.0;  // after warm-up
  ASSERT_GT(r.imu_to_output.count(), static_cast<uint64_t>(0.9 * 400.0 * seconds))
      << "too few IMU samples timed";
  ASSERT_GT(r.tracking.count(), static_cast<uint64_t>(0.9 * 30.0 * seconds)) << "too few frames timed";
  EXPECT_LT(imu_p99_ms, 2.0) << "IMU-to-pose latency budget";
  EXPECT_LT(trk_p99_ms, frame_period_ms) << "tracking budget: one frame period";
  if (r.optimizer.count() > 0) {  // backends with an optimizer (window): on its own thread in realtime pace
    const double opt_p99_ms = 1e-6 * static_cast<double>(r.optimizer.percentile(99));
    std::printf("TIMING | optimizer (%s): %llu solves, p50 %.2f p99 %.2f max %.2f ms\n",
                r.optimizer_threaded ? "own thread" : "inline",
                static_cast<unsigned long long>(r.optimizer.count()),
                1e-6 * static_cast<double>(r.optimizer.percentile(50)), opt_p99_ms,
                1e-6 * static_cast<double>(r.optimizer.max()));
    EXPECT_LT(opt_p99_ms, 100.0) << "optimizer budget";
  }
  // The IMU-rate pose reaches the output: at least one per output drain
  // (~1 ms) at 400 Hz IMU is ~13 per frame; ask for 5 to leave room for load.
  EXPECT_EQ(imu_poses_seen, r.counters.count("output.imu_rate_poses"));
  EXPECT_GT(imu_poses_seen, 5u * r.tracking.count());
  EXPECT_TRUE(imu_poses_in_order);
  EXPECT_EQ(r.counters.count("rings.imu_drops"), 0u);
  EXPECT_EQ(r.counters.count("rings.frame_drops"), 0u);
  EXPECT_EQ(r.counters.count("rings.output_drops"), 0u);
  EXPECT_EQ(r.counters.count("rings.propagator_forward_drops"), 0u);
  EXPECT_EQ(r.replay.imu_dropped, 0u);
  EXPECT_EQ(r.replay.frames_dropped, 0u);
  EXPECT_EQ(r.counters.count("rings.image_pool_exhausted"), 0u);
  EXPECT_TRUE(r.alloc_counting);
  EXPECT_EQ(r.steady_allocs, 0) << "heap allocations on the estimator thread after warm-up";
  // Realtime pace keeps pace: the replay took about as long as the log.
  EXPECT_NEAR(r.realtime_factor, 1.0, 0.05);
  // Idle threads sleep on their doorbells (docs/threads.md): the estimator
  // thread's CPU outside the backend's calls is the cost of waking per sample,
  // a few per cent of the wall time. The busy-yield it replaced spent most of
  // the wall time here (on a loaded machine still over a third).
  std::printf(
      "TIMING | process cpu %.2f s over %.2f s wall; estimator thread %.2f s, of it outside the backend %.2f "
      "s\n",
      r.cpu_s, r.wall_s, r.estimator_thread_cpu_s, r.estimator_thread_overhead_cpu_s);
  EXPECT_LT(r.estimator_thread_overhead_cpu_s, 0.1 * r.wall_s) << "the estimator thread spins while idle";
}

// One small core (docs/embedded.md): every pipeline thread pinned to the same
// CPU, VGA at 30 Hz, the embedded window (`window-embedded`), a figure-8 so
// tracking and the optimizer do real work. A companion computer that gives
// Kestrel one core sees this worst case: tracking, the optimizer, the feeder
// standing in for the drivers and the IMU-rate pose all share it, and only the
// priorities keep the pose stream on time: IMU-rate pose 65, feeder 64,
// tracking 60, optimizer 40 (the live configs' order, docs/threads.md, except
// the feeder). The feeder sits below the pose stream, not above it as a live
// driver does: it reads and copies each VGA frame out of the log (~1 ms),
// work a live camera driver does not do (it hands over a mapped buffer), and
// above kst-propagate that replay-only cost took the IMU-to-pose p99 from
// 0.2 ms to 1.4 ms. It stays above tracking so the samples are pushed on time.
// Budgets: no frame or IMU sample dropped, IMU-to-pose p99 < 1 ms, tracking
// p99 < one frame period, every frame after start-up posed, no steady-state
// allocation. The rest of the machine is not ours (ctest -j 2 runs another
// test beside this one, unpinned): SCHED_FIFO is what lets a budget hold.
// Without the privilege to use it the pose stream competes with tracking as
// an equal and 1 ms is not what that configuration promises: the test then
// says so and holds the 2 ms budget of the test above.
TEST(PipelineTiming, OneCoreVgaEmbeddedProfile) {
  ASSERT_TRUE(rt::alloc_hook_linked());
  cpu_set_t allowed;
  CPU_ZERO(&allowed);
  ASSERT_EQ(sched_getaffinity(0, sizeof(allowed), &allowed), 0);
  int cpu = -1;
  for (int c = 0; c < CPU_SETSIZE && cpu < 0; ++c)
    if (CPU_ISSET(c, &allowed)) cpu = c;
  ASSERT_GE(cpu, 0);

  const std::string dir = test::temp_dir("pipeline_one_core");
  tools::SimOptions o = small_sim(env_int("KESTREL_TIMING_SECONDS", 20), 23);
  o.scenario = "figure8";
  o.width = 640;
  const tools::SimSummary sim = render(o, dir, "figure8_vga.klog");

  cli::ReplayOptions ro = realtime_replay(o, "window-embedded");
  drivers::ThreadTable& t = ro.threads;
  for (rt::ThreadSpec& spec : t.spec) spec.cpu = cpu;
  t[drivers::PipelineThread::kPropagate].priority = 65;
  t[drivers::PipelineThread::kReplay].priority = 64;
  t[drivers::PipelineThread::kEstimator].priority = 60;
  t[drivers::PipelineThread::kOptimizer].priority = 40;
  const cli::ReplayReport r = cli::run_replay(ro);
  std::filesystem::remove_all(dir);
  std::printf("%s", cli::replay_summary(r).c_str());
  std::printf("TIMING | one core: %s\n", cli::threads_summary(r.threads).c_str());

  bool all_applied = !r.threads.empty();
  for (const cli::AppliedThread& a : r.threads) all_applied = all_applied && a.applied;
  const double imu_budget_ms = all_applied ? 1.0 : 2.0;
  if (!all_applied)
    std::printf(
        "TIMING | WARNING: the one-core table was not fully granted (no CAP_SYS_NICE / RLIMIT_RTPRIO, or CPU "
        "%d "
        "refused): IMU-to-pose held to %.0f ms, not 1 ms\n",
        cpu, imu_budget_ms);

  const double imu_p99_ms = 1e-6 * static_cast<double>(r.imu_to_output.percentile(99));
  const double trk_p99_ms = 1e-6 * static_cast<double>(r.tracking.percentile(99));
  const double opt_p99_ms = 1e-6 * static_cast<double>(r.optimizer.percentile(99));
  std::printf(
      "TIMING | one core %d | %dx%d window-embedded | imu->pose p50 %.3f p99 %.3f max %.3f ms | tracking p50 "
      "%.2f "
      "p99 %.2f ms | optimizer %llu solves p50 %.2f p99 %.2f ms | steady allocs %lld | drops imu %llu frame "
      "%llu "
      "out %llu | rt factor %.3f\n",
      cpu, *o.width, *o.height, 1e-6 * static_cast<double>(r.imu_to_output.percentile(50)), imu_p99_ms,
      1e-6 * static_cast<double>(r.imu_to_output.max()),
      1e-6 * static_cast<double>(r.tracking.percentile(50)), trk_p99_ms,
      static_cast<unsigned long long>(r.optimizer.count()),
      1e-6 * static_cast<double>(r.optimizer.percentile(50)), opt_p99_ms,
      static_cast<long long>(r.steady_allocs),
      static_cast<unsigned long long>(r.counters.count("rings.imu_drops")),
      static_cast<unsigned long long>(r.counters.count("rings.frame_drops")),
      static_cast<unsigned long long>(r.counters.count("rings.output_drops")), r.realtime_factor);

  const double seconds = sim.duration_s - 2.0;  // after warm-up
  ASSERT_GT(r.tracking.count(), static_cast<uint64_t>(0.9 * 30.0 * seconds)) << "too few frames timed";
  ASSERT_GT(r.optimizer.count(), 0u) << "the window ran no solve";
  EXPECT_LT(imu_p99_ms, imu_budget_ms) << "IMU-to-pose latency on one core";
  EXPECT_LT(trk_p99_ms, 1000.0 / 30.0) << "tracking budget: one frame period";
  EXPECT_EQ(r.counters.count("rings.imu_drops"), 0u);
  EXPECT_EQ(r.counters.count("rings.frame_drops"), 0u);
  EXPECT_EQ(r.counters.count("rings.output_drops"), 0u);
  EXPECT_EQ(r.counters.count("rings.propagator_forward_drops"), 0u);
  EXPECT_EQ(r.replay.imu_dropped, 0u);
  EXPECT_EQ(r.replay.frames_dropped, 0u) << "a frame dropped on one core";
  EXPECT_EQ(r.counters.count("rings.image_pool_exhausted"), 0u);
  EXPECT_EQ(r.steady_allocs, 0) << "heap allocations on the estimator thread after warm-up";
  // Every frame after start-up is posed: one core kept up, not merely survived.
  EXPECT_GE(static_cast<double>(r.trajectory.size()), 0.97 * static_cast<double>(sim.frames));
  EXPECT_NEAR(r.realtime_factor, 1.0, 0.05);
}

}  // namespace
}  // namespace kestrel::pipeline_test

// `kestrel replay` as a library call, so `kestrel bench` and the tests run the
// very same harness: log → ReplaySource → sensor rings → estimator thread →
// output ring → trajectory.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/core/estimator.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/replay_source.hpp"
#include "kestrel/rt/latency_histogram.hpp"
#include "kestrel/tools/trajectory_eval.hpp"

namespace kestrel::cli {

struct ReplayOptions {
  std::string path;
  drivers::LogFormat format = drivers::LogFormat::kAuto;
  drivers::ReplayPace pace = drivers::ReplayPace::kLockstep;
  std::string estimator = "vo";   // core::make_estimator name
  // Allocation counting and latency statistics start after this much log time,
  // so start-up (buffers reserved, first frames) is not counted as steady state.
  int64_t warmup_ns = 2'000'000'000;
  // Logs without camera records still get a trajectory, at this period.
  int64_t imu_only_output_period_ns = 50'000'000;
};

struct ReplayReport {
  std::string estimator;
  std::string log_path;
  std::string log_format;
  drivers::ReplayPace pace = drivers::ReplayPace::kLockstep;
  tools::Trajectory trajectory;        // body pose in W at each camera frame
  double log_duration_s = 0;
  double wall_s = 0;
  double realtime_factor = 0;          // log seconds per wall second
  double cpu_s = 0;                    // whole process
  double estimator_cpu_s = 0;          // the estimator thread alone
  double peak_rss_mb = 0;
  // Realtime pace: ring push of a sample -> its pose available (end to end).
  // Fast/lockstep pace: estimator takes the sample -> its pose available.
  rt::LatencyHistogram imu_to_output;
  rt::LatencyHistogram tracking;       // per frame, inside the estimator
  drivers::ReplayStats replay;
  core::EstimatorCounters estimator_counters;
  uint64_t imu_ring_drops = 0;
  uint64_t frame_ring_drops = 0;
  uint64_t output_ring_drops = 0;
  uint64_t image_pool_exhausted = 0;
  // Heap allocations made by the estimator thread after warm-up, and how many
  // frames it processed in that span.
  int64_t steady_allocs = 0;
  uint64_t steady_frames = 0;
  bool alloc_counting = false;
  std::vector<drivers::LogProblem> problems;
};

ReplayReport run_replay(const ReplayOptions& opt);

std::string replay_metrics_json(const ReplayReport& r);
// A few human-readable lines for the terminal.
std::string replay_summary(const ReplayReport& r);

}  // namespace kestrel::cli

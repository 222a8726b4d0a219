// Shared by the pipeline tests: short simulated logs with a fault injected
// while they are written, a replay through the real harness that keeps every
// output pose with its quality and reset counter, and the recovery measure.
#pragma once

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <string>
#include <vector>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/tools/simulator.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "test_data.hpp"

namespace kestrel::pipeline_test {

// The backend under test: `window` (the default of `kestrel replay|run`);
// KESTREL_PIPELINE_ESTIMATOR=vo (or any factory name) runs the suite on another.
inline std::string backend() {
  const char* e = std::getenv("KESTREL_PIPELINE_ESTIMATOR");
  return e != nullptr && *e != '\0' ? e : "window";
}

// Writes what the simulator produces into a .klog, through hooks that may
// drop, alter, repeat or reorder records: the fault is in the file, so the
// whole chain (reader, replay, rings, harness, estimator) meets it.
class FaultSink final : public tools::SimSink {
 public:
  using ImuHook = std::function<void(const ImuSample&, drivers::KlogWriter&)>;
  using ImageHook =
      std::function<void(drivers::RecordType, int64_t, uint32_t, const ImageView&, drivers::KlogWriter&)>;

  explicit FaultSink(std::string path) : path_(std::move(path)) {}
  ImuHook on_imu;
  ImageHook on_image;

  void begin(const Rig& rig) override { w_.open(path_, rig); }
  void imu(const ImuSample& s) override {
    if (on_imu) {
      on_imu(s, w_);
    } else {
      w_.write_imu(s);
    }
  }
  void image(drivers::RecordType type, int64_t t_ns, uint32_t seq, const ImageView& v) override {
    if (on_image) {
      on_image(type, t_ns, seq, v, w_);
    } else {
      w_.write_image(type, t_ns, t_ns, seq, 0, v);
    }
  }
  void ground_truth(const GroundTruthPose& gt) override { w_.write_ground_truth(gt); }
  void event(const Event& e) override { w_.write_event(e); }
  void end() override { w_.close(); }

 private:
  std::string path_;
  drivers::KlogWriter w_;
};

// A small, quick log: 160x120 at 30 Hz, IMU at 400 Hz, the hover flight.
inline tools::SimOptions small_sim(double duration_s, uint64_t seed = 11) {
  tools::SimOptions o;
  o.scenario = "hover";
  o.duration_s = duration_s;
  o.seed = seed;
  o.width = 160;
  o.height = 120;
  o.fps = 30.0;
  o.imu_rate_hz = 400.0;
  o.threads = 1;
  return o;
}

struct ReplayRun {
  cli::ReplayReport report;
  std::vector<core::PoseSample> poses;
  tools::Trajectory gt;
  int64_t t0_ns = 0;  // first record of the log
};

inline ReplayRun replay(const std::string& path, drivers::ReplayPace pace = drivers::ReplayPace::kLockstep) {
  ReplayRun run;
  cli::ReplayOptions o;
  o.path = path;
  o.pace = pace;
  o.estimator = backend();
  o.on_pose = [&run](const core::PoseSample& p) { run.poses.push_back(p); };
  run.report = cli::run_replay(o);
  std::vector<std::string> warnings;
  run.gt = tools::load_trajectory(path, &warnings);
  run.t0_ns = run.report.replay.first_t_ns;
  return run;
}

inline double rel_s(const ReplayRun& r, int64_t t_ns) { return 1e-9 * static_cast<double>(t_ns - r.t0_ns); }

// A pose that claims to be right: tracking, or (a backend without an IMU, or
// one whose IMU has gone silent) tracking by vision alone.
inline bool claims_tracking(core::TrackingQuality q) {
  return q == core::TrackingQuality::kTracking || q == core::TrackingQuality::kVisionOnly;
}

// Relative translation error over the last `span_s` before pose i, in the
// body frame of the earlier pose: independent of the world frames' yaw and
// origin, and of error accumulated before the span (odometry keeps that).
inline double local_error_m(const ReplayRun& r, size_t i, double span_s) {
  const auto& b = r.poses[i];
  const int64_t ta = b.t_ns - static_cast<int64_t>(span_s * 1e9);
  size_t j = i;
  while (j > 0 && r.poses[j].t_ns > ta) --j;
  const auto& a = r.poses[j];
  if (b.t_ns - a.t_ns < static_cast<int64_t>(0.5 * span_s * 1e9)) return NAN;
  const auto ga = tools::pose_at(r.gt, a.t_ns, 20'000'000);
  const auto gb = tools::pose_at(r.gt, b.t_ns, 20'000'000);
  if (!ga || !gb) return NAN;
  const Eigen::Vector3d d_est = a.q_WB().conjugate() * (b.p_WB() - a.p_WB());
  const Eigen::Vector3d d_gt = ga->q.conjugate() * (gb->p - ga->p);
  return (d_est - d_gt).norm();
}

// What the pipeline tests assert after a fault.
struct Recovery {
  bool recovered = false;
  double time_to_recover_s = NAN;  // from the end of the fault
  bool said_so = false;            // quality left kTracking or the reset counter moved during the fault
  uint32_t resets_in_fault = 0;
  double worst_local_error_after_m = 0;
  double final_local_error_m = NAN;
};

// Good: tracking, and the motion over the last 0.5 s agrees with the ground
// truth to within `bound_m`. Recovered at the first pose after the fault from
// which at least 90 % of the poses of the next second are good.
inline Recovery measure_recovery(const ReplayRun& r, double fault_start_s, double fault_end_s,
                                 double bound_m = 0.03) {
  Recovery rec;
  uint32_t reset_before = 0;
  bool have_before = false;
  std::vector<char> good(r.poses.size(), 0);
  for (size_t i = 0; i < r.poses.size(); ++i) {
    const double t = rel_s(r, r.poses[i].t_ns);
    if (t < fault_start_s) {
      reset_before = r.poses[i].reset_counter;
      have_before = true;
    }
    if (t >= fault_start_s && t <= fault_end_s + 0.5) {
      if (!claims_tracking(r.poses[i].quality)) rec.said_so = true;
      if (have_before && r.poses[i].reset_counter != reset_before) {
        rec.said_so = true;
        rec.resets_in_fault = r.poses[i].reset_counter - reset_before;
      }
    }
    const double e = local_error_m(r, i, 0.5);
    good[i] = claims_tracking(r.poses[i].quality) && std::isfinite(e) && e < bound_m;
  }
  for (size_t i = 0; i < r.poses.size(); ++i) {
    const double t = rel_s(r, r.poses[i].t_ns);
    if (t < fault_end_s) continue;
    int n = 0, ok = 0;
    size_t k = i;
    for (; k < r.poses.size() && rel_s(r, r.poses[k].t_ns) < t + 1.0; ++k) {
      ++n;
      ok += good[k];
    }
    if (k == r.poses.size()) break;  // less than a second of log left
    if (n > 0 && ok >= 0.9 * n && good[i]) {
      rec.recovered = true;
      rec.time_to_recover_s = t - fault_end_s;
      for (size_t m = i; m < r.poses.size(); ++m) {
        const double e = local_error_m(r, m, 0.5);
        if (std::isfinite(e) && e > rec.worst_local_error_after_m) rec.worst_local_error_after_m = e;
      }
      break;
    }
  }
  if (!r.poses.empty()) rec.final_local_error_m = local_error_m(r, r.poses.size() - 1, 1.0);
  return rec;
}

// One row of the fault table, printed for the report (tests/pipeline/README.md).
inline void print_row(const char* fault, const std::string& counted, const Recovery& rec) {
  std::printf(
      "FAULT-TABLE | %s | %s | %s | said so: %s |\n", fault, counted.c_str(),
      rec.recovered ? (std::to_string(rec.time_to_recover_s).substr(0, 4) + " s").c_str() : "not recovered",
      rec.said_so ? "yes" : "no");
}

}  // namespace kestrel::pipeline_test

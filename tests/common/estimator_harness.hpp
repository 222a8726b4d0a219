// Feeds simulated RGB-D + IMU logs to an Estimator the way the replay harness
// does (IMU and frames merged in time order), for the core estimator tests.
#pragma once

#include <functional>
#include <memory>
#include <string>

#include "kestrel/core/estimator.hpp"
#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/core/rig_transforms.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/tools/simulator.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "test_data.hpp"

namespace kestrel::test {

// `more`, when given, sets further options (a covered lens, a time offset);
// a caller that passes it names its own `prefix`, which names the folder.
inline std::string simulate(const std::string& scenario, double duration_s, uint64_t seed = 7,
                            const std::string& prefix = "estimator",
                            const std::function<void(tools::SimOptions&)>& more = {}) {
  // One log per (scenario, duration, seed) in a folder of this process's own
  // (temp_dir): a test that asks twice gets the same log rebuilt.
  const std::string dir = test::temp_dir(prefix + "_" + scenario + "_" + std::to_string(seed) + "_" +
                                         std::to_string(static_cast<int>(duration_s * 1000)));
  tools::SimOptions o;
  o.scenario = scenario;
  o.duration_s = duration_s;
  o.seed = seed;
  o.width = 320;
  o.height = 240;
  o.out_path = dir + "/log.klog";
  if (more) more(o);
  tools::run_simulation(o);
  return o.out_path;
}

inline Eigen::Isometry3d to_iso(const Mat4d& T) { return core::to_isometry(T); }

// Walks a simulated log frame by frame (a colour image followed by its depth):
// fn(t_ns, rgb, depth, true T_WC). For tests that drive the tracker on the truth.
template <typename Fn>
void for_each_true_frame(const std::string& path, Fn fn) {
  auto log = drivers::open_log(path);
  const Eigen::Isometry3d T_BC = to_iso(log->rig().T_BC);
  Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();
  drivers::LogRecord rec;
  drivers::LogImage rgb;
  bool have_rgb = false;
  while (log->next(rec)) {
    if (rec.type == drivers::RecordType::kGroundTruth) {
      T_WB.linear() = Eigen::Quaterniond(rec.gt.q_WB[0], rec.gt.q_WB[1], rec.gt.q_WB[2], rec.gt.q_WB[3])
                          .toRotationMatrix();
      T_WB.translation() = Eigen::Vector3d(rec.gt.p_WB.data());
    } else if (rec.type == drivers::RecordType::kRgb) {
      rgb = rec.image;
      have_rgb = true;
    } else if (rec.type == drivers::RecordType::kDepth && have_rgb) {
      have_rgb = false;
      fn(rgb.t_ns, rgb.view(), rec.image.view(), T_WB * T_BC);
    }
  }
}

struct RunResult {
  tools::Trajectory est, gt;
  uint64_t steady_allocs = 0;
  uint64_t frames = 0;        // frames fed after warm-up
  uint64_t frames_total = 0;  // frames fed
  core::EstimatorCounters counters;
};

using EstimatorMaker = std::function<std::unique_ptr<core::Estimator>(const Rig&)>;
using ImuFilter = std::function<bool(const ImuSample&)>;  // false: the sample is withheld

using AfterFrame = std::function<void(const tools::TimedPose& gt)>;  // newest ground truth at the frame

// Counts allocations inside the estimator after 1 s of log; calls
// `after_frame` (when given) after each frame that got a pose and has ground
// truth at its time.
inline RunResult run_on(drivers::LogSource& log, core::Estimator& est, const ImuFilter& keep_imu = {},
                        const AfterFrame& after_frame = {}) {
  RunResult out;
  drivers::LogRecord rec;
  drivers::LogImage rgb;
  bool have_rgb = false;
  int64_t t_first = -1;
  auto feed_frame = [&](const drivers::LogImage* depth) {
    core::RgbdFrame f;
    f.t_ns = rgb.t_ns;
    f.rgb = rgb.view();
    if (depth != nullptr) f.depth = depth->view();
    const bool steady = t_first >= 0 && rgb.t_ns - t_first > 1'000'000'000;
    rt::AllocCountScope scope;
    est.add_frame(f);
    if (steady) {
      out.steady_allocs += scope.count();
      ++out.frames;
    }
    ++out.frames_total;
    if (est.output().quality != core::TrackingQuality::kUninitialized) {
      const auto& s = est.output().state;
      out.est.push_back(tools::TimedPose{s.t_ns, s.p_WB, s.q_WB});
      if (after_frame && !out.gt.empty() && out.gt.back().t_ns == f.t_ns) after_frame(out.gt.back());
    }
    have_rgb = false;
  };
  while (log.next(rec)) {
    switch (rec.type) {
      case drivers::RecordType::kImu: {
        if (have_rgb) feed_frame(nullptr);
        if (t_first < 0) t_first = rec.imu.t_ns;
        if (keep_imu && !keep_imu(rec.imu)) break;
        const bool steady = rec.imu.t_ns - t_first > 1'000'000'000;
        rt::AllocCountScope scope;
        est.add_imu(rec.imu);
        if (steady) out.steady_allocs += scope.count();
        break;
      }
      case drivers::RecordType::kRgb:
        if (have_rgb) feed_frame(nullptr);
        rgb = rec.image;
        have_rgb = true;
        break;
      case drivers::RecordType::kDepth:
        if (have_rgb) feed_frame(&rec.image);
        break;
      case drivers::RecordType::kGroundTruth:
        out.gt.push_back(tools::TimedPose{
            rec.gt.t_ns, Eigen::Vector3d(rec.gt.p_WB.data()),
            Eigen::Quaterniond(rec.gt.q_WB[0], rec.gt.q_WB[1], rec.gt.q_WB[2], rec.gt.q_WB[3])});
        break;
      default:
        break;
    }
  }
  out.counters = est.counters();
  return out;
}

// The same with an estimator made for the log's rig. `est_out`, when given,
// receives the estimator (for backend-specific counters).
inline RunResult run(const std::string& log_path, const EstimatorMaker& make, const ImuFilter& keep_imu = {},
                     std::unique_ptr<core::Estimator>* est_out = nullptr) {
  auto log = drivers::open_log(log_path);
  std::unique_ptr<core::Estimator> est = make(log->rig());
  RunResult out = run_on(*log, *est, keep_imu);
  if (est_out != nullptr) *est_out = std::move(est);
  return out;
}

inline RunResult run(const std::string& log_path, core::Estimator& est, const AfterFrame& after_frame = {}) {
  auto log = drivers::open_log(log_path);
  return run_on(*log, est, {}, after_frame);
}

inline RunResult run(const std::string& log_path, const std::string& estimator) {
  return run(log_path, [&](const Rig& rig) { return core::make_estimator(estimator, rig); });
}

inline double ate(const RunResult& r) {
  tools::EvalOptions eo;
  eo.align = tools::Alignment::kPosYaw;
  return tools::evaluate(r.gt, r.est, eo).ate_m.rmse;
}

}  // namespace kestrel::test

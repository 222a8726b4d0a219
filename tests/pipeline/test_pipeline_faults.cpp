// Faults survived: each test writes a short simulated log with one fault in
// it, replays it through the real harness (reader, ReplaySource, rings,
// estimator stage, output stage) and checks that nothing crashed, that the
// fault was counted where the report says, that the output said so (quality /
// reset counter) where the camera was cut, and that the estimate was good
// again within a bound. Each prints a FAULT-TABLE row for docs/timing.md.
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "pipeline_fixture.hpp"
#include "test_scale.hpp"

namespace kestrel::pipeline_test {
namespace {

// Sanitizer-sized (test_scale.hpp): 8 s with the fault at 3 s still leaves
// the longest fault (2 s) its recovery and a second of log after it.
const double kDuration_s = test::scaled(10.0, 8.0);
const double kFault_s = test::scaled(4.0, 3.0);
constexpr double kRecoverWithin_s = 3.0;

std::string log_path(const std::string& name) {
  return test::temp_dir("pipeline_" + name) + "/" + name + ".klog";
}

double t_rel(int64_t t_ns, int64_t t0_ns) { return 1e-9 * static_cast<double>(t_ns - t0_ns); }

// Share of poses from `from_s` on that are tracking with a good local motion.
double good_share(const ReplayRun& r, double from_s, double bound_m = 0.03) {
  int n = 0, ok = 0;
  for (size_t i = 0; i < r.poses.size(); ++i) {
    if (rel_s(r, r.poses[i].t_ns) < from_s) continue;
    ++n;
    const double e = local_error_m(r, i, 0.5);
    ok += r.poses[i].quality == core::TrackingQuality::kTracking && std::isfinite(e) && e < bound_m;
  }
  return n > 0 ? static_cast<double>(ok) / n : 0.0;
}

void expect_recovered(const Recovery& rec) {
  EXPECT_TRUE(rec.recovered) << "the estimate is not good again after the fault";
  if (rec.recovered) {
    EXPECT_LE(rec.time_to_recover_s, kRecoverWithin_s);
  }
}

// A baseline without a fault: what "good" looks like on these logs, so a
// failure below is the fault's doing and not the log's.
TEST(PipelineFaults, BaselineIsGood) {
  const std::string path = log_path("baseline");
  tools::SimOptions o = small_sim(kDuration_s);
  o.out_path = path;
  tools::run_simulation(o);
  const ReplayRun r = replay(path);
  ASSERT_GT(static_cast<double>(r.poses.size()), 20.0 * kDuration_s);  // two thirds of the 30 Hz frames
  EXPECT_GT(good_share(r, 1.5), 0.95);
  for (const char* path : {"input.frames_missing", "input.frames_out_of_order", "input.frames_repeated",
                           "input.frames_no_depth", "input.imu_gaps"})
    EXPECT_EQ(r.report.counters.count(path), 0u) << path;
  EXPECT_EQ(r.report.estimator_counters.imu_rejects.non_finite +
                r.report.estimator_counters.imu_rejects.out_of_order,
            0u);
}

TEST(PipelineFaults, TenPercentOfFramesDropped) {
  const std::string path = log_path("frame_drop");
  tools::SimOptions o = small_sim(kDuration_s);
  o.out_path = path;
  o.frame_drop_rate = 0.10;
  const tools::SimSummary sim = tools::run_simulation(o);
  ASSERT_GT(sim.frames_dropped, 15u);
  const ReplayRun r = replay(path);
  // Each lost frame is a time gap the harness counts (a drop of the very
  // first frames cannot be seen).
  EXPECT_NEAR(static_cast<double>(r.report.counters.count("input.frames_missing")),
              static_cast<double>(sim.frames_dropped), 2.0);
  EXPECT_GT(good_share(r, 1.5), 0.9);
  Recovery rec;
  rec.recovered = true;
  rec.time_to_recover_s = 0;
  print_row("10 % of frames dropped",
            "input_faults.missing = " + std::to_string(r.report.counters.count("input.frames_missing")) +
                " (sim dropped " + std::to_string(sim.frames_dropped) + "); tracking throughout",
            rec);
}

// The counts live once, in the run's perf registry: the metrics JSON (its
// `counters` object and the older keys), the status line and the report read
// the same numbers.
TEST(PipelineFaults, CountsReachEveryReaderFromOneRegistry) {
  const std::string path = log_path("counters");
  tools::SimOptions o = small_sim(kDuration_s);
  o.out_path = path;
  o.frame_drop_rate = 0.10;
  tools::run_simulation(o);
  cli::ReplayOptions opt;
  opt.path = path;
  opt.pace = drivers::ReplayPace::kLockstep;
  opt.estimator = backend();
  opt.status_line = true;
  std::vector<std::string> lines;
  opt.on_status = [&lines](const cli::PipelineStatus&, const std::string& line) { lines.push_back(line); };
  const cli::ReplayReport r = cli::run_replay(opt);
  const rt::PerfValues& n = r.counters;
  const uint64_t missing = n.count("input.frames_missing");
  EXPECT_GT(missing, 5u);
  EXPECT_EQ(n.count("output.status_lines"), lines.size());
  ASSERT_GE(lines.size(), 3u);
  // The last line's camera count is the registry's at that second: some, at most the final figure.
  const std::size_t at = lines.back().find("cam miss ");
  ASSERT_NE(at, std::string::npos) << lines.back();
  const uint64_t shown = std::stoull(lines.back().substr(at + 9));
  EXPECT_GT(shown, 0u) << lines.back();
  EXPECT_LE(shown, missing) << lines.back();
  EXPECT_EQ(n.count("estimator.frames_in"), r.estimator_counters.frames_in);
  EXPECT_EQ(n.count("estimator.imu_in"), r.estimator_counters.imu_in);
  const rt::PerfValue* add_frame = n.find("estimator.add_frame");
  ASSERT_NE(add_frame, nullptr);
  EXPECT_EQ(add_frame->kind, rt::PerfKind::kElapsed);
  EXPECT_EQ(add_frame->count, r.estimator_counters.frames_in);
  // Counters of parts that did not run are not registered: no dense map here.
  EXPECT_EQ(n.find("dense.keyframes"), nullptr);
  if (r.has_map) {
    EXPECT_EQ(n.count("map.loop_closures"), r.map.loop_closures);
    EXPECT_EQ(n.count("map.relocalisations"), r.map.relocalisations);
  }

  const auto j = nlohmann::json::parse(cli::replay_metrics_json(r));
  ASSERT_TRUE(j.contains("counters")) << "the metrics JSON has no counters object";
  EXPECT_EQ(j["counters"].size(), n.all().size());
  for (const rt::PerfValue& v : n.all()) {
    ASSERT_TRUE(j["counters"].contains(v.name)) << v.name;
    const auto& c = j["counters"][v.name];
    EXPECT_EQ(v.kind == rt::PerfKind::kCount ? c.get<uint64_t>() : c["count"].get<uint64_t>(), v.count)
        << v.name;
  }
  EXPECT_EQ(j["input_faults"]["missing"].get<uint64_t>(), missing);
  EXPECT_EQ(j["drops"]["output_ring"].get<uint64_t>(), n.count("rings.output_drops"));
  EXPECT_EQ(j["imu_rate_poses"].get<uint64_t>(), n.count("output.imu_rate_poses"));
}

TEST(PipelineFaults, ImuGapOf300ms) {
  const std::string path = log_path("imu_gap");
  tools::SimOptions o = small_sim(kDuration_s);
  o.out_path = path;
  FaultSink sink(path);
  int64_t t0 = -1;
  int dropped = 0;
  sink.on_imu = [&](const ImuSample& s, drivers::KlogWriter& w) {
    if (t0 < 0) t0 = s.t_ns;
    const double t = t_rel(s.t_ns, t0);
    if (t >= kFault_s && t < kFault_s + 0.3) {
      ++dropped;
      return;
    }
    w.write_imu(s);
  };
  tools::run_simulation(o, sink);
  ASSERT_GT(dropped, 100);
  const ReplayRun r = replay(path);
  EXPECT_EQ(r.report.counters.count("input.imu_gaps"), 1u);
  const Recovery rec = measure_recovery(r, kFault_s, kFault_s + 0.3);
  expect_recovered(rec);
  print_row("300 ms IMU gap",
            "input_faults.imu_gaps = " + std::to_string(r.report.counters.count("input.imu_gaps")) +
                " (estimator imu_rejects.gaps = " +
                std::to_string(r.report.estimator_counters.imu_rejects.gaps) + ")",
            rec);
}

TEST(PipelineFaults, OutOfOrderAndDuplicatedTimestamps) {
  const std::string path = log_path("out_of_order");
  tools::SimOptions o = small_sim(kDuration_s);
  o.out_path = path;
  FaultSink sink(path);
  int64_t t0 = -1;
  int imu_dup = 0, imu_swapped = 0, n = 0;
  bool holding = false;
  ImuSample held;
  sink.on_imu = [&](const ImuSample& s, drivers::KlogWriter& w) {
    if (t0 < 0) t0 = s.t_ns;
    const double t = t_rel(s.t_ns, t0);
    ++n;
    if (holding) {  // the swapped pair: the later sample first
      w.write_imu(s);
      w.write_imu(held);
      holding = false;
      ++imu_swapped;
      return;
    }
    if (t >= kFault_s && t < kFault_s + 0.5 && n % 20 == 0) {
      held = s;
      holding = true;
      return;
    }
    w.write_imu(s);
    if (t >= kFault_s + 0.5 && t < kFault_s + 1.0 && n % 20 == 0) {
      w.write_imu(s);
      ++imu_dup;
    }
  };
  // Frames: one written twice (same stamp), one stale copy stamped two periods back.
  std::map<drivers::RecordType, std::vector<uint8_t>> last;
  std::map<drivers::RecordType, ImageView> last_view;
  int64_t last_t = -1;
  int input_faults = 0;
  sink.on_image = [&](drivers::RecordType type, int64_t t_ns, uint32_t seq, const ImageView& v,
                      drivers::KlogWriter& w) {
    w.write_image(type, t_ns, t_ns, seq, 0, v);
    const double t = t0 < 0 ? 0 : t_rel(t_ns, t0);
    const bool dup = t >= kFault_s + 1.0 && last_t >= 0 && t_rel(last_t, t0) < kFault_s + 1.0;
    const bool stale = t >= kFault_s + 1.5 && last_t >= 0 && t_rel(last_t, t0) < kFault_s + 1.5;
    if (type == drivers::RecordType::kDepth) {
      if (dup) {
        w.write_image(drivers::RecordType::kRgb, t_ns, t_ns, seq, 0, last_view[drivers::RecordType::kRgb]);
        w.write_image(drivers::RecordType::kDepth, t_ns, t_ns, seq, 0, v);
        ++input_faults;
      }
      if (stale) {
        const int64_t old = t_ns - 2 * 33'333'333;
        w.write_image(drivers::RecordType::kRgb, old, old, seq, 0, last_view[drivers::RecordType::kRgb]);
        w.write_image(drivers::RecordType::kDepth, old, old, seq, 0, v);
        ++input_faults;
      }
      last_t = t_ns;
    } else {
      last[type].assign(v.data, v.data + static_cast<size_t>(v.height) * v.stride_bytes);
      ImageView c = v;
      c.data = last[type].data();
      last_view[type] = c;
    }
  };
  tools::run_simulation(o, sink);
  ASSERT_GT(imu_swapped, 5);
  ASSERT_GT(imu_dup, 5);
  ASSERT_EQ(input_faults, 2);
  const ReplayRun r = replay(path);
  EXPECT_EQ(r.report.estimator_counters.imu_rejects.out_of_order,
            static_cast<uint64_t>(imu_swapped + imu_dup));
  EXPECT_EQ(r.report.counters.count("input.frames_out_of_order"), 2u);
  const Recovery rec = measure_recovery(r, kFault_s, kFault_s + 1.6);
  expect_recovered(rec);
  EXPECT_GT(good_share(r, 1.5), 0.9) << "out-of-order input must not derail the estimate";
  print_row("out-of-order and duplicated timestamps",
            "imu_out_of_order = " + std::to_string(r.report.estimator_counters.imu_rejects.out_of_order) +
                " (injected " + std::to_string(imu_swapped + imu_dup) + "), input_faults.out_of_order = " +
                std::to_string(r.report.counters.count("input.frames_out_of_order")) + " (withheld)",
            rec);
}

TEST(PipelineFaults, NanAndSaturatedImuSamples) {
  const std::string path = log_path("imu_nan");
  tools::SimOptions o = small_sim(kDuration_s);
  o.out_path = path;
  FaultSink sink(path);
  int64_t t0 = -1;
  int nan = 0, sat = 0, n = 0;
  sink.on_imu = [&](const ImuSample& in, drivers::KlogWriter& w) {
    if (t0 < 0) t0 = in.t_ns;
    ImuSample s = in;
    const double t = t_rel(s.t_ns, t0);
    ++n;
    if (t >= kFault_s && t < kFault_s + 0.5) {
      if (n % 10 == 0) {  // a driver bug: NaN without the flag
        s.gyro_rps[0] = std::nan("");
        s.acc_mps2[2] = std::nan("");
        ++nan;
      } else if (n % 10 == 5) {  // a hard knock: the chip clips and the driver flags it
        s.gyro_rps[1] = 2000.0 * M_PI / 180.0;
        s.acc_mps2[0] = 16 * 9.81;
        s.flags |= kImuGyroSaturated | kImuAccSaturated;
        ++sat;
      }
    }
    w.write_imu(s);
  };
  tools::run_simulation(o, sink);
  ASSERT_GT(nan, 10);
  const ReplayRun r = replay(path);
  const auto& c = r.report.estimator_counters.imu_rejects;
  EXPECT_EQ(c.non_finite, static_cast<uint64_t>(nan));
  EXPECT_EQ(c.saturated, static_cast<uint64_t>(sat));
  for (const auto& p : r.poses) {
    ASSERT_TRUE(p.p_WB().allFinite() && p.q_WB().coeffs().allFinite()) << "a NaN reached the output";
  }
  const Recovery rec = measure_recovery(r, kFault_s, kFault_s + 0.5);
  expect_recovered(rec);
  print_row("NaN and saturated IMU samples",
            "imu_non_finite = " + std::to_string(c.non_finite) +
                ", imu_saturated = " + std::to_string(c.saturated) + " (rejected, integrated across)",
            rec);
}

TEST(PipelineFaults, FrozenCamera) {
  const std::string path = log_path("frozen");
  tools::SimOptions o = small_sim(kDuration_s);
  o.out_path = path;
  FaultSink sink(path);
  int64_t t0 = -1;
  std::map<drivers::RecordType, std::vector<uint8_t>> frozen;
  int frozen_frames = 0;
  sink.on_imu = [&](const ImuSample& s, drivers::KlogWriter& w) {
    if (t0 < 0) t0 = s.t_ns;
    w.write_imu(s);
  };
  sink.on_image = [&](drivers::RecordType type, int64_t t_ns, uint32_t seq, const ImageView& v,
                      drivers::KlogWriter& w) {
    const double t = t0 < 0 ? 0 : t_rel(t_ns, t0);
    ImageView out = v;
    const size_t bytes = static_cast<size_t>(v.height) * v.stride_bytes;
    if (t < kFault_s) {
      frozen[type].assign(v.data, v.data + bytes);  // the last good exposure
    } else if (t < kFault_s + 1.0) {
      out.data = frozen[type].data();
      if (type == drivers::RecordType::kRgb) ++frozen_frames;
    }
    w.write_image(type, t_ns, t_ns, seq, 0, out);
  };
  tools::run_simulation(o, sink);
  ASSERT_GT(frozen_frames, 25);
  const ReplayRun r = replay(path);
  EXPECT_EQ(r.report.counters.count("input.frames_repeated"), static_cast<uint64_t>(frozen_frames));
  const Recovery rec = measure_recovery(r, kFault_s, kFault_s + 1.0);
  EXPECT_TRUE(rec.said_so) << "the output kept claiming tracking on a frozen camera";
  expect_recovered(rec);
  print_row("frozen camera (1 s of repeated frames)",
            "input_faults.repeated = " + std::to_string(r.report.counters.count("input.frames_repeated")) +
                " (withheld); quality imu-only while frozen",
            rec);
}

TEST(PipelineFaults, DepthInvalidForTwoSeconds) {
  const std::string path = log_path("no_depth");
  tools::SimOptions o = small_sim(kDuration_s);
  o.out_path = path;
  FaultSink sink(path);
  int64_t t0 = -1;
  int no_depth = 0;
  std::vector<uint8_t> zeros;
  sink.on_imu = [&](const ImuSample& s, drivers::KlogWriter& w) {
    if (t0 < 0) t0 = s.t_ns;
    w.write_imu(s);
  };
  sink.on_image = [&](drivers::RecordType type, int64_t t_ns, uint32_t seq, const ImageView& v,
                      drivers::KlogWriter& w) {
    const double t = t0 < 0 ? 0 : t_rel(t_ns, t0);
    ImageView out = v;
    if (type == drivers::RecordType::kDepth && t >= kFault_s && t < kFault_s + 2.0) {
      zeros.assign(static_cast<size_t>(v.height) * v.stride_bytes, 0);
      out.data = zeros.data();
      ++no_depth;
    }
    w.write_image(type, t_ns, t_ns, seq, 0, out);
  };
  tools::run_simulation(o, sink);
  ASSERT_GT(no_depth, 55);
  const ReplayRun r = replay(path);
  EXPECT_EQ(r.report.counters.count("input.frames_no_depth"), static_cast<uint64_t>(no_depth));
  const Recovery rec = measure_recovery(r, kFault_s, kFault_s + 2.0);
  expect_recovered(rec);
  print_row("depth all invalid for 2 s",
            "input_faults.no_depth = " + std::to_string(r.report.counters.count("input.frames_no_depth")) +
                "; resets in fault = " + std::to_string(rec.resets_in_fault),
            rec);
}

TEST(PipelineFaults, CorruptLogChunk) {
  const std::string path = log_path("corrupt");
  tools::SimOptions o = small_sim(kDuration_s);
  o.out_path = path;
  tools::run_simulation(o);
  const auto size = std::filesystem::file_size(path);
  // 300 kB of garbage from 45 % of the file: about three frames and the IMU
  // records between them, sync markers and CRCs included.
  const uint64_t a = size * 45 / 100, len = 300'000;
  {
    std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary);
    f.seekp(static_cast<std::streamoff>(a));
    std::vector<char> junk(len);
    for (size_t i = 0; i < len; ++i) junk[i] = static_cast<char>((i * 2654435761u) >> 13);
    f.write(junk.data(), static_cast<std::streamsize>(len));
  }
  const ReplayRun r = replay(path);
  ASSERT_FALSE(r.report.problems.empty()) << "the damage was not reported";
  const double d = r.report.log_duration_s;
  const double fa = d * static_cast<double>(a) / static_cast<double>(size) - 0.3;
  const double fb = d * static_cast<double>(a + len) / static_cast<double>(size) + 0.3;
  EXPECT_GE(r.report.counters.count("input.frames_missing"), 1u)
      << "frames lost in the chunk are not counted";
  const Recovery rec = measure_recovery(r, fa, fb);
  expect_recovered(rec);
  print_row(
      "corrupt log chunk (300 kB)",
      "log problems = " + std::to_string(r.report.problems.size()) + " (first: " + r.report.problems[0].kind +
          "), input_faults.missing = " + std::to_string(r.report.counters.count("input.frames_missing")) +
          ", imu_gaps = " + std::to_string(r.report.estimator_counters.imu_rejects.gaps),
      rec);
}

TEST(PipelineFaults, FastRotationBurstBeyondTheTracker) {
  // Hover, then one full turn about the vertical axis in 0.5 s (peak
  // 1440 deg/s, ~48 deg between frames: no keyframe survives it), then hover.
  const std::string dir = test::temp_dir("pipeline_spin");
  const std::string gt_path = dir + "/spin_gt.txt";
  {
    std::ofstream f(gt_path);
    f << "# t x y z qx qy qz qw\n";
    for (int k = 0; k <= static_cast<int>(kDuration_s * 200); ++k) {
      const double t = k / 200.0;
      const double x = 0.04 * std::sin(0.3 * t), y = 0.03 * std::sin(0.2 * t + 1.0),
                   z = 1.2 + 0.02 * std::sin(0.5 * t);
      double yaw = 0.05 * std::sin(0.4 * t);
      const double ts = t - kFault_s;
      if (ts > 0)
        yaw += ts >= 0.5 ? 2 * M_PI : 2 * M_PI * (ts / 0.5 - std::sin(2 * M_PI * ts / 0.5) / (2 * M_PI));
      const Eigen::Quaterniond q(Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()));
      char line[256];
      std::snprintf(line, sizeof line, "%.4f %.6f %.6f %.6f %.9f %.9f %.9f %.9f\n", 100.0 + t, x, y, z, q.x(),
                    q.y(), q.z(), q.w());
      f << line;
    }
  }
  const std::string path = dir + "/spin.klog";
  tools::SimOptions o = small_sim(kDuration_s);
  o.scenario.clear();
  o.trajectory_path = gt_path;
  o.out_path = path;
  tools::run_simulation(o);
  const ReplayRun r = replay(path);
  const Recovery rec = measure_recovery(r, kFault_s, kFault_s + 0.5);
  EXPECT_TRUE(rec.said_so) << "the tracker lost the scene but the output kept claiming tracking";
  expect_recovered(rec);
  print_row("fast rotation burst (360 deg in 0.5 s)",
            "resets in fault = " + std::to_string(rec.resets_in_fault) +
                ", imu_saturated = " + std::to_string(r.report.estimator_counters.imu_rejects.saturated),
            rec);
}

}  // namespace
}  // namespace kestrel::pipeline_test

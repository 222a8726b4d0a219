// `kestrel bench`: the benchmark suite as one table (and --json).
//
// Each case is simulated (built-in scenarios, and hybrid logs built from the
// real IMU and ground truth of every EuRoC sequence in ../shared/data), then
// replayed in a forked child so its peak RSS and allocations are its own, then
// scored against ground truth. Figures that do not exist yet are null.
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <limits>
#include <map>
#include <sstream>
#include <utility>

#include "kestrel/commands.hpp"
#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/tools/config_file.hpp"
#include "kestrel/tools/cpu_budget.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"
#include "kestrel/tools/report_json.hpp"
#include "kestrel/tools/simulator.hpp"
#include "kestrel/tools/trajectory_eval.hpp"

namespace fs = std::filesystem;

namespace kestrel::cli {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

struct BenchCase {
  std::string name;
  std::string kind;         // "scenario", "hybrid", "real-images", "real-rgbd", "real-synth-imu"
  std::string scenario;     // scenario name
  std::string gt_path;      // hybrid: EuRoC gt_body_20hz.csv; real-images: its GT
  std::string imu_path;     // hybrid: EuRoC imu0.csv
  std::string log_path;     // real-images: the EuRoC ASL folder; real-rgbd: the recording
  std::string images_path;  // real-synth-imu: the recording its log is made from (`kestrel sim --images`)
  std::vector<std::string> backends;  // non-empty: these backends, whatever --estimator says
  std::string skipped;                // non-empty: why it cannot run
  double room_m = 0.0;  // hybrid: rendered hall size (SimOptions::room_m); 0: a room around the flight
  bool stereo = false;  // hybrid: rendered as stereo pairs instead of RGB-D (`kestrel sim --stereo`)
};

// The figures of one row; NaN where a figure does not exist (yet).
struct BenchRow {
  std::string name;
  std::string estimator;
  std::string status = "ok";
  double duration_s = kNaN;
  double ate_rmse_m = kNaN;      // posyaw alignment (the DoF VIO cannot observe)
  double ate_se3_rmse_m = kNaN;  // se3 alignment, as the peers' evaluations: also forgives a ground truth
                                 // whose world frame is tilted against gravity (docs/bench.md)
  double rpe_trans_m_per_s = kNaN;
  double tracking_ms_p50 = kNaN, tracking_ms_p99 = kNaN;
  double optimizer_ms_p50 = kNaN, optimizer_ms_p99 = kNaN;
  double imu_to_output_ms_p99 = kNaN;
  double tracking_ms_max = kNaN, optimizer_ms_max = kNaN;
  double imu_to_output_ms_p50 = kNaN, imu_to_output_ms_max = kNaN;
  double allocs_per_frame = kNaN;
  double realtime_factor = kNaN;
  double peak_rss_mb = kNaN;
  double pose_share = kNaN;   // frames that got a pose / frames
  double divergences = kNaN;  // times the backend said it lost the truth and re-initialised
  double coast_s = kNaN;      // IMU-only time after visual fixes
  double cpu_s_per_s = kNaN;  // the estimator's work: CPU seconds per second of flight (waiting not counted)
  double map_cpu_s_per_s = kNaN;  // the mapping and loop threads' CPU seconds per second of flight
  std::string fail;               // why the row fails (empty: it does not); docs/bench.md "FAIL"
  double sim_s = kNaN;
  double replay_wall_s = kNaN;
  double cpu_per_s = kNaN;  // process CPU seconds per second of flight (all threads)
  // The map (backends with one): the trajectory in the map frame, the map's
  // counters, and the mapping / loop threads' time per keyframe.
  double map_ate_se3_rmse_m = kNaN;
  double map_final_ate_se3_rmse_m = kNaN;  // through the map's keyframes as they ended the flight
  double loop_closures = kNaN, relocalisations = kNaN, keyframes_in_map = kNaN, map_points = kNaN;
  // The loops against the ground truth (loop_truth.hpp): revisit keyframes,
  // shares of them the loop closer recognised and the map found either way,
  // closed loops whose correction disagrees with the truth.
  double loop_revisits = kNaN, loop_recall = kNaN, map_recall = kNaN, false_loops = kNaN;
  double map_correction_m = kNaN;
  double mapping_ms_p50 = kNaN, mapping_ms_p99 = kNaN, loop_ms_p50 = kNaN, loop_ms_p99 = kNaN;
};

std::vector<BenchCase> discover_cases(const std::string& data_dir) {
  std::vector<BenchCase> cases;
  for (const char* s : {"hover", "figure8", "aggressive", "static", "hard"}) {
    BenchCase c;
    c.name = s;
    c.kind = "scenario";
    c.scenario = s;
    cases.push_back(c);
  }
  const fs::path euroc = fs::path(data_dir) / "euroc";
  const char* sequences[] = {"MH_01_easy",      "MH_03_medium", "V1_01_easy",  "V1_02_medium",
                             "V1_03_difficult", "V2_01_easy",   "V2_02_medium"};
  for (const char* seq : sequences) {
    BenchCase c;
    c.name = std::string("hybrid-") + seq;
    c.kind = "hybrid";
    c.gt_path = (euroc / seq / "gt_body_20hz.csv").string();
    c.imu_path = (euroc / seq / "imu0.csv").string();
    if (!fs::exists(c.gt_path) || !fs::exists(c.imu_path)) c.skipped = "not found: " + (euroc / seq).string();
    cases.push_back(c);
  }
  // Every hybrid flight again as a stereo rig (issue 48, docs/stereo.md): the
  // same motion, room and IMU, a right image instead of a depth image.
  for (const char* seq : sequences) {
    BenchCase c;
    c.name = std::string("stereo-") + seq;
    c.kind = "hybrid";
    c.stereo = true;
    c.gt_path = (euroc / seq / "gt_body_20hz.csv").string();
    c.imu_path = (euroc / seq / "imu0.csv").string();
    if (!fs::exists(c.gt_path) || !fs::exists(c.imu_path)) c.skipped = "not found: " + (euroc / seq).string();
    cases.push_back(c);
  }
  // The machine-hall flights again, in a rendered hall as large as the real
  // one (walls up to 20 m away, far beyond the 6 m depth range), where the
  // hybrid cases above render a room around the flight.
  for (const char* seq : {"MH_01_easy", "MH_03_medium"}) {
    BenchCase c;
    c.name = std::string("hall-") + seq;
    c.kind = "hybrid";
    c.room_m = 20.0;
    c.gt_path = (euroc / seq / "gt_body_20hz.csv").string();
    c.imu_path = (euroc / seq / "imu0.csv").string();
    if (!fs::exists(c.gt_path) || !fs::exists(c.imu_path)) c.skipped = "not found: " + (euroc / seq).string();
    cases.push_back(c);
  }
  {
    BenchCase c;
    c.name = "real-V1_01_first95";
    c.kind = "real-images";
    c.log_path = (euroc / "V1_01_easy_first95").string();
    c.gt_path = (euroc / "V1_01_easy" / "gt_body_20hz.csv").string();
    if (!fs::exists(c.log_path) || !fs::exists(c.gt_path)) c.skipped = "not found: " + c.log_path;
    cases.push_back(c);
  }
  // Real Kinect v1 images (7-Scenes, 500 frames, hand-held, no IMU): the rgbd
  // backend on them as they are, and the visual-inertial backends with an IMU
  // synthesised along their ground truth (docs/real-imagery.md).
  const fs::path seven = fs::path(data_dir) / "real-rgbd" / "7scenes_first500";
  {
    BenchCase c;
    c.name = "real-7scenes-rgbd";
    c.kind = "real-rgbd";
    c.log_path = c.gt_path = seven.string();
    c.backends = {"rgbd"};
    if (!fs::exists(seven)) c.skipped = "not found: " + seven.string();
    cases.push_back(c);
  }
  {
    BenchCase c;
    c.name = "real-7scenes-synth-imu";
    c.kind = "real-synth-imu";
    c.images_path = seven.string();
    if (!fs::exists(seven)) c.skipped = "not found: " + seven.string();
    cases.push_back(c);
  }
  return cases;
}

// Runs replay + eval in a child process and returns its figures as text
// lines "key value", so the child's peak RSS is the case's own.
std::map<std::string, double> replay_in_child(const std::string& log, const std::string& gt,
                                              drivers::ReplayPace pace, const core::EstimatorConfig& config,
                                              const std::string& traj_out, std::string& estimator,
                                              std::string& error, std::string* gt_note = nullptr) {
  int fds[2];
  if (pipe(fds) != 0) throw std::runtime_error("pipe failed");
  std::fflush(nullptr);
  const pid_t pid = fork();
  if (pid < 0) throw std::runtime_error("fork failed");
  if (pid == 0) {
    close(fds[0]);
    std::ostringstream o;
    o.precision(10);
    try {
      ReplayOptions opt;
      opt.path = log;
      opt.pace = pace;
      opt.estimator = config.backend;
      opt.config = config;
      opt.loop_log = true;
      ReplayReport r = run_replay(opt);
      if (!traj_out.empty()) tools::write_tum(traj_out, r.trajectory);
      o << "estimator " << r.estimator << "\n";
      auto ms = [](int64_t ns) { return 1e-6 * static_cast<double>(ns); };
      if (r.tracking.count() > 0) {
        o << "tracking_ms_p50 " << ms(r.tracking.p50()) << "\n";
        o << "tracking_ms_p99 " << ms(r.tracking.p99()) << "\n";
        o << "tracking_ms_max " << ms(r.tracking.max()) << "\n";
      }
      if (r.optimizer.count() > 0) {
        o << "optimizer_ms_p50 " << ms(r.optimizer.p50()) << "\n";
        o << "optimizer_ms_p99 " << ms(r.optimizer.p99()) << "\n";
        o << "optimizer_ms_max " << ms(r.optimizer.max()) << "\n";
      }
      if (r.imu_to_output.count() > 0) {
        o << "imu_to_output_ms_p50 " << ms(r.imu_to_output.p50()) << "\n";
        o << "imu_to_output_ms_p99 " << ms(r.imu_to_output.p99()) << "\n";
        o << "imu_to_output_ms_max " << ms(r.imu_to_output.max()) << "\n";
      }
      if (r.alloc_counting && r.steady_frames > 0) {
        o << "allocs_per_frame "
          << static_cast<double>(r.steady_allocs) / static_cast<double>(r.steady_frames) << "\n";
      }
      o << "realtime_factor " << r.realtime_factor << "\n";
      o << "divergences " << r.estimator_counters.divergence.divergences << "\n";
      o << "coast_s " << 1e-9 * static_cast<double>(r.estimator_counters.divergence.coast_ns) << "\n";
      if (r.log_duration_s > 0 && r.estimator_cpu_s > 0)
        o << "cpu_s_per_s " << r.estimator_cpu_s / r.log_duration_s << "\n";
      if (r.log_duration_s > 0) o << "cpu_per_s " << r.cpu_s / r.log_duration_s << "\n";
      if (r.has_map) {
        o << "loop_closures " << r.map.loop_closures << "\nrelocalisations " << r.map.relocalisations << "\n";
        o << "keyframes_in_map " << r.map.keyframes << "\nmap_points " << r.map.points << "\n";
        o << "map_correction_m " << r.map.T_map_odom().translation().norm() << "\n";
        if (r.log_duration_s > 0)
          o << "map_cpu_s_per_s " << (r.mapping_cpu_s + r.loop_cpu_s) / r.log_duration_s << "\n";
        if (r.mapping.count() > 0)
          o << "mapping_ms_p50 " << ms(r.mapping.p50()) << "\nmapping_ms_p99 " << ms(r.mapping.p99()) << "\n";
        if (r.loop.count() > 0)
          o << "loop_ms_p50 " << ms(r.loop.p50()) << "\nloop_ms_p99 " << ms(r.loop.p99()) << "\n";
        const auto src = drivers::open_log(log, drivers::LogOpenOptions{});
        const LoopTruth t = evaluate_loops(*src, r.loop_log);
        if (t.available) {
          o << "loop_revisits " << t.revisit_keyframes << "\nfalse_loops " << t.closed_false << "\n";
          if (t.revisit_keyframes > 0)
            o << "loop_recall " << t.loop_recall << "\nmap_recall " << t.map_recall << "\n";
        }
      }
      o << "peak_rss_mb " << r.peak_rss_mb << "\n";
      o << "duration_s " << r.log_duration_s << "\n";
      o << "replay_wall_s " << r.wall_s << "\n";
      const double frames = static_cast<double>(r.replay.frames_pushed);
      if (frames > 0)
        o << "pose_share " << std::min(1.0, static_cast<double>(r.trajectory.size()) / frames) << "\n";
      std::vector<std::string> warnings;
      tools::Trajectory g;
      if (gt_note != nullptr) {
        // --dataset-root: a sequence without ground truth is still run and its trajectory written.
        try {
          g = tools::load_trajectory(gt, &warnings);
        } catch (const std::exception& ex) {
          o << "gt_note " << ex.what() << "\n";
        }
      } else {
        g = tools::load_trajectory(gt, &warnings);
      }
      if (!g.empty()) {
        tools::EvalOptions eo;
        // A backend whose W is not levelled (rgbd) has a tilt no yaw alignment
        // takes out: it is scored after SE(3) in both columns.
        eo.align = r.world_levelled ? tools::Alignment::kPosYaw : tools::Alignment::kSe3;
        tools::EvalResult e = tools::evaluate(g, r.trajectory, eo);
        o << "ate_rmse_m " << e.ate_m.rmse << "\n";
        eo.align = tools::Alignment::kSe3;
        o << "ate_se3_rmse_m " << tools::evaluate(g, r.trajectory, eo).ate_m.rmse << "\n";
        if (r.has_map && !r.map_trajectory.empty())
          o << "map_ate_se3_rmse_m " << tools::evaluate(g, r.map_trajectory, eo).ate_m.rmse << "\n";
        if (r.has_map && !r.map_final_trajectory.empty()) {
          o << "map_final_ate_se3_rmse_m " << tools::evaluate(g, r.map_final_trajectory, eo).ate_m.rmse
            << "\n";
        }
        o << "rpe_trans_m_per_s " << e.rpe_trans_m_per_s << "\n";
        eo.align = tools::Alignment::kSim3;
        const tools::EvalResult sim3 = tools::evaluate(g, r.trajectory, eo);
        o << "ate_sim3_rmse_m " << sim3.ate_m.rmse << "\nsim3_scale " << sim3.T_align.scale << "\n";
      }
      o << "frames " << frames << "\nposes " << r.trajectory.size() << "\n";
    } catch (const std::exception& ex) {
      o << "error " << ex.what() << "\n";
    }
    const std::string s = o.str();
    ssize_t off = 0;
    while (off < static_cast<ssize_t>(s.size())) {
      const ssize_t n = write(fds[1], s.data() + off, s.size() - static_cast<size_t>(off));
      if (n <= 0) break;
      off += n;
    }
    close(fds[1]);
    _exit(0);
  }
  close(fds[1]);
  std::string text;
  char buf[4096];
  for (;;) {
    const ssize_t n = read(fds[0], buf, sizeof buf);
    if (n <= 0) break;
    text.append(buf, static_cast<size_t>(n));
  }
  close(fds[0]);
  int status = 0;
  waitpid(pid, &status, 0);
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0)
    error = "replay child crashed (status " + std::to_string(status) + ")";
  std::map<std::string, double> out;
  std::istringstream in(text);
  std::string line;
  while (std::getline(in, line)) {
    const auto sp = line.find(' ');
    if (sp == std::string::npos) continue;
    const std::string k = line.substr(0, sp), v = line.substr(sp + 1);
    if (k == "estimator") {
      estimator = v;
    } else if (k == "gt_note") {
      if (gt_note != nullptr) *gt_note = v;
    } else if (k == "error") {
      error = v;
    } else {
      out[k] = std::strtod(v.c_str(), nullptr);
    }
  }
  return out;
}

double get(const std::map<std::string, double>& m, const char* k) {
  auto it = m.find(k);
  return it == m.end() ? kNaN : it->second;
}

std::string fmt(double v, const char* f) {
  if (!std::isfinite(v)) return "-";
  char buf[32];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

void print_table(const std::vector<BenchRow>& rows) {
  std::printf("%-26s %-20s %9s %9s %9s %9s %9s %8s %8s %8s %8s %9s %8s %8s %8s %7s %5s %7s %6s\n", "case",
              "estimator", "ate_m", "ate_se3_m", "map_se3_m", "final_m", "rpe_m/s", "trk_p50", "trk_p99",
              "opt_p50", "opt_p99", "imu_p99", "alloc/f", "rt_x", "rss_mb", "poses", "div", "coast_s",
              "cpu/s");
  for (const auto& r : rows) {
    if (r.status != "ok") {
      std::printf("%-26s %s\n", r.name.c_str(), r.status.c_str());
      continue;
    }
    std::printf("%-26s %-20s %9s %9s %9s %9s %9s %8s %8s %8s %8s %9s %8s %8s %8s %7s %5s %7s %6s%s\n",
                r.name.c_str(), r.estimator.c_str(), fmt(r.ate_rmse_m, "%.4f").c_str(),
                fmt(r.ate_se3_rmse_m, "%.4f").c_str(), fmt(r.map_ate_se3_rmse_m, "%.4f").c_str(),
                fmt(r.map_final_ate_se3_rmse_m, "%.4f").c_str(), fmt(r.rpe_trans_m_per_s, "%.4f").c_str(),
                fmt(r.tracking_ms_p50, "%.3f").c_str(), fmt(r.tracking_ms_p99, "%.3f").c_str(),
                fmt(r.optimizer_ms_p50, "%.2f").c_str(), fmt(r.optimizer_ms_p99, "%.2f").c_str(),
                fmt(r.imu_to_output_ms_p99, "%.3f").c_str(), fmt(r.allocs_per_frame, "%.2f").c_str(),
                fmt(r.realtime_factor, "%.1f").c_str(), fmt(r.peak_rss_mb, "%.0f").c_str(),
                fmt(100.0 * r.pose_share, "%.1f%%").c_str(), fmt(r.divergences, "%.0f").c_str(),
                fmt(r.coast_s, "%.2f").c_str(), fmt(r.cpu_s_per_s, "%.3f").c_str(),
                r.fail.empty() ? "" : ("  FAIL: " + r.fail).c_str());
  }
}

// The bench's floor (issue 17): a backend that ends a metre off or leaves
// frames without a pose has failed the case, whatever its other figures.
std::string fail_reasons(const BenchRow& r) {
  std::string f;
  auto add = [&f](const std::string& s) { f += (f.empty() ? "" : ", ") + s; };
  if (!std::isfinite(r.ate_rmse_m) || r.ate_rmse_m > 1.0 ||
      (std::isfinite(r.ate_se3_rmse_m) && r.ate_se3_rmse_m > 1.0))
    add("ATE over 1 m");
  if (!std::isfinite(r.pose_share) || r.pose_share < 0.99) add("pose share under 99 %");
  return f;
}

// Per stage p50 / p99 / max [ms]: the timing table of the pipeline issue.
void print_timing_table(const std::vector<BenchRow>& rows) {
  std::printf("\ntiming [ms] (p50 / p99 / max)\n%-26s %-20s %-26s %-26s %-26s %6s\n", "case", "estimator",
              "tracking", "optimizer", "imu_to_output", "rt_x");
  auto three = [](double a, double b, double c) {
    return fmt(a, "%.3f") + " / " + fmt(b, "%.3f") + " / " + fmt(c, "%.3f");
  };
  for (const auto& r : rows) {
    if (r.status != "ok") continue;
    std::printf("%-26s %-20s %-26s %-26s %-26s %6s\n", r.name.c_str(), r.estimator.c_str(),
                three(r.tracking_ms_p50, r.tracking_ms_p99, r.tracking_ms_max).c_str(),
                three(r.optimizer_ms_p50, r.optimizer_ms_p99, r.optimizer_ms_max).c_str(),
                three(r.imu_to_output_ms_p50, r.imu_to_output_ms_p99, r.imu_to_output_ms_max).c_str(),
                fmt(r.realtime_factor, "%.1f").c_str());
  }
}

// The map's figures: per keyframe cost of its threads and what it did.
void print_map_table(const std::vector<BenchRow>& rows) {
  bool any = false;
  for (const auto& r : rows) any |= r.status == "ok" && std::isfinite(r.keyframes_in_map);
  if (!any) return;
  std::printf(
      "\nmap (per keyframe [ms] p50 / p99; cpu/s: the map's threads, then the whole process)\n"
      "%-26s %-20s %-17s %-17s %6s %8s %6s %6s %8s %7s %7s %8s %6s %6s %6s\n",
      "case", "estimator", "mapping", "loop", "kfs", "points", "loops", "relocs", "corr_m", "map", "proc",
      "revisits", "recall", "found", "false");
  for (const auto& r : rows) {
    if (r.status != "ok" || !std::isfinite(r.keyframes_in_map)) continue;
    std::printf("%-26s %-20s %-17s %-17s %6s %8s %6s %6s %8s %7s %7s %8s %6s %6s %6s\n", r.name.c_str(),
                r.estimator.c_str(),
                (fmt(r.mapping_ms_p50, "%.1f") + " / " + fmt(r.mapping_ms_p99, "%.1f")).c_str(),
                (fmt(r.loop_ms_p50, "%.1f") + " / " + fmt(r.loop_ms_p99, "%.1f")).c_str(),
                fmt(r.keyframes_in_map, "%.0f").c_str(), fmt(r.map_points, "%.0f").c_str(),
                fmt(r.loop_closures, "%.0f").c_str(), fmt(r.relocalisations, "%.0f").c_str(),
                fmt(r.map_correction_m, "%.3f").c_str(), fmt(r.map_cpu_s_per_s, "%.2f").c_str(),
                fmt(r.cpu_per_s, "%.2f").c_str(), fmt(r.loop_revisits, "%.0f").c_str(),
                fmt(r.loop_recall, "%.2f").c_str(), fmt(r.map_recall, "%.2f").c_str(),
                fmt(r.false_loops, "%.0f").c_str());
  }
}

std::string rows_json(const std::vector<BenchRow>& rows, double duration_s) {
  using tools::json_figure;
  tools::Json cases = tools::Json::array();
  for (const auto& r : rows) {
    tools::Json c = tools::Json::object();
    c["name"] = r.name;
    c["status"] = r.status;
    c["estimator"] = r.estimator;
    const std::pair<const char*, double> figures[] = {
        {"duration_s", r.duration_s},
        {"ate_rmse_m", r.ate_rmse_m},
        {"ate_se3_rmse_m", r.ate_se3_rmse_m},
        {"rpe_trans_m_per_s", r.rpe_trans_m_per_s},
        {"tracking_ms_p50", r.tracking_ms_p50},
        {"tracking_ms_p99", r.tracking_ms_p99},
        {"tracking_ms_max", r.tracking_ms_max},
        {"optimizer_ms_p50", r.optimizer_ms_p50},
        {"optimizer_ms_p99", r.optimizer_ms_p99},
        {"optimizer_ms_max", r.optimizer_ms_max},
        {"imu_to_output_ms_p50", r.imu_to_output_ms_p50},
        {"imu_to_output_ms_p99", r.imu_to_output_ms_p99},
        {"imu_to_output_ms_max", r.imu_to_output_ms_max},
        {"allocs_per_frame", r.allocs_per_frame},
        {"realtime_factor", r.realtime_factor},
        {"peak_rss_mb", r.peak_rss_mb},
        {"pose_share", r.pose_share},
        {"divergences", r.divergences},
        {"coast_s", r.coast_s},
        {"cpu_s_per_s", r.cpu_s_per_s},
        {"sim_s", r.sim_s},
        {"replay_wall_s", r.replay_wall_s},
        {"cpu_per_s", r.cpu_per_s},
        {"map_cpu_s_per_s", r.map_cpu_s_per_s},
        {"map_ate_se3_rmse_m", r.map_ate_se3_rmse_m},
        {"map_final_ate_se3_rmse_m", r.map_final_ate_se3_rmse_m},
        {"loop_closures", r.loop_closures},
        {"relocalisations", r.relocalisations},
        {"keyframes_in_map", r.keyframes_in_map},
        {"map_points", r.map_points},
        {"map_correction_m", r.map_correction_m},
        {"mapping_ms_p50", r.mapping_ms_p50},
        {"mapping_ms_p99", r.mapping_ms_p99},
        {"loop_ms_p50", r.loop_ms_p50},
        {"loop_ms_p99", r.loop_ms_p99},
        {"loop_revisits", r.loop_revisits},
        {"loop_recall", r.loop_recall},
        {"map_recall", r.map_recall},
        {"false_loops", r.false_loops}};
    for (const auto& [key, value] : figures) c[key] = json_figure(value);
    c["fail"] = !r.fail.empty();
    c["fail_reasons"] = r.fail;
    cases.push_back(std::move(c));
  }
  tools::Json j = tools::Json::object();
  // --duration full: each case's own length (its duration_s), null here.
  j["duration_s_per_case"] = duration_s > 0 ? json_figure(duration_s) : tools::Json(nullptr);
  j["cases"] = std::move(cases);
  return tools::json_text(j);
}

// ---- --cpu-budget ------------------------------------------------------------
// One stage of the budget: a function callgrind charges, and what its count is
// divided by (frames tracked, optimizer solves or IMU samples).
struct BudgetStage {
  const char* label;
  const char* needle;  // substring of the demangled name
  const char* per;     // "frame", "solve", "sample"
};

const std::vector<BudgetStage>& budget_stages() {
  static const std::vector<BudgetStage> st{
      {"tracking, whole frame", "kestrel::core::Tracker::track(", "frame"},
      {"  ORB extraction", "kestrel::core::OrbExtractor::extract(", "frame"},
      {"  depth back-projection", "kestrel::core::Tracker::Impl::back_project(", "frame"},
      {"  IMU-predicted matching", "kestrel::core::Tracker::Impl::match_keyframe(", "frame"},
      {"  LONSC", "kestrel::core::LonscEstimator::estimate(", "frame"},
      {"  pose refinement", "kestrel::core::refine_pose_gauss_newton(", "frame"},
      {"  keyframe", "kestrel::core::Tracker::Impl::make_keyframe(", "frame"},
      {"  map-point search", "kestrel::core::Tracker::Impl::search_map(", "frame"},
      {"optimizer solve", "kestrel::core::WindowOptimizer::optimize()", "solve"},
      {"IMU propagation", "kestrel::core::ImuPropagator::propagate(", "sample"},
  };
  return st;
}

// Runs `kestrel replay` (this very binary) under callgrind; stdout and stderr
// go to `console`. Returns the exit status text, empty when it succeeded.
std::string run_under_callgrind(const std::vector<std::string>& replay_args, const std::string& out_file,
                                const std::string& console) {
  const std::string self = fs::read_symlink("/proc/self/exe").string();
  std::vector<std::string> argv{"valgrind",
                                "--tool=callgrind",
                                "--compress-strings=no",
                                "--compress-pos=no",
                                "--dump-instr=no",
                                "--callgrind-out-file=" + out_file,
                                self};
  argv.insert(argv.end(), replay_args.begin(), replay_args.end());
  std::fflush(nullptr);
  const pid_t pid = fork();
  if (pid < 0) throw std::runtime_error("fork failed");
  if (pid == 0) {
    FILE* f = std::freopen(console.c_str(), "w", stdout);
    if (f == nullptr) _exit(126);
    dup2(fileno(stdout), 2);
    std::vector<char*> a;
    a.reserve(argv.size());

    for (auto& s : argv) a.push_back(s.data());
    a.push_back(nullptr);
    execvp("valgrind", a.data());
    _exit(127);
  }
  int status = 0;
  waitpid(pid, &status, 0);
  if (WIFEXITED(status) && WEXITSTATUS(status) == 127)
    return "valgrind not found (tools/install-deps.sh installs it)";
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    return "replay under callgrind failed (status " + std::to_string(status) + "; its output: " + console +
           ")";
  }
  return {};
}

// ---- --dataset-root -----------------------------------------------------------
// The standard table of the VIO papers from a user's own copy of EuRoC or
// TUM-VI (docs/stereo.md): every sequence under the root, whole length, the
// ATE after SE(3) and after Sim(3) per sequence, the share of frames posed and
// the CPU per second of flight; evo-compatible TUM trajectories beside it.

struct DatasetSequence {
  std::string name;  // path under the root ("V1_01_easy", "tumvi/dataset-room1_512_16")
  std::string path;
};

// A sequence is a folder the EuRoC or TUM-VI reader takes; its insides are not searched further.
void find_sequences(const fs::path& dir, const fs::path& root, int depth, std::vector<DatasetSequence>& out) {
  std::vector<fs::path> children;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(dir, ec))
    if (e.is_directory(ec)) children.push_back(e.path());
  std::sort(children.begin(), children.end());
  for (const fs::path& c : children) {
    const std::string p = c.string();
    if (drivers::is_tumvi_folder(p) || drivers::is_euroc_folder(p)) {
      out.push_back({fs::relative(c, root).string(), p});
    } else if (depth > 1) {
      find_sequences(c, root, depth - 1, out);
    }
  }
}

struct DatasetRow {
  DatasetSequence seq;
  std::string format = "-", mode = "-";
  double frames = kNaN, duration_s = kNaN, pose_share = kNaN, ate_se3_m = kNaN, ate_sim3_m = kNaN;
  double sim3_scale = kNaN, cpu_s_per_s = kNaN, process_cpu_s_per_s = kNaN;
  std::string status = "ok";   // else what went wrong; the other rows still run
  std::string input_problems;  // the reader's LogProblems, counted, the first named
  std::string traj;            // the TUM trajectory written ("" when none)
};

// CSV fields are ours except the status text, which may hold commas or quotes.
std::string csv_quoted(const std::string& v) {
  std::string o = "\"";
  for (char c : v) o += c == '"' ? std::string("\"\"") : std::string(1, c);
  return o + "\"";
}

int run_dataset_root(const std::string& root, const std::string& out_dir, drivers::ReplayPace pace,
                     const core::EstimatorConfig& cfg, bool strict) {
  if (!fs::is_directory(root)) throw UsageError("--dataset-root: no such folder: " + root);
  std::vector<DatasetSequence> seqs;
  if (drivers::is_tumvi_folder(root) || drivers::is_euroc_folder(root)) {
    fs::path p = fs::path(root).lexically_normal();
    if (p.filename().empty()) p = p.parent_path();  // "DIR/"
    seqs.push_back({p.filename().string(), root});
  } else {
    find_sequences(root, root, 3, seqs);
  }
  if (seqs.empty()) {
    throw std::runtime_error(root +
                             ": no EuRoC or TUM-VI sequence (a folder with mav0/, imu0/data.csv or imu0.csv) "
                             "up to three levels down");
  }
  fs::create_directories(out_dir);
  std::vector<DatasetRow> rows;
  for (const DatasetSequence& sq : seqs) {
    DatasetRow row;
    row.seq = sq;
    std::fprintf(stderr, "bench: %s ...\n", sq.name.c_str());
    // Opened here first (the tables only; images stay on disk) so a sequence
    // that cannot be replayed is named in its row rather than lost in a child.
    try {
      const auto src = drivers::open_log(sq.path);
      row.format = src->format_name();
      const auto* folder = dynamic_cast<const drivers::FolderLogSource*>(src.get());
      if (folder != nullptr && folder->rgb_count() == 0) {
        row.status = "FAILED: no cam0 images (IMU and ground truth only?)";
        rows.push_back(row);
        continue;
      }
      const bool stereo = src->rig().stereo.present && (folder == nullptr || folder->right_count() > 0);
      // What the reader skipped or repaired stays visible beside the figures it affects.
      if (!src->problems().empty()) {
        const drivers::LogProblem& p = src->problems().front();
        row.input_problems = std::to_string(src->problems().size()) +
                             " input problem(s), the first: " + p.kind + " at " + p.where;
      }
      row.mode = stereo ? "stereo-inertial" : "mono-inertial";
    } catch (const std::exception& e) {
      row.status = std::string("FAILED: ") + e.what();
      rows.push_back(row);
      continue;
    }
    std::string name = sq.name;
    std::replace(name.begin(), name.end(), '/', '_');
    row.traj = (fs::path(out_dir) / (name + ".tum")).string();
    std::string est, error, gt_note;
    const auto m = replay_in_child(sq.path, sq.path, pace, cfg, row.traj, est, error, &gt_note);
    row.frames = get(m, "frames");
    row.duration_s = get(m, "duration_s");
    row.pose_share = get(m, "pose_share");
    row.ate_se3_m = get(m, "ate_se3_rmse_m");
    row.ate_sim3_m = get(m, "ate_sim3_rmse_m");
    row.sim3_scale = get(m, "sim3_scale");
    row.cpu_s_per_s = get(m, "cpu_s_per_s");
    row.process_cpu_s_per_s = get(m, "cpu_per_s");
    if (!error.empty()) {
      row.status = "FAILED: " + error;
    } else if (!gt_note.empty()) {
      row.status = "no ground truth: " + gt_note;
    }
    if (!row.input_problems.empty()) row.status += "; " + row.input_problems;
    if (!fs::exists(row.traj)) row.traj.clear();
    rows.push_back(row);
  }

  const std::string md_path = (fs::path(out_dir) / "table.md").string();
  const std::string csv_path = (fs::path(out_dir) / "table.csv").string();
  std::ostringstream md;
  md << "| sequence | format | mode | frames | length s | posed % | ATE SE(3) m | ATE Sim(3) m | Sim(3) "
        "scale | "
        "estimator CPU s/s | process CPU s/s | status |\n"
     << "|---|---|---|---|---|---|---|---|---|---|---|---|\n";
  std::ostringstream csv;
  csv << "sequence,format,mode,frames,duration_s,pose_share,ate_se3_rmse_m,ate_sim3_rmse_m,sim3_scale,cpu_s_"
         "per_s,"
         "process_cpu_s_per_s,trajectory,status\n";
  int failed = 0;
  auto cell = [](double v, const char* f) { return fmt(v, f); };
  for (const DatasetRow& r : rows) {
    if (r.status.rfind("FAILED", 0) == 0) ++failed;
    std::string status = r.status;
    std::replace(status.begin(), status.end(), '|', '/');
    std::replace(status.begin(), status.end(), '\n', ' ');
    md << "| " << r.seq.name << " | " << r.format << " | " << r.mode << " | " << cell(r.frames, "%.0f")
       << " | " << cell(r.duration_s, "%.1f") << " | " << cell(100.0 * r.pose_share, "%.1f") << " | "
       << cell(r.ate_se3_m, "%.4f") << " | " << cell(r.ate_sim3_m, "%.4f") << " | "
       << cell(r.sim3_scale, "%.3f") << " | " << cell(r.cpu_s_per_s, "%.3f") << " | "
       << cell(r.process_cpu_s_per_s, "%.3f") << " | " << status << " |\n";
    auto num = [](double v) { return std::isfinite(v) ? fmt(v, "%.6g") : std::string(); };
    csv << csv_quoted(r.seq.name) << ',' << r.format << ',' << r.mode << ',' << num(r.frames) << ','
        << num(r.duration_s) << ',' << num(r.pose_share) << ',' << num(r.ate_se3_m) << ','
        << num(r.ate_sim3_m) << ',' << num(r.sim3_scale) << ',' << num(r.cpu_s_per_s) << ','
        << num(r.process_cpu_s_per_s) << ',' << csv_quoted(r.traj) << ',' << csv_quoted(r.status) << '\n';
  }
  for (const auto& [path, text] : {std::pair<const std::string&, std::string>{md_path, md.str()},
                                   std::pair<const std::string&, std::string>{csv_path, csv.str()}}) {
    std::ofstream f(path);
    if (!(f << text)) throw std::runtime_error("cannot write " + path);
  }
  std::printf("%s\ntable: %s, %s; trajectories (TUM: t[s] x y z qx qy qz qw, body in W): %s/<sequence>.tum\n",
              md.str().c_str(), md_path.c_str(), csv_path.c_str(), out_dir.c_str());
  if (failed > 0)
    std::fprintf(stderr, "bench: %d of %zu sequence(s) FAILED (named in the table)\n", failed, rows.size());
  if (failed == static_cast<int>(rows.size())) return 1;
  return strict && failed > 0 ? 2 : 0;
}

bool selected(const std::string& name, const std::vector<std::string>& only) {
  if (only.empty()) return true;
  for (const auto& o : only)
    if (name == o || name.find(o) != std::string::npos) return true;
  return false;
}

}  // namespace

namespace {

// `kestrel bench`'s options.
struct BenchArgs {
  std::string json_out;
  std::vector<std::string> cases;
  std::string duration = "30";
  std::vector<std::string> mapping{"on"};
  std::string workdir = "build/bench";
  std::string data_dir = "../shared/data";
  std::string pace = "fast";
  std::vector<std::string> estimators{"window"};
  std::vector<std::string> lonsc_variants{"tuned"};
  std::string config;
  int width = 640, height = 480;
  bool keep_logs = false;
  bool list = false;
  bool strict = false;
  bool cpu_budget = false;
  CLI::Option* duration_opt = nullptr;
  CLI::Option* mapping_opt = nullptr;
  std::string cpu_budget_log;
  std::string dataset_root;
  std::string out_dir;
};

// A row's figures from its replay's metrics (replay_in_child).
void fill_row(BenchRow& er, const std::map<std::string, double>& m) {
  er.duration_s = get(m, "duration_s");
  er.ate_rmse_m = get(m, "ate_rmse_m");
  er.ate_se3_rmse_m = get(m, "ate_se3_rmse_m");
  er.rpe_trans_m_per_s = get(m, "rpe_trans_m_per_s");
  er.tracking_ms_p50 = get(m, "tracking_ms_p50");
  er.tracking_ms_p99 = get(m, "tracking_ms_p99");
  er.optimizer_ms_p50 = get(m, "optimizer_ms_p50");
  er.optimizer_ms_p99 = get(m, "optimizer_ms_p99");
  er.imu_to_output_ms_p99 = get(m, "imu_to_output_ms_p99");
  er.imu_to_output_ms_p50 = get(m, "imu_to_output_ms_p50");
  er.imu_to_output_ms_max = get(m, "imu_to_output_ms_max");
  er.tracking_ms_max = get(m, "tracking_ms_max");
  er.optimizer_ms_max = get(m, "optimizer_ms_max");
  er.allocs_per_frame = get(m, "allocs_per_frame");
  er.realtime_factor = get(m, "realtime_factor");
  er.peak_rss_mb = get(m, "peak_rss_mb");
  er.pose_share = get(m, "pose_share");
  er.replay_wall_s = get(m, "replay_wall_s");
  er.divergences = get(m, "divergences");
  er.coast_s = get(m, "coast_s");
  er.cpu_s_per_s = get(m, "cpu_s_per_s");
  er.fail = fail_reasons(er);
  er.cpu_per_s = get(m, "cpu_per_s");
  er.map_cpu_s_per_s = get(m, "map_cpu_s_per_s");
  er.map_ate_se3_rmse_m = get(m, "map_ate_se3_rmse_m");
  er.map_final_ate_se3_rmse_m = get(m, "map_final_ate_se3_rmse_m");
  er.loop_closures = get(m, "loop_closures");
  er.relocalisations = get(m, "relocalisations");
  er.keyframes_in_map = get(m, "keyframes_in_map");
  er.map_points = get(m, "map_points");
  er.map_correction_m = get(m, "map_correction_m");
  er.mapping_ms_p50 = get(m, "mapping_ms_p50");
  er.mapping_ms_p99 = get(m, "mapping_ms_p99");
  er.loop_ms_p50 = get(m, "loop_ms_p50");
  er.loop_ms_p99 = get(m, "loop_ms_p99");
  er.loop_revisits = get(m, "loop_revisits");
  er.loop_recall = get(m, "loop_recall");
  er.map_recall = get(m, "map_recall");
  er.false_loops = get(m, "false_loops");
}

// --cpu-budget: instructions per frame for each tracking stage and per
// optimizer solve under callgrind, with ARM estimates (docs/embedded.md).
int run_cpu_budget(const BenchArgs& a, double duration_s) {
  const std::string backend = a.estimators.front();
  const std::string mapping = a.mapping.front();
  const double budget_s = a.duration_opt->count() > 0 ? duration_s : 4.0;
  if (!(budget_s > 0)) throw UsageError("--cpu-budget needs a --duration in seconds, not `full`");
  fs::create_directories(a.workdir);
  std::string log = a.cpu_budget_log;
  std::string what;
  if (log.empty()) {
    tools::SimOptions so;
    so.seed = 1;
    so.scenario = "figure8";
    so.duration_s = budget_s;
    so.width = a.width;
    so.height = a.height;
    log = (fs::path(a.workdir) / "cpu_budget.klog").string();
    so.out_path = log;
    std::fprintf(stderr, "bench: simulating the budget flight (figure8, %.0f s, %dx%d, seed 1)\n", budget_s,
                 a.width, a.height);
    tools::run_simulation(so);
    char buf[96];
    std::snprintf(buf, sizeof buf, "figure8 %.0f s %dx%d seed 1", budget_s, a.width, a.height);
    what = buf;
  } else {
    if (!fs::exists(log)) throw UsageError("--cpu-budget-log: no such file: " + log);
    what = log;
  }
  core::EstimatorConfig cfg = tools::load_config(a.config, backend).estimator;
  // The ekf's map is off unless asked for (ekf.mapping): the bench's default "on" is the window's.
  const bool given = a.mapping_opt->count() > 0 || backend != "ekf";
  tools::apply_map_switches(cfg, given ? mapping : "", "");
  std::fprintf(stderr, "bench: native replay (lockstep) for the time per frame here\n");
  std::string est_name, error;
  const auto native = replay_in_child(log, log, drivers::ReplayPace::kLockstep, cfg, "", est_name, error);
  if (!error.empty()) throw std::runtime_error("native replay: " + error);
  const std::string cg_out = (fs::path(a.workdir) / "cpu_budget.callgrind").string();
  const std::string console = (fs::path(a.workdir) / "cpu_budget.replay.txt").string();
  std::vector<std::string> rargs{"replay", log, "--estimator", backend, "--pace", "lockstep", "--quiet"};
  if (given) {
    rargs.push_back("--mapping");
    rargs.push_back(mapping);
  }
  if (!a.config.empty()) {
    rargs.push_back("--config");
    rargs.push_back(a.config);
  }
  std::fprintf(stderr, "bench: the same replay under callgrind (about 50x slower) -> %s\n", cg_out.c_str());
  const std::string cg_error = run_under_callgrind(rargs, cg_out, console);
  if (!cg_error.empty()) throw std::runtime_error(cg_error);
  std::vector<std::string> needles;
  for (const auto& st : budget_stages()) needles.push_back(st.needle);
  const auto costs = tools::callgrind_inclusive(cg_out, needles);
  const double frames = static_cast<double>(costs.at(budget_stages()[0].needle).calls);
  if (frames <= 0) {
    throw std::runtime_error(cg_out + ": no call of Tracker::track: the backend '" + backend +
                             "' has no tracker, or the binary's symbols are stripped");
  }
  auto count_of = [&](const char* per) {
    for (const auto& st : budget_stages())
      if (std::strcmp(st.per, per) == 0) return static_cast<double>(costs.at(st.needle).calls);
    return 0.0;
  };
  const double solves = count_of("solve"), samples = count_of("sample");
  const auto& cores = tools::arm_core_models();
  std::printf(
      "cpu budget: %s, %s (mapping %s) — %.0f frames, %.0f optimizer solves, %.0f IMU samples; "
      "instructions counted by callgrind (x86-64, this build)\n",
      backend.c_str(), what.c_str(), mapping.c_str(), frames, solves, samples);
  std::printf("%-26s %8s %12s %10s", "stage", "calls", "Minstr/call", "Minstr/per");
  for (const auto& c : cores) std::printf(" %14s", (std::string(c.name) + " ms").c_str());
  std::printf("\n");
  tools::Json j;
  j["backend"] = backend;
  j["flight"] = what;
  j["frames"] = frames;
  j["optimizer_solves"] = solves;
  j["imu_samples"] = samples;
  tools::Json jstages = tools::Json::array();
  for (const auto& st : budget_stages()) {
    const tools::CallgrindCost& c = costs.at(st.needle);
    const double denom = std::strcmp(st.per, "frame") == 0   ? frames
                         : std::strcmp(st.per, "solve") == 0 ? solves
                                                             : samples;
    const double per = denom > 0 ? static_cast<double>(c.inclusive_ir) / denom : kNaN;
    const double per_call =
        c.calls > 0 ? static_cast<double>(c.inclusive_ir) / static_cast<double>(c.calls) : kNaN;
    std::printf("%-26s %8llu %12s %10s", st.label, static_cast<unsigned long long>(c.calls),
                fmt(per_call * 1e-6, "%.4g").c_str(), (fmt(per * 1e-6, "%.4g") + "/" + st.per).c_str());
    tools::Json js;
    js["stage"] = std::string(st.label).substr(std::string(st.label).find_first_not_of(' '));
    js["function"] = st.needle;
    js["per"] = st.per;
    js["calls"] = c.calls;
    js["instructions_per_call"] = tools::json_figure(per_call);
    js["instructions_per_unit"] = tools::json_figure(per);
    for (const auto& core_m : cores) {
      const double ms = tools::estimated_ms(per, core_m);
      std::printf(" %14s", fmt(ms, ms < 0.1 ? "%.2g" : "%.2f").c_str());
      js[std::string("ms_") + core_m.name] = tools::json_figure(ms);
    }
    std::printf("\n");
    jstages.push_back(js);
  }
  j["stages"] = jstages;
  const double track_ms_p50 = get(native, "tracking_ms_p50"), track_ms_p99 = get(native, "tracking_ms_p99");
  const double opt_ms_p50 = get(native, "optimizer_ms_p50"), opt_ms_p99 = get(native, "optimizer_ms_p99");
  const double track_ir = static_cast<double>(costs.at(budget_stages()[0].needle).inclusive_ir) / frames;
  std::printf(
      "here (wall clock, lockstep): tracking p50 %s ms p99 %s ms; optimizer p50 %s ms p99 %s ms; "
      "%s instructions per ns of tracking p50\n",
      fmt(track_ms_p50, "%.2f").c_str(), fmt(track_ms_p99, "%.2f").c_str(), fmt(opt_ms_p50, "%.2f").c_str(),
      fmt(opt_ms_p99, "%.2f").c_str(), fmt(track_ir / (track_ms_p50 * 1e6), "%.2f").c_str());
  std::printf("ARM estimate = instructions / (IPC x clock), same instruction count as x86-64 assumed:");
  for (const auto& c : cores)
    std::printf(" %s (%s) %.1f GHz IPC %.1f;", c.name, c.example, c.clock_ghz, c.ipc);
  std::printf("\n");
  j["here"] = {{"tracking_ms_p50", tools::json_figure(track_ms_p50)},
               {"tracking_ms_p99", tools::json_figure(track_ms_p99)},
               {"optimizer_ms_p50", tools::json_figure(opt_ms_p50)},
               {"optimizer_ms_p99", tools::json_figure(opt_ms_p99)}};
  tools::Json jc = tools::Json::array();
  for (const auto& c : cores)
    jc.push_back({{"core", c.name}, {"example", c.example}, {"clock_ghz", c.clock_ghz}, {"ipc", c.ipc}});
  j["core_models"] = jc;
  if (!a.json_out.empty()) {
    std::ofstream f(a.json_out);
    if (!f) throw std::runtime_error("cannot write " + a.json_out);
    f << tools::json_text(j);
    std::printf("json: %s\n", a.json_out.c_str());
  }
  if (a.cpu_budget_log.empty() && !a.keep_logs) fs::remove(log);
  return 0;
}

// The cases (rendered, hybrid, real): one log each, every backend, LONSC
// variant and map switch on it, then the tables.
int run_cases(const BenchArgs& a, double duration_s, drivers::ReplayPace pace) {
  std::vector<BenchCase> cases = discover_cases(a.data_dir);
  if (a.list) {
    for (const auto& c : cases) {
      std::printf("%-26s %-12s %s\n", c.name.c_str(), c.kind.c_str(),
                  c.skipped.empty() ? "ready" : ("SKIPPED: " + c.skipped).c_str());
    }
    return 0;
  }
  fs::create_directories(a.workdir);
  std::vector<BenchRow> rows;
  int ran = 0;
  for (const auto& c : cases) {
    if (!selected(c.name, a.cases)) continue;
    BenchRow row;
    row.name = c.name;
    if (!c.skipped.empty()) {
      row.status = "SKIPPED: " + c.skipped;
      std::fprintf(stderr, "bench: %s SKIPPED: %s\n", c.name.c_str(), c.skipped.c_str());
      rows.push_back(row);
      continue;
    }
    std::fprintf(stderr, "bench: %s ...\n", c.name.c_str());
    const std::string traj = (fs::path(a.workdir) / (c.name + ".traj.txt")).string();
    std::string log = c.log_path;
    std::string gt = c.gt_path;
    bool generated = false;
    if (c.kind != "real-images" && c.kind != "real-rgbd") {
      tools::SimOptions so;
      so.seed = 1;
      if (c.kind == "real-synth-imu") {
        so.images_path = c.images_path;  // the recording's length, size and rate
      } else {
        so.duration_s = duration_s;
        so.width = a.width;
        so.height = a.height;
      }
      if (c.kind == "real-synth-imu") {
        // nothing more: the motion is the recording's
      } else if (c.kind == "scenario") {
        so.scenario = c.scenario;
      } else {
        so.trajectory_path = c.gt_path;
        so.imu_path = c.imu_path;
        so.fps = 30.0;
        so.room_m = c.room_m;
        so.stereo = c.stereo;
      }
      log = (fs::path(a.workdir) / (c.name + ".klog")).string();
      so.out_path = log;
      try {
        tools::SimSummary s = tools::run_simulation(so);
        row.sim_s = s.wall_s;
      } catch (const std::exception& e) {
        row.status = std::string("FAILED (sim): ") + e.what();
        rows.push_back(row);
        continue;
      }
      gt = log;  // the simulator writes ground truth into the log (--images: the recording's own)
      generated = true;
    }
    // One log, every backend on it: the comparison is like for like.
    for (const std::string& backend : c.backends.empty() ? a.estimators : c.backends) {
      for (const std::string& variant : a.lonsc_variants) {
        for (const std::string& mapping : a.mapping) {
          const bool windowed = backend.rfind("window", 0) == 0;
          const bool ekf = backend == "ekf";
          if (!windowed && !ekf && mapping == "off" && a.mapping.size() > 1)
            continue;  // no map to switch off
          core::EstimatorConfig cfg = tools::load_config(a.config, backend).estimator;
          // The ekf's map is off unless asked for (ekf.mapping, or --mapping
          // given): the bench's default "on" is the window's.
          tools::apply_map_switches(cfg, windowed || a.mapping_opt->count() > 0 ? mapping : "", "");
          // A row's name: the backend, the LONSC variant when it is not the
          // default, "-nomap" for the window without its map and "-map" for the
          // ekf with one.
          const std::string map_tag = windowed && mapping == "off" ? "-nomap"
                                      : ekf && cfg.ekf.mapping     ? "-map"
                                                                   : "";
          const std::string est_name =
              (variant == "tuned" ? backend : backend + "+lonsc-" + variant) + map_tag;
          if (variant != to_string(cfg.lonsc_variant)) {
            cfg.lonsc_variant = variant == "paper" ? core::LonscVariant::kPaper : core::LonscVariant::kTuned;
            cfg.tracker.lonsc = core::lonsc_options(cfg.lonsc_variant);
          }
          BenchRow er = row;
          std::string error;
          const bool many = (c.backends.empty() ? a.estimators : c.backends).size() *
                                a.lonsc_variants.size() * a.mapping.size() >
                            1;
          const std::string traj_e =
              many ? (fs::path(a.workdir) / (c.name + "." + est_name + ".traj.txt")).string() : traj;
          const auto m = replay_in_child(log, gt, pace, cfg, traj_e, er.estimator, error);
          if (error.empty() && variant != "tuned") er.estimator += "+lonsc-" + variant;
          if (error.empty()) er.estimator += map_tag;
          if (!error.empty()) {
            er.estimator = est_name;
            er.status = "FAILED: " + error;
            rows.push_back(er);
            continue;
          }
          fill_row(er, m);
          rows.push_back(er);
          ++ran;
        }
      }
    }
    if (generated && !a.keep_logs) fs::remove(log);
  }
  print_table(rows);
  print_timing_table(rows);
  print_map_table(rows);
  if (!a.json_out.empty()) {
    std::ofstream f(a.json_out);
    if (!f) throw std::runtime_error("cannot write " + a.json_out);
    f << rows_json(rows, duration_s);
    std::printf("json: %s\n", a.json_out.c_str());
  }
  if (ran == 0) {
    std::fprintf(stderr, "bench: no case ran\n");
    return 1;
  }
  if (a.strict) {
    int failed = 0;
    for (const auto& r : rows)
      if (!r.fail.empty() || r.status.rfind("FAILED", 0) == 0) ++failed;
    if (failed > 0) {
      std::fprintf(stderr, "bench: %d row(s) FAIL (--strict)\n", failed);
      return 2;
    }
  }
  return 0;
}

}  // namespace

Subcommand add_bench_command(CLI::App& parent) {
  auto args = std::make_shared<BenchArgs>();
  CLI::App* app = parent.add_subcommand("bench", "run the benchmark suite and print one table");
  app->add_option("--json", args->json_out, "also write the table as JSON to this file");
  app->add_option("--cases", args->cases, "only the cases whose name contains one of these")->delimiter(',');
  args->duration_opt =
      app->add_option(
             "--duration", args->duration,
             "seconds of flight per case, or `full`: every hybrid flight over its whole length (scenarios: "
             "their default length)")
          ->capture_default_str();
  args->mapping_opt =
      app->add_option(
             "--mapping", args->mapping,
             "on, off or both (on,off): the window backend with and without the map threads, one row each; "
             "the ekf runs the map only when asked (ekf.mapping, or --mapping on: a row `ekf-map`)")
          ->delimiter(',')
          ->capture_default_str();
  app->add_option("--workdir", args->workdir, "where generated logs and trajectories go")
      ->capture_default_str();
  app->add_option("--data", args->data_dir, "the shared data folder (EuRoC sequences, real-rgbd/)")
      ->capture_default_str();
  app->add_option("--pace", args->pace, "replay pace: fast or lockstep (realtime is for timing tests)")
      ->capture_default_str();
  app->add_option("--estimator", args->estimators,
                  std::string("backends, comma separated, one row each per case: ") + core::estimator_names())
      ->delimiter(',')
      ->capture_default_str();
  app->add_option("--lonsc-variant", args->lonsc_variants,
                  "LONSC variants, comma separated, one row each per backend: tuned, paper (docs/lonsc.md)")
      ->delimiter(',')
      ->capture_default_str();
  app->add_option("--config", args->config,
                  "estimator settings applied to every backend (its estimator sections; docs/config.md)");
  app->add_option("--width", args->width, "rendered image width")->capture_default_str();
  app->add_option("--height", args->height, "rendered image height")->capture_default_str();
  app->add_flag("--keep-logs", args->keep_logs, "keep the generated .klog files (several GB at VGA)");
  app->add_flag("--list", args->list, "list the cases and whether their data is present, then exit");
  app->add_flag(
      "--cpu-budget", args->cpu_budget,
      "instead of the table: instructions per frame for each tracking stage and per optimizer solve, "
      "counted by valgrind's callgrind on a fixed simulated flight (figure8, seed 1, --width x --height, "
      "--duration default 4 s here), with estimates for ARM cores (docs/embedded.md)");
  app->add_option("--cpu-budget-log", args->cpu_budget_log,
                  "--cpu-budget on this log instead of the simulated flight (it needs ground truth)");
  app->add_option(
      "--dataset-root", args->dataset_root,
      "instead of the cases: every EuRoC or TUM-VI sequence found under this folder, whole length, "
      "the first --estimator (stereo-inertial where the sequence has cam1); writes table.md, "
      "table.csv and <sequence>.tum into --out (docs/stereo.md)");
  app->add_option("--out", args->out_dir,
                  "--dataset-root: where the table and trajectories go (default: <workdir>/datasets)");
  app->add_flag(
      "--strict", args->strict,
      "exit non-zero when a row FAILs (ATE over 1 m or pose share under 99 %) or a case fails to run");

  Subcommand cmd;
  cmd.app = app;
  cmd.run = [args]() -> int {
    double duration_s = -1.0;  // full
    if (args->duration != "full") {
      char* end = nullptr;
      duration_s = std::strtod(args->duration.c_str(), &end);
      if (end == args->duration.c_str() || *end != '\0' || !(duration_s > 0))
        throw UsageError("--duration must be > 0 seconds or `full`, got '" + args->duration + "'");
    }
    for (const std::string& m : args->mapping)
      if (m != "on" && m != "off") throw UsageError("unknown --mapping '" + m + "' (expected on, off)");
    if (args->width < 32 || args->height < 32) throw UsageError("--width/--height must be >= 32");
    drivers::ReplayPace pace;
    try {
      pace = drivers::parse_replay_pace(args->pace);
    } catch (const std::exception& e) {
      throw UsageError(e.what());
    }
    for (const std::string& e : args->estimators) {
      if (!core::estimator_known(e)) {
        throw UsageError("unknown --estimator '" + e + "' (expected one of: " + core::estimator_names() +
                         ")");
      }
    }
    for (const std::string& v : args->lonsc_variants) {
      if (v != "tuned" && v != "paper")
        throw UsageError("unknown --lonsc-variant '" + v + "' (expected tuned, paper)");
    }
    if (!args->dataset_root.empty()) {
      const std::string backend = args->estimators.front();
      core::EstimatorConfig cfg = tools::load_config(args->config, backend).estimator;
      tools::apply_map_switches(cfg, backend.rfind("window", 0) == 0 ? args->mapping.front() : "", "");
      const std::string out =
          args->out_dir.empty() ? (fs::path(args->workdir) / "datasets").string() : args->out_dir;
      return run_dataset_root(args->dataset_root, out, pace, cfg, args->strict);
    }
    if (args->cpu_budget) return run_cpu_budget(*args, duration_s);
    return run_cases(*args, duration_s, pace);
  };
  return cmd;
}

}  // namespace kestrel::cli

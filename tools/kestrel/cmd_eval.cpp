// `kestrel eval`: compare an estimated trajectory with ground truth (ATE, RPE).
// The work is in kestrel_eval (tools/eval); this file is options and output.
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/commands.hpp"
#include "kestrel/tools/trajectory_eval.hpp"

namespace kestrel::cli {
namespace {

struct EvalArgs {
  std::string gt_path;
  std::string est_path;
  std::string align = "posyaw";
  double max_gap_ms = 20.0;
  double rpe_delta_s = 1.0;
  std::vector<double> segments_m{1.0, 2.0, 5.0};
  bool json = false;
  std::string plot_path;
  std::string aligned_out;
  std::string report_path;
  std::string metrics_path;
};

std::string num(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", v);
  return buf;
}

void print_warnings(const std::vector<std::string>& warnings) {
  for (const auto& w : warnings) std::fprintf(stderr, "kestrel eval: warning: %s\n", w.c_str());
}

int run_eval(const EvalArgs& a) {
  if (!a.metrics_path.empty() && a.report_path.empty())
    throw UsageError("--metrics goes with --report (its latency histograms go into the page)");
  tools::EvalOptions opt;
  const auto align = tools::parse_alignment(a.align);
  if (!align) throw UsageError("unknown --align '" + a.align + "' (expected se3, sim3, posyaw or none)");
  opt.align = *align;
  if (!std::isfinite(a.max_gap_ms) || a.max_gap_ms < 0)
    throw UsageError("--max-gap-ms must be >= 0, got " + num(a.max_gap_ms));
  if (!std::isfinite(a.rpe_delta_s) || a.rpe_delta_s <= 0)
    throw UsageError("--rpe-delta-s must be > 0, got " + num(a.rpe_delta_s));
  for (double L : a.segments_m)
    if (!std::isfinite(L) || L <= 0) throw UsageError("--segments-m lengths must be > 0, got " + num(L));
  opt.max_gap_ms = a.max_gap_ms;
  opt.rpe_delta_s = a.rpe_delta_s;
  opt.segment_lengths_m = a.segments_m;

  std::vector<std::string> gt_warnings, est_warnings;
  const tools::Trajectory gt = tools::load_trajectory(a.gt_path, &gt_warnings);
  print_warnings(gt_warnings);
  const tools::Trajectory est = tools::load_trajectory(a.est_path, &est_warnings);
  print_warnings(est_warnings);

  // The metrics file is read before anything is computed: a bad one is a
  // mistake to report at once, not after the evaluation.
  tools::HtmlReportOptions report;
  if (!a.metrics_path.empty()) {
    report.latencies = tools::read_replay_latencies(a.metrics_path);
    report.metrics_file = a.metrics_path;
  }

  tools::EvalResult result = tools::evaluate(gt, est, opt);
  result.gt_file = a.gt_path;
  result.est_file = a.est_path;
  // Loader warnings count too: a reader of the numbers should know lines were skipped.
  std::vector<std::string> all = gt_warnings;
  all.insert(all.end(), est_warnings.begin(), est_warnings.end());
  print_warnings(result.warnings);
  all.insert(all.end(), result.warnings.begin(), result.warnings.end());
  result.warnings = std::move(all);

  const std::string out = a.json ? tools::to_json(result) : tools::to_text(result);
  std::fwrite(out.data(), 1, out.size(), stdout);
  std::fflush(stdout);

  if (!a.plot_path.empty()) {
    tools::write_svg_plot(a.plot_path, gt, result, a.est_path);
    std::fprintf(stderr, "kestrel eval: plot written to %s\n", a.plot_path.c_str());
  }
  if (!a.report_path.empty()) {
    report.title = "Kestrel: " + a.est_path + " against " + a.gt_path;
    report.max_gap_ms = a.max_gap_ms;
    tools::write_html_report(a.report_path, gt, result, report);
    std::fprintf(stderr, "kestrel eval: report written to %s\n", a.report_path.c_str());
  }
  if (!a.aligned_out.empty()) {
    tools::write_tum(a.aligned_out, result.est_aligned);
    std::fprintf(stderr, "kestrel eval: aligned estimate written to %s\n", a.aligned_out.c_str());
  }
  return 0;
}

}  // namespace

Subcommand add_eval_command(CLI::App& parent) {
  auto args = std::make_shared<EvalArgs>();
  CLI::App* app =
      parent.add_subcommand("eval", "compare an estimated trajectory with ground truth (ATE, RPE)");
  app->footer(
      "Trajectories: TUM text (t[s] x y z qx qy qz qw), EuRoC CSV (t[ns],px,py,pz,qw,qx,qy,qz,...),\n"
      "or a .klog / EuRoC / TUM RGB-D log (its ground-truth records). See docs/evaluation.md.\n"
      "First output line: `ate_rmse_m: <value>`.");
  app->add_option("--gt", args->gt_path, "ground-truth trajectory or log")->required();
  app->add_option("--est", args->est_path, "estimated trajectory")->required();
  app->add_option("--align", args->align,
                  "se3 | sim3 | posyaw | none (posyaw: translation + yaw, the unobservable DoF of VIO)")
      ->capture_default_str();
  app->add_option("--max-gap-ms", args->max_gap_ms, "association tolerance [ms]")->capture_default_str();
  app->add_option("--rpe-delta-s", args->rpe_delta_s, "RPE time step [s]")->capture_default_str();
  app->add_option("--segments-m", args->segments_m, "KITTI-style RPE segment lengths [m], comma separated")
      ->delimiter(',')
      ->capture_default_str();
  app->add_flag("--json", args->json, "print a JSON object instead of key: value lines");
  app->add_option("--plot", args->plot_path, "write an SVG plot (top view + error over time)");
  app->add_option(
      "--report", args->report_path,
      "write a self-contained HTML page: top/side views after alignment, error over time and per axis, "
      "RPE over several time steps (opens with no network)");
  app->add_option(
      "--metrics", args->metrics_path,
      "with --report: a `kestrel replay --metrics-out` JSON whose latency histograms go into the page");
  app->add_option("--save-aligned", args->aligned_out, "write the aligned, associated estimate as TUM text");
  return Subcommand{app, [args]() { return run_eval(*args); }};
}

}  // namespace kestrel::cli

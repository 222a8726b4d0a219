// `kestrel eval --report out.html`: one self-contained page (inline CSS and
// SVG drawn here, no script, nothing fetched), so it opens from a mail
// attachment or a CI artefact with no network and no server.
#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <stdexcept>
#include <string>
#include <tuple>
#include <vector>

#include "kestrel/tools/trajectory_eval.hpp"
#include "svg_plot.hpp"

namespace kestrel::tools {
namespace {

using svg::axes;
using svg::fmt;
using svg::padded;
using svg::Panel;
using svg::polyline;
using svg::xml_escape;

constexpr const char* kGtColour = "#222";
constexpr const char* kEstColour = "#d62728";
constexpr const char* kAxisColours[3] = {"#d62728", "#2ca02c", "#1f77b4"};

std::string open_svg(const std::string& id, double w, double h) {
  return "<svg id='" + id + "' width='" + fmt("%.0f", w) + "' height='" + fmt("%.0f", h) + "' viewBox='0 0 " +
         fmt("%.0f", w) + " " + fmt("%.0f", h) + "' font-family='sans-serif' font-size='12'>\n";
}

void title(std::string& s, const Panel& p, const std::string& text) {
  s += "<text x='" + fmt("%.1f", p.x0 + p.w / 2) + "' y='" + fmt("%.1f", p.y0 - 8) +
       "' text-anchor='middle'>" + xml_escape(text) + "</text>\n";
}

// One projection of both trajectories (a, b: the axes, 0 = x, 1 = y, 2 = z) at equal scale.
std::string view(const std::string& id, const std::string& heading, const Trajectory& gt, const EvalResult& r,
                 int a, int b) {
  double lo[2] = {INFINITY, INFINITY}, hi[2] = {-INFINITY, -INFINITY};
  auto grow = [&](const Eigen::Vector3d& p) {
    if (!p.allFinite()) return;
    lo[0] = std::min(lo[0], p[a]);
    hi[0] = std::max(hi[0], p[a]);
    lo[1] = std::min(lo[1], p[b]);
    hi[1] = std::max(hi[1], p[b]);
  };
  for (const auto& p : gt) grow(p.p);
  for (const auto& p : r.est_aligned) grow(p.p);
  std::string s = open_svg(id, 560, 520);
  Panel p{70, 30, 460, 440, padded(lo[0], hi[0], 0.5), padded(lo[1], hi[1], 0.5)};
  svg::equal_aspect(p);
  const char* names = "xyz";
  axes(s, p, std::string(1, names[a]) + " [m]", std::string(1, names[b]) + " [m]");
  title(s, p, heading);
  polyline(
      s, p, gt.size(), [&](size_t i) { return gt[i].p[a]; }, [&](size_t i) { return gt[i].p[b]; },
      [&](size_t i) { return gt[i].t_ns; }, std::string("stroke='") + kGtColour + "' stroke-width='1.5'");
  const auto& E = r.est_aligned;
  polyline(
      s, p, E.size(), [&](size_t i) { return E[i].p[a]; }, [&](size_t i) { return E[i].p[b]; },
      [&](size_t i) { return E[i].t_ns; },
      std::string("stroke='") + kEstColour + "' stroke-width='1.2' stroke-opacity='0.85'");
  svg::legend(s, p.x0 + 10, p.y0 + 14, {{kGtColour, "ground truth"}, {kEstColour, "estimate (aligned)"}},
              170);
  return s + "</svg>\n";
}

// Lines over time since the first associated pose; values(k, i) for series k.
template <typename Value>
std::string time_plot(const std::string& id, const std::string& heading, const std::string& ylabel,
                      const EvalResult& r, const std::vector<std::pair<std::string, std::string>>& series,
                      Value value, bool from_zero) {
  const auto& E = r.est_aligned;
  const int64_t t0 = E.empty() ? 0 : E.front().t_ns;
  double tmax = E.empty() ? 1.0 : 1e-9 * static_cast<double>(E.back().t_ns - t0);
  double vlo = from_zero ? 0.0 : INFINITY, vhi = -INFINITY;
  for (size_t k = 0; k < series.size(); ++k) {
    for (size_t i = 0; i < E.size(); ++i) {
      const double v = value(k, i);
      if (!std::isfinite(v)) continue;
      vlo = std::min(vlo, v);
      vhi = std::max(vhi, v);
    }
  }
  if (!(tmax > 0)) tmax = 1.0;
  if (!(vhi > vlo)) {
    vlo = std::isfinite(vlo) ? vlo - 1e-3 : 0;
    vhi = vlo + 2e-3;
  }
  const double pad = 0.06 * (vhi - vlo);
  std::string s = open_svg(id, 560, 300);
  Panel p{70, 30, 460, 220, {0, tmax}, {from_zero ? 0.0 : vlo - pad, vhi + pad}};
  axes(s, p, "time since first associated pose [s]", ylabel);
  title(s, p, heading);
  for (size_t k = 0; k < series.size(); ++k) {
    polyline(
        s, p, E.size(), [&](size_t i) { return 1e-9 * static_cast<double>(E[i].t_ns - t0); },
        [&](size_t i) { return value(k, i); }, [&](size_t i) { return E[i].t_ns; },
        "stroke='" + series[k].first + "' stroke-width='1.1'");
  }
  if (series.size() > 1) svg::legend(s, p.x0 + 10, p.y0 + 14, series, 120);
  return s + "</svg>\n";
}

// RPE translation RMSE against the time step, log-log.
std::string rpe_plot(const std::vector<RpeStats>& rows) {
  std::string s = open_svg("rpe", 560, 300);
  double lo = INFINITY, hi = -INFINITY;
  for (const auto& r : rows) {
    if (r.pairs > 0 && r.trans_rmse_m > 0) {
      lo = std::min(lo, r.trans_rmse_m);
      hi = std::max(hi, r.trans_rmse_m);
    }
  }
  if (!(hi >= lo)) {
    s += "<text x='280' y='150' text-anchor='middle'>no RPE pairs at any time step</text>\n";
    return s + "</svg>\n";
  }
  const double dlo = std::log10(rows.front().delta_s), dhi = std::log10(rows.back().delta_s);
  Panel p{70, 30, 460, 220, padded(dlo, dhi, 0.3), padded(std::log10(lo), std::log10(hi), 0.3)};
  axes(s, p, "time step [s]", "translation RMSE [m]", true, true);
  title(s, p, "relative pose error against the time step");
  std::string pts;
  for (const auto& r : rows) {
    if (r.pairs == 0 || !(r.trans_rmse_m > 0)) continue;
    const double x = p.px(std::log10(r.delta_s)), y = p.py(std::log10(r.trans_rmse_m));
    pts += fmt("%.1f", x) + "," + fmt("%.1f", y) + " ";
    s += "<circle cx='" + fmt("%.1f", x) + "' cy='" + fmt("%.1f", y) + "' r='3' fill='#1f77b4'/>\n";
  }
  s += "<polyline fill='none' stroke='#1f77b4' stroke-width='1.2' points='" + pts + "'/>\n";
  return s + "</svg>\n";
}

// A latency histogram on a log time axis: the exported bins regrouped into
// about 48 buckets between the fastest and the slowest sample.
std::string latency_plot(const LatencyDistribution& d) {
  std::string s = open_svg("latency-" + d.name, 560, 260);
  int64_t lo_ns = std::numeric_limits<int64_t>::max(), hi_ns = 0;
  for (const auto& b : d.bins) {
    lo_ns = std::min(lo_ns, std::max<int64_t>(b.lower_ns, 1));
    hi_ns = std::max(hi_ns, b.lower_ns + b.width_ns);
  }
  const double l0 = std::log10(1e-6 * static_cast<double>(lo_ns)),
               l1 = std::log10(1e-6 * static_cast<double>(hi_ns));
  constexpr int kBuckets = 48;
  const double span = std::max(l1 - l0, 0.05);
  std::vector<double> count(kBuckets, 0.0);
  for (const auto& b : d.bins) {
    const double mid_ms = 1e-6 * (static_cast<double>(b.lower_ns) + 0.5 * static_cast<double>(b.width_ns));
    const int k = std::clamp(static_cast<int>((std::log10(std::max(mid_ms, 1e-6)) - l0) / span * kBuckets), 0,
                             kBuckets - 1);
    count[static_cast<size_t>(k)] += static_cast<double>(b.count);
  }
  const double cmax = *std::max_element(count.begin(), count.end());
  Panel p{70, 30, 460, 180, {l0, l0 + span}, {0, std::max(cmax, 1.0) * 1.1}};
  axes(s, p, "latency [ms]", "samples", true, false);
  title(s, p,
        d.name + ": " + std::to_string(d.count) + " samples, p50 " + fmt("%.3g", d.p50_ms) + " ms, p99 " +
            fmt("%.3g", d.p99_ms) + " ms, max " + fmt("%.3g", d.max_ms) + " ms");
  for (int k = 0; k < kBuckets; ++k) {
    if (count[static_cast<size_t>(k)] <= 0) continue;
    const double x0 = p.px(l0 + span * k / kBuckets), x1 = p.px(l0 + span * (k + 1) / kBuckets);
    const double y = p.py(count[static_cast<size_t>(k)]);
    s += "<rect class='bar' x='" + fmt("%.1f", x0) + "' y='" + fmt("%.1f", y) + "' width='" +
         fmt("%.1f", std::max(x1 - x0 - 1, 1.0)) + "' height='" + fmt("%.1f", p.y0 + p.h - y) +
         "' fill='#1f77b4'/>\n";
  }
  for (const auto& [v, label, colour] :
       {std::tuple<double, const char*, const char*>{d.p50_ms, "p50", "#2ca02c"},
        {d.p99_ms, "p99", "#ff7f0e"}}) {
    if (!(v > 0)) continue;
    const double x = p.px(std::log10(v));
    s += "<line x1='" + fmt("%.1f", x) + "' y1='" + fmt("%.1f", p.y0) + "' x2='" + fmt("%.1f", x) + "' y2='" +
         fmt("%.1f", p.y0 + p.h) + "' stroke='" + colour + "' stroke-dasharray='5,3'/>\n";
    s += "<text x='" + fmt("%.1f", x + 3) + "' y='" + fmt("%.1f", p.y0 + 12) + "' fill='" + colour + "'>" +
         label + "</text>\n";
  }
  return s + "</svg>\n";
}

std::string cell(double v, const char* f) { return std::isfinite(v) ? fmt(f, v) : std::string("&ndash;"); }

std::string row(const std::string& k, const std::string& v) {
  return "<tr><td>" + xml_escape(k) + "</td><td>" + v + "</td></tr>\n";
}

const char* kStyle = R"(
body { font: 14px/1.4 system-ui, sans-serif; margin: 24px; color: #222; background: #fafafa; }
h1 { font-size: 20px; margin: 0 0 4px; } h2 { font-size: 16px; margin: 28px 0 8px; }
.sub { color: #666; margin-bottom: 16px; }
.grid { display: flex; flex-wrap: wrap; gap: 12px; }
svg { background: white; border: 1px solid #ddd; border-radius: 4px; }
table { border-collapse: collapse; background: white; }
td, th { border: 1px solid #ddd; padding: 3px 10px; text-align: right; }
td:first-child, th:first-child { text-align: left; }
.warn { color: #a15c00; }
)";

}  // namespace

std::vector<LatencyDistribution> read_replay_latencies(const std::string& path) {
  std::ifstream f(path);
  if (!f) throw std::runtime_error("cannot read '" + path + "': " + std::strerror(errno));
  const nlohmann::json j = nlohmann::json::parse(f, nullptr, false);
  if (j.is_discarded())
    throw std::runtime_error(path + ": not JSON (expected `kestrel replay --metrics-out`)");
  if (!j.is_object() || !j.contains("latency") || !j["latency"].is_object())
    throw std::runtime_error(path + ": no \"latency\" object (expected `kestrel replay --metrics-out`)");
  std::vector<LatencyDistribution> out;
  for (const auto& item : j["latency"].items()) {
    // Not a structured binding: C++17 does not let the lambda below capture
    // one (GCC accepts it as an extension, clang refuses).
    const std::string& name = item.key();
    const nlohmann::json& h = item.value();
    const std::string where = path + ": latency." + name;
    if (!h.is_object()) throw std::runtime_error(where + ": expected an object");
    LatencyDistribution d;
    d.name = name;
    d.count = h.value("count", uint64_t{0});
    if (d.count == 0) continue;
    auto ms = [&](const char* k) {
      if (!h.contains(k) || !h[k].is_number())
        throw std::runtime_error(where + "." + k + ": expected a number");
      return h[k].get<double>();
    };
    d.p50_ms = ms("p50_ms");
    d.p90_ms = ms("p90_ms");
    d.p99_ms = ms("p99_ms");
    d.max_ms = ms("max_ms");
    if (!h.contains("bins") || !h["bins"].is_array())
      throw std::runtime_error(where + ".bins: missing (a metrics file from before the bins were exported?)");
    const auto& bins = h["bins"];
    for (size_t i = 0; i < bins.size(); ++i) {
      const auto& b = bins[i];
      if (!b.is_array() || b.size() != 3 || !b[0].is_number_integer() || !b[1].is_number_integer() ||
          !b[2].is_number_unsigned()) {
        throw std::runtime_error(where + ".bins[" + std::to_string(i) +
                                 "]: expected [lower_ns, width_ns, count]");
      }
      d.bins.push_back({b[0].get<int64_t>(), b[1].get<int64_t>(), b[2].get<uint64_t>()});
    }
    if (d.bins.empty())
      throw std::runtime_error(where + ".bins: empty while count is " + std::to_string(d.count));
    out.push_back(std::move(d));
  }
  return out;
}

void write_html_report(const std::string& path, const Trajectory& gt, const EvalResult& r,
                       const HtmlReportOptions& o) {
  std::string h = "<!doctype html>\n<html lang='en'><head><meta charset='utf-8'>\n<title>" +
                  xml_escape(o.title.empty() ? std::string("trajectory evaluation") : o.title) +
                  "</title>\n<style>" + kStyle + "</style></head><body>\n";
  h += "<h1>" + xml_escape(o.title.empty() ? std::string("Trajectory evaluation") : o.title) + "</h1>\n";
  h += "<div class='sub'>ground truth <b>" + xml_escape(r.gt_file) + "</b>, estimate <b>" +
       xml_escape(r.est_file) + "</b>; alignment " + alignment_name(r.align) +
       " (docs/evaluation.md)</div>\n";

  h += "<h2>Summary</h2>\n<table id='summary'>\n";
  h += row("ATE RMSE", cell(r.ate_m.rmse, "%.4g") + " m");
  h += row("ATE mean / median / max", cell(r.ate_m.mean, "%.4g") + " / " + cell(r.ate_m.median, "%.4g") +
                                          " / " + cell(r.ate_m.max, "%.4g") + " m");
  h += row("rotation error RMSE", cell(r.ate_rot_deg.rmse, "%.3g") + " deg");
  h += row("RPE over " + fmt("%g", r.rpe_delta_s) + " s (translation RMSE)",
           cell(r.rpe_trans_rmse_m, "%.4g") + " m");
  h += row(
      "poses matched / estimate / ground truth",
      std::to_string(r.matched) + " / " + std::to_string(r.est_poses) + " / " + std::to_string(r.gt_poses));
  h += row("coverage of the ground truth's time span", cell(100 * r.coverage, "%.1f") + " %");
  h += row("ground-truth path length / duration",
           cell(r.gt_length_m, "%.2f") + " m / " + cell(r.gt_duration_s, "%.1f") + " s");
  if (r.align == Alignment::kSim3) h += row("scale", cell(r.T_align.scale, "%.4f"));
  for (const SegmentError& s : r.segments) {
    h += row("drift over " + fmt("%g", s.length_m) + " m segments",
             s.count > 0 ? cell(s.trans_pct, "%.2f") + " % / " + cell(s.rot_deg_per_m, "%.3f") + " deg/m"
                         : std::string("&ndash; (path too short)"));
  }
  h += "</table>\n";
  for (const auto& w : r.warnings) h += "<div class='warn'>warning: " + xml_escape(w) + "</div>\n";

  h += "<h2>Trajectories after alignment</h2>\n<div class='grid'>\n";
  h += view("top-view", "top view (x-y)", gt, r, 0, 1);
  h += view("side-view", "side view (x-z)", gt, r, 0, 2);
  h += "</div>\n";

  h += "<h2>Error over time</h2>\n<div class='grid'>\n";
  h += time_plot(
      "error-time", "position error after alignment", "position error [m]", r, {{"#1f77b4", "|p error|"}},
      [&](size_t, size_t i) { return r.pos_err_m[i]; }, true);
  h += time_plot(
      "error-rotation", "rotation error after alignment", "rotation error [deg]", r, {{"#9467bd", "angle"}},
      [&](size_t, size_t i) { return r.rot_err_deg[i]; }, true);
  h += time_plot(
      "error-axes", "error per axis (estimate - ground truth, world frame)", "error [m]", r,
      {{kAxisColours[0], "x"}, {kAxisColours[1], "y"}, {kAxisColours[2], "z"}},
      [&](size_t k, size_t i) {
        return r.est_aligned[i].p[static_cast<int>(k)] - r.gt_matched[i].p[static_cast<int>(k)];
      },
      false);
  h += "</div>\n";

  std::vector<RpeStats> rpe;
  for (double d : o.rpe_deltas_s) {
    const RpeStats s = relative_pose_error(r, d, o.max_gap_ms);
    if (s.pairs > 0) rpe.push_back(s);
  }
  h += "<h2>Relative pose error over several time steps</h2>\n<div class='grid'>\n";
  h += "<table id='rpe-table'><thead><tr><th>time step [s]</th><th>pairs</th><th>translation RMSE [m]</th>"
       "<th>translation [m/s]</th><th>rotation RMSE [deg]</th></tr></thead><tbody>\n";
  for (const RpeStats& s : rpe) {
    h += "<tr><td>" + fmt("%g", s.delta_s) + "</td><td>" + std::to_string(s.pairs) + "</td><td>" +
         cell(s.trans_rmse_m, "%.4g") + "</td><td>" + cell(s.trans_m_per_s, "%.4g") + "</td><td>" +
         cell(s.rot_rmse_deg, "%.3g") + "</td></tr>\n";
  }
  h += "</tbody></table>\n";
  h += rpe.empty() ? std::string("<p>no time step fits in the associated estimate</p>\n") : rpe_plot(rpe);
  h += "</div>\n";

  if (!o.latencies.empty()) {
    h += "<h2>Latency of the run</h2>\n<div class='sub'>from " + xml_escape(o.metrics_file) +
         " (kestrel replay --metrics-out; docs/timing.md says what each one measures)</div>\n";
    h += "<div class='grid' id='latency'>\n";
    for (const LatencyDistribution& d : o.latencies) h += latency_plot(d);
    h += "</div>\n";
  }
  h += "</body></html>\n";

  svg::write_file(path, h);
}

}  // namespace kestrel::tools

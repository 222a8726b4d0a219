// Hand-written SVG: no plotting dependency, opens in any browser.
#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/tools/trajectory_eval.hpp"

namespace kestrel::tools {
namespace {

// Polylines longer than this are decimated: a browser chokes on 10^5 points and
// the eye cannot tell the difference at this size.
constexpr size_t kMaxPoints = 4000;
// A jump in time longer than this breaks a line instead of drawing a chord.
constexpr int64_t kBreakGapNs = 1'000'000'000;

struct Range {
  double lo = 0, hi = 0;
  double span() const { return hi - lo; }
};

struct Panel {
  double x0, y0, w, h;   // pixel box of the plot area
  Range xr, yr;          // data range shown
  double px(double x) const { return x0 + (x - xr.lo) / xr.span() * w; }
  double py(double y) const { return y0 + h - (y - yr.lo) / yr.span() * h; }
};

std::string xml_escape(const std::string& s) {
  std::string out;
  for (char c : s) {
    switch (c) {
      case '&': out += "&amp;"; break;
      case '<': out += "&lt;"; break;
      case '>': out += "&gt;"; break;
      case '"': out += "&quot;"; break;
      case '\'': out += "&apos;"; break;
      default:
        if (static_cast<unsigned char>(c) >= 0x20 || c == '\t') out += c;
    }
  }
  return out;
}

std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

double nice_step(double span, int target_ticks) {
  const double raw = span / std::max(1, target_ticks);
  const double mag = std::pow(10.0, std::floor(std::log10(raw)));
  const double r = raw / mag;
  return (r < 1.5 ? 1.0 : r < 3.0 ? 2.0 : r < 7.0 ? 5.0 : 10.0) * mag;
}

Range padded(double lo, double hi, double min_span) {
  if (!std::isfinite(lo) || !std::isfinite(hi) || lo > hi) return {0, 1};
  const double pad = std::max((hi - lo) * 0.05, min_span * 0.5);
  return {lo - pad, hi + pad};
}

void axes(std::string& svg, const Panel& p, const std::string& xlabel, const std::string& ylabel) {
  svg += "<rect x='" + fmt("%.1f", p.x0) + "' y='" + fmt("%.1f", p.y0) + "' width='" + fmt("%.1f", p.w) +
         "' height='" + fmt("%.1f", p.h) + "' fill='none' stroke='#444'/>\n";
  const double sx = nice_step(p.xr.span(), 6), sy = nice_step(p.yr.span(), 6);
  for (double v = std::ceil(p.xr.lo / sx) * sx; v <= p.xr.hi + 1e-12; v += sx) {
    const double x = p.px(v);
    svg += "<line x1='" + fmt("%.1f", x) + "' y1='" + fmt("%.1f", p.y0) + "' x2='" + fmt("%.1f", x) + "' y2='" +
           fmt("%.1f", p.y0 + p.h) + "' stroke='#ddd'/>\n";
    svg += "<text x='" + fmt("%.1f", x) + "' y='" + fmt("%.1f", p.y0 + p.h + 16) + "' text-anchor='middle'>" +
           fmt("%g", std::fabs(v) < sx * 1e-6 ? 0.0 : v) + "</text>\n";
  }
  for (double v = std::ceil(p.yr.lo / sy) * sy; v <= p.yr.hi + 1e-12; v += sy) {
    const double y = p.py(v);
    svg += "<line x1='" + fmt("%.1f", p.x0) + "' y1='" + fmt("%.1f", y) + "' x2='" + fmt("%.1f", p.x0 + p.w) +
           "' y2='" + fmt("%.1f", y) + "' stroke='#ddd'/>\n";
    svg += "<text x='" + fmt("%.1f", p.x0 - 6) + "' y='" + fmt("%.1f", y + 4) + "' text-anchor='end'>" +
           fmt("%g", std::fabs(v) < sy * 1e-6 ? 0.0 : v) + "</text>\n";
  }
  svg += "<text x='" + fmt("%.1f", p.x0 + p.w / 2) + "' y='" + fmt("%.1f", p.y0 + p.h + 36) +
         "' text-anchor='middle'>" + xml_escape(xlabel) + "</text>\n";
  svg += "<text transform='translate(" + fmt("%.1f", p.x0 - 48) + "," + fmt("%.1f", p.y0 + p.h / 2) +
         ") rotate(-90)' text-anchor='middle'>" + xml_escape(ylabel) + "</text>\n";
}

// One <polyline> per run of samples without a time gap.
template <typename GetX, typename GetY, typename GetT>
void polyline(std::string& svg, const Panel& p, size_t n, GetX gx, GetY gy, GetT gt, const std::string& style) {
  if (n == 0) return;
  const size_t stride = std::max<size_t>(1, (n + kMaxPoints - 1) / kMaxPoints);
  std::string pts;
  int64_t prev_t = 0;
  auto flush = [&]() {
    if (!pts.empty()) svg += "<polyline fill='none' " + style + " points='" + pts + "'/>\n";
    pts.clear();
  };
  for (size_t i = 0; i < n; i += stride) {
    const int64_t t = gt(i);
    if (!pts.empty() && t - prev_t > kBreakGapNs * static_cast<int64_t>(stride)) flush();
    pts += fmt("%.2f", p.px(gx(i))) + "," + fmt("%.2f", p.py(gy(i))) + " ";
    prev_t = t;
  }
  flush();
}

}  // namespace

void write_svg_plot(const std::string& path, const Trajectory& gt, const EvalResult& r, const std::string& title) {
  constexpr double kW = 1200, kH = 560;
  std::string svg;
  svg += "<?xml version='1.0' encoding='UTF-8'?>\n";
  svg += "<svg xmlns='http://www.w3.org/2000/svg' width='" + fmt("%.0f", kW) + "' height='" + fmt("%.0f", kH) +
         "' viewBox='0 0 " + fmt("%.0f", kW) + " " + fmt("%.0f", kH) +
         "' font-family='sans-serif' font-size='12'>\n";
  svg += "<rect width='100%' height='100%' fill='white'/>\n";
  const std::string heading = (title.empty() ? std::string("trajectory evaluation") : title) + "  (align " +
                              alignment_name(r.align) + ", ATE RMSE " + fmt("%.4g", r.ate_m.rmse) + " m, " +
                              std::to_string(r.matched) + " poses)";
  svg += "<text x='" + fmt("%.0f", kW / 2) + "' y='24' text-anchor='middle' font-size='15'>" + xml_escape(heading) +
         "</text>\n";

  // ---- left: top view, equal scale on both axes so shapes are not distorted ----
  double xlo = INFINITY, xhi = -INFINITY, ylo = INFINITY, yhi = -INFINITY;
  auto grow = [&](const Eigen::Vector3d& p) {
    if (!p.allFinite()) return;
    xlo = std::min(xlo, p.x());
    xhi = std::max(xhi, p.x());
    ylo = std::min(ylo, p.y());
    yhi = std::max(yhi, p.y());
  };
  for (const auto& p : gt) grow(p.p);
  for (const auto& p : r.est_aligned) grow(p.p);
  Panel top{80, 50, 440, 440, padded(xlo, xhi, 0.5), padded(ylo, yhi, 0.5)};
  const double per_px = std::max(top.xr.span() / top.w, top.yr.span() / top.h);
  const double cx = 0.5 * (top.xr.lo + top.xr.hi), cy = 0.5 * (top.yr.lo + top.yr.hi);
  top.xr = {cx - per_px * top.w / 2, cx + per_px * top.w / 2};
  top.yr = {cy - per_px * top.h / 2, cy + per_px * top.h / 2};
  axes(svg, top, "x [m]", "y [m]");
  svg += "<text x='" + fmt("%.1f", top.x0 + top.w / 2) + "' y='" + fmt("%.1f", top.y0 - 8) +
         "' text-anchor='middle'>top view (x-y)</text>\n";
  polyline(
      svg, top, gt.size(), [&](size_t i) { return gt[i].p.x(); }, [&](size_t i) { return gt[i].p.y(); },
      [&](size_t i) { return gt[i].t_ns; }, "stroke='#222' stroke-width='1.5'");
  const auto& E = r.est_aligned;
  polyline(
      svg, top, E.size(), [&](size_t i) { return E[i].p.x(); }, [&](size_t i) { return E[i].p.y(); },
      [&](size_t i) { return E[i].t_ns; }, "stroke='#d62728' stroke-width='1.2' stroke-opacity='0.85'");
  // Legend
  const double lx = top.x0 + 10, ly = top.y0 + 14;
  svg += "<rect x='" + fmt("%.1f", lx - 4) + "' y='" + fmt("%.1f", ly - 12) +
         "' width='190' height='42' fill='white' fill-opacity='0.85' stroke='#999'/>\n";
  svg += "<line x1='" + fmt("%.1f", lx) + "' y1='" + fmt("%.1f", ly - 4) + "' x2='" + fmt("%.1f", lx + 24) +
         "' y2='" + fmt("%.1f", ly - 4) + "' stroke='#222' stroke-width='2'/>\n";
  svg += "<text x='" + fmt("%.1f", lx + 30) + "' y='" + fmt("%.1f", ly) + "'>ground truth</text>\n";
  svg += "<line x1='" + fmt("%.1f", lx) + "' y1='" + fmt("%.1f", ly + 16) + "' x2='" + fmt("%.1f", lx + 24) +
         "' y2='" + fmt("%.1f", ly + 16) + "' stroke='#d62728' stroke-width='2'/>\n";
  svg += "<text x='" + fmt("%.1f", lx + 30) + "' y='" + fmt("%.1f", ly + 20) + "'>estimate (aligned, " +
         std::string(alignment_name(r.align)) + ")</text>\n";

  // ---- right: position error over time ----
  const int64_t t0 = E.empty() ? 0 : E.front().t_ns;
  double tmax = E.empty() ? 1.0 : static_cast<double>(E.back().t_ns - t0) * 1e-9;
  double emax = 0;
  for (double e : r.pos_err_m)
    if (std::isfinite(e)) emax = std::max(emax, e);
  if (!(tmax > 0)) tmax = 1.0;
  if (!(emax > 0)) emax = 1e-3;
  Panel err{660, 50, 500, 440, {0, tmax}, {0, emax * 1.08}};
  axes(svg, err, "time since first associated pose [s]", "position error [m]");
  svg += "<text x='" + fmt("%.1f", err.x0 + err.w / 2) + "' y='" + fmt("%.1f", err.y0 - 8) +
         "' text-anchor='middle'>position error after alignment</text>\n";
  polyline(
      svg, err, E.size(), [&](size_t i) { return static_cast<double>(E[i].t_ns - t0) * 1e-9; },
      [&](size_t i) { return r.pos_err_m[i]; }, [&](size_t i) { return E[i].t_ns; },
      "stroke='#1f77b4' stroke-width='1.2'");
  if (std::isfinite(r.ate_m.rmse)) {
    const double y = err.py(r.ate_m.rmse);
    svg += "<line x1='" + fmt("%.1f", err.x0) + "' y1='" + fmt("%.1f", y) + "' x2='" + fmt("%.1f", err.x0 + err.w) +
           "' y2='" + fmt("%.1f", y) + "' stroke='#ff7f0e' stroke-dasharray='6,4'/>\n";
    svg += "<text x='" + fmt("%.1f", err.x0 + err.w - 4) + "' y='" + fmt("%.1f", y - 5) +
           "' text-anchor='end' fill='#ff7f0e'>RMSE " + fmt("%.4g", r.ate_m.rmse) + " m</text>\n";
  }
  svg += "</svg>\n";

  std::FILE* f = std::fopen(path.c_str(), "w");
  if (f == nullptr) throw std::runtime_error("cannot write '" + path + "': " + std::strerror(errno));
  const size_t written = std::fwrite(svg.data(), 1, svg.size(), f);
  if (std::fclose(f) != 0 || written != svg.size())
    throw std::runtime_error("error writing '" + path + "': " + std::strerror(errno));
}

}  // namespace kestrel::tools

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
#include "svg_plot.hpp"

namespace kestrel::tools {
namespace {

using svg::axes;
using svg::fmt;
using svg::padded;
using svg::Panel;
using svg::polyline;
using svg::xml_escape;

}  // namespace

void write_svg_plot(const std::string& path, const Trajectory& gt, const EvalResult& r,
                    const std::string& title) {
  constexpr double kW = 1200, kH = 560;
  std::string svg;
  svg += "<?xml version='1.0' encoding='UTF-8'?>\n";
  svg += "<svg xmlns='http://www.w3.org/2000/svg' width='" + fmt("%.0f", kW) + "' height='" +
         fmt("%.0f", kH) + "' viewBox='0 0 " + fmt("%.0f", kW) + " " + fmt("%.0f", kH) +
         "' font-family='sans-serif' font-size='12'>\n";
  svg += "<rect width='100%' height='100%' fill='white'/>\n";
  const std::string heading = (title.empty() ? std::string("trajectory evaluation") : title) + "  (align " +
                              alignment_name(r.align) + ", ATE RMSE " + fmt("%.4g", r.ate_m.rmse) + " m, " +
                              std::to_string(r.matched) + " poses)";
  svg += "<text x='" + fmt("%.0f", kW / 2) + "' y='24' text-anchor='middle' font-size='15'>" +
         xml_escape(heading) + "</text>\n";

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
  svg::equal_aspect(top);
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
  svg::legend(svg, top.x0 + 10, top.y0 + 14,
              {{"#222", "ground truth"},
               {"#d62728", std::string("estimate (aligned, ") + alignment_name(r.align) + ")"}});

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
    svg += "<line x1='" + fmt("%.1f", err.x0) + "' y1='" + fmt("%.1f", y) + "' x2='" +
           fmt("%.1f", err.x0 + err.w) + "' y2='" + fmt("%.1f", y) +
           "' stroke='#ff7f0e' stroke-dasharray='6,4'/>\n";
    svg += "<text x='" + fmt("%.1f", err.x0 + err.w - 4) + "' y='" + fmt("%.1f", y - 5) +
           "' text-anchor='end' fill='#ff7f0e'>RMSE " + fmt("%.4g", r.ate_m.rmse) + " m</text>\n";
  }
  svg += "</svg>\n";

  svg::write_file(path, svg);
}

}  // namespace kestrel::tools

// Hand-written SVG pieces shared by the SVG plot (eval_plot.cpp) and the
// HTML report (eval_html.cpp): no plotting dependency, and the output opens
// in any browser with no network. Private to tools/eval.
#pragma once

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace kestrel::tools::svg {

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
  double x0{}, y0{}, w{}, h{};  // pixel box of the plot area
  Range xr, yr;                 // data range shown
  double px(double x) const { return x0 + (x - xr.lo) / xr.span() * w; }
  double py(double y) const { return y0 + h - (y - yr.lo) / yr.span() * h; }
};

inline std::string xml_escape(const std::string& s) {
  std::string out;
  for (char c : s) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      case '\'':
        out += "&apos;";
        break;
      default:
        if (static_cast<unsigned char>(c) >= 0x20 || c == '\t') out += c;
    }
  }
  return out;
}

inline std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

inline double nice_step(double span, int target_ticks) {
  const double raw = span / std::max(1, target_ticks);
  const double mag = std::pow(10.0, std::floor(std::log10(raw)));
  const double r = raw / mag;
  return (r < 1.5 ? 1.0 : r < 3.0 ? 2.0 : r < 7.0 ? 5.0 : 10.0) * mag;
}

inline Range padded(double lo, double hi, double min_span) {
  if (!std::isfinite(lo) || !std::isfinite(hi) || lo > hi) return {0, 1};
  const double pad = std::max((hi - lo) * 0.05, min_span * 0.5);
  return {lo - pad, hi + pad};
}

// Tick positions of one axis over [lo, hi]: even steps, or for a log axis
// (the range in log10 units) the 1-2-5 values of each decade (decades only
// when the range spans more than four). Each tick: (position, label value).
inline std::vector<std::pair<double, double>> ticks(double lo, double hi, bool log_axis) {
  std::vector<std::pair<double, double>> t;
  if (!log_axis) {
    const double step = nice_step(hi - lo, 6);
    for (double v = std::ceil(lo / step) * step; v <= hi + 1e-12; v += step)
      t.emplace_back(v, std::fabs(v) < step * 1e-6 ? 0.0 : v);
    return t;
  }
  const bool decades_only = hi - lo > 4;
  for (int k = static_cast<int>(std::floor(lo)); k <= static_cast<int>(std::ceil(hi)); ++k) {
    for (double m : {1.0, 2.0, 5.0}) {
      if (decades_only && m != 1.0) continue;
      const double v = m * std::pow(10.0, k), pos = std::log10(v);
      if (pos >= lo - 1e-9 && pos <= hi + 1e-9) t.emplace_back(pos, v);
    }
  }
  return t;
}

// Frame, grid, tick labels and axis labels of a panel. A log axis takes its
// data as log10 values and labels the ticks with the values themselves.
inline void axes(std::string& svg, const Panel& p, const std::string& xlabel, const std::string& ylabel,
                 bool log_x = false, bool log_y = false) {
  svg += "<rect x='" + fmt("%.1f", p.x0) + "' y='" + fmt("%.1f", p.y0) + "' width='" + fmt("%.1f", p.w) +
         "' height='" + fmt("%.1f", p.h) + "' fill='none' stroke='#444'/>\n";
  for (const auto& [pos, v] : ticks(p.xr.lo, p.xr.hi, log_x)) {
    const double x = p.px(pos);
    svg += "<line x1='" + fmt("%.1f", x) + "' y1='" + fmt("%.1f", p.y0) + "' x2='" + fmt("%.1f", x) +
           "' y2='" + fmt("%.1f", p.y0 + p.h) + "' stroke='#ddd'/>\n";
    svg += "<text x='" + fmt("%.1f", x) + "' y='" + fmt("%.1f", p.y0 + p.h + 16) + "' text-anchor='middle'>" +
           fmt("%g", v) + "</text>\n";
  }
  for (const auto& [pos, v] : ticks(p.yr.lo, p.yr.hi, log_y)) {
    const double y = p.py(pos);
    svg += "<line x1='" + fmt("%.1f", p.x0) + "' y1='" + fmt("%.1f", y) + "' x2='" + fmt("%.1f", p.x0 + p.w) +
           "' y2='" + fmt("%.1f", y) + "' stroke='#ddd'/>\n";
    svg += "<text x='" + fmt("%.1f", p.x0 - 6) + "' y='" + fmt("%.1f", y + 4) + "' text-anchor='end'>" +
           fmt("%g", v) + "</text>\n";
  }
  svg += "<text x='" + fmt("%.1f", p.x0 + p.w / 2) + "' y='" + fmt("%.1f", p.y0 + p.h + 36) +
         "' text-anchor='middle'>" + xml_escape(xlabel) + "</text>\n";
  svg += "<text transform='translate(" + fmt("%.1f", p.x0 - 48) + "," + fmt("%.1f", p.y0 + p.h / 2) +
         ") rotate(-90)' text-anchor='middle'>" + xml_escape(ylabel) + "</text>\n";
}

// One <polyline> per run of samples without a time gap.
template <typename GetX, typename GetY, typename GetT>
void polyline(std::string& svg, const Panel& p, size_t n, GetX gx, GetY gy, GetT gt,
              const std::string& style) {
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

// Widens the panel's smaller range so one metre spans as many pixels on both
// axes: a trajectory's shape is not distorted.
inline void equal_aspect(Panel& p) {
  const double per_px = std::max(p.xr.span() / p.w, p.yr.span() / p.h);
  const double cx = 0.5 * (p.xr.lo + p.xr.hi), cy = 0.5 * (p.yr.lo + p.yr.hi);
  p.xr = {cx - per_px * p.w / 2, cx + per_px * p.w / 2};
  p.yr = {cy - per_px * p.h / 2, cy + per_px * p.h / 2};
}

// A boxed legend at (x, y): one line per (colour, label).
inline void legend(std::string& svg, double x, double y,
                   const std::vector<std::pair<std::string, std::string>>& items, double width = 190) {
  svg += "<rect x='" + fmt("%.1f", x - 4) + "' y='" + fmt("%.1f", y - 12) + "' width='" + fmt("%.0f", width) +
         "' height='" + fmt("%.0f", 10 + 20.0 * static_cast<double>(items.size())) +
         "' fill='white' fill-opacity='0.85' stroke='#999'/>\n";
  for (size_t i = 0; i < items.size(); ++i) {
    const double yy = y + 20.0 * static_cast<double>(i);
    svg += "<line x1='" + fmt("%.1f", x) + "' y1='" + fmt("%.1f", yy - 4) + "' x2='" + fmt("%.1f", x + 24) +
           "' y2='" + fmt("%.1f", yy - 4) + "' stroke='" + items[i].first + "' stroke-width='2'/>\n";
    svg += "<text x='" + fmt("%.1f", x + 30) + "' y='" + fmt("%.1f", yy) + "'>" +
           xml_escape(items[i].second) + "</text>\n";
  }
}

// Writes a finished page; throws std::runtime_error naming the path.
inline void write_file(const std::string& path, const std::string& text) {
  std::FILE* f = std::fopen(path.c_str(), "w");
  if (f == nullptr) throw std::runtime_error("cannot write '" + path + "': " + std::strerror(errno));
  const size_t written = std::fwrite(text.data(), 1, text.size(), f);
  if (std::fclose(f) != 0 || written != text.size())
    throw std::runtime_error("error writing '" + path + "': " + std::strerror(errno));
}

}  // namespace kestrel::tools::svg

// Text and JSON renderings of an EvalResult. Both come from one ordered field
// list so their keys can never drift apart. Also the JSON conventions every
// report of the tools shares (report_json.hpp).
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "kestrel/tools/report_json.hpp"
#include "kestrel/tools/trajectory_eval.hpp"

namespace kestrel::tools {
namespace {

struct Field {
  enum Kind { kNumber, kInteger, kString } kind;
  std::string key;
  double number = 0;
  long long integer = 0;
  std::string text;
};

Field num(std::string key, double v) { return Field{Field::kNumber, std::move(key), v, 0, {}}; }
Field integer(std::string key, long long v) { return Field{Field::kInteger, std::move(key), 0, v, {}}; }
Field str(std::string key, std::string v) {
  return Field{Field::kString, std::move(key), 0, 0, std::move(v)};
}

std::string format_length(double L) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", L);
  return buf;
}

std::vector<Field> fields(const EvalResult& r) {
  std::vector<Field> f;
  f.push_back(num("ate_rmse_m", r.ate_m.rmse));  // first, always: scripts read line 1
  f.push_back(num("ate_mean_m", r.ate_m.mean));
  f.push_back(num("ate_median_m", r.ate_m.median));
  f.push_back(num("ate_std_m", r.ate_m.std));
  f.push_back(num("ate_min_m", r.ate_m.min));
  f.push_back(num("ate_max_m", r.ate_m.max));
  f.push_back(num("ate_rot_rmse_deg", r.ate_rot_deg.rmse));
  f.push_back(num("ate_rot_mean_deg", r.ate_rot_deg.mean));
  f.push_back(num("ate_rot_max_deg", r.ate_rot_deg.max));
  f.push_back(num("rot_gain_x", r.rot_gain.x()));
  f.push_back(num("rot_gain_y", r.rot_gain.y()));
  f.push_back(num("rot_gain_z", r.rot_gain.z()));
  f.push_back(num("rpe_delta_s", r.rpe_delta_s));
  f.push_back(integer("rpe_pairs", r.rpe_pairs));
  f.push_back(num("rpe_trans_rmse_m", r.rpe_trans_rmse_m));
  f.push_back(num("rpe_trans_mean_m", r.rpe_trans_mean_m));
  f.push_back(num("rpe_trans_m_per_s", r.rpe_trans_m_per_s));
  f.push_back(num("rpe_rot_rmse_deg", r.rpe_rot_rmse_deg));
  f.push_back(num("rpe_rot_mean_deg", r.rpe_rot_mean_deg));
  double sum_t = 0, sum_r = 0;
  int used = 0;
  for (const SegmentError& s : r.segments) {
    const std::string k = "kitti_" + format_length(s.length_m) + "m_";
    f.push_back(integer(k + "count", s.count));
    f.push_back(num(k + "trans_pct", s.trans_pct));
    f.push_back(num(k + "rot_deg_per_m", s.rot_deg_per_m));
    if (s.count > 0) {
      sum_t += s.trans_pct;
      sum_r += s.rot_deg_per_m;
      ++used;
    }
  }
  const double nan = std::nan("");
  f.push_back(num("kitti_trans_pct", used > 0 ? sum_t / used : nan));
  f.push_back(num("kitti_rot_deg_per_m", used > 0 ? sum_r / used : nan));
  f.push_back(integer("matched", r.matched));
  f.push_back(integer("interpolated", r.interpolated));
  f.push_back(integer("unmatched", r.unmatched));
  f.push_back(integer("gt_poses", r.gt_poses));
  f.push_back(integer("est_poses", r.est_poses));
  f.push_back(num("coverage", r.coverage));
  f.push_back(num("gt_duration_s", r.gt_duration_s));
  f.push_back(num("gt_length_m", r.gt_length_m));
  f.push_back(str("align", alignment_name(r.align)));
  f.push_back(num("scale", r.T_align.scale));
  f.push_back(num("align_rot_deg", Eigen::AngleAxisd(r.T_align.R).angle() * 180.0 / M_PI));
  f.push_back(num("align_trans_m", r.T_align.t.norm()));
  f.push_back(str("gt_file", r.gt_file));
  f.push_back(str("est_file", r.est_file));
  f.push_back(integer("warnings", static_cast<long long>(r.warnings.size())));
  return f;
}

std::string format_number(double v) {
  if (!std::isfinite(v)) return "nan";
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.10g", v);
  return buf;
}

}  // namespace

std::string to_text(const EvalResult& r) {
  std::string out;
  for (const Field& f : fields(r)) {
    out += f.key + ": ";
    switch (f.kind) {
      case Field::kNumber:
        out += format_number(f.number);
        break;
      case Field::kInteger:
        out += std::to_string(f.integer);
        break;
      case Field::kString: {
        // One line per key, whatever the value holds.
        for (char c : f.text) out += (c == '\n' || c == '\r') ? ' ' : c;
        break;
      }
    }
    out += '\n';
  }
  return out;
}

std::string to_json(const EvalResult& r) {
  Json j = Json::object();
  for (const Field& f : fields(r)) {
    switch (f.kind) {
      case Field::kNumber:
        j[f.key] = json_figure(f.number);
        break;
      case Field::kInteger:
        j[f.key] = f.integer;
        break;
      case Field::kString:
        j[f.key] = f.text;
        break;
    }
  }
  return json_text(j);
}

Json json_figure(double v) {
  if (!std::isfinite(v)) return nullptr;
  // Through the decimal text: the double nearest the 10-digit figure, which
  // the serializer then prints in its shortest form (those same digits).
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.10g", v);
  return std::strtod(buf, nullptr);
}

std::string json_text(const Json& j) { return j.dump(2, ' ', false, Json::error_handler_t::replace) + "\n"; }

}  // namespace kestrel::tools

#include "kestrel/dense/dense_config.hpp"

#include <yaml-cpp/yaml.h>

#include <sstream>
#include <stdexcept>

namespace kestrel::dense {

namespace {
// One table for reading and printing, so a key cannot be read but not listed.
template <class Fn>
void visit(DenseOptions& o, Fn&& fn) {
  fn("enabled", o.enabled);
  fn("voxel_size_m", o.tsdf.voxel_size_m);
  fn("memory_budget_mb", o.tsdf.memory_budget_mb);
  fn("truncation_voxels", o.tsdf.truncation_voxels);
  fn("max_depth_m", o.tsdf.max_depth_m);
  fn("pixel_stride", o.tsdf.pixel_stride);
  fn("carve_stride", o.tsdf.carve_stride);
  fn("weight_reference_depth_m", o.tsdf.weight_reference_depth_m);
  fn("max_weight", o.tsdf.max_weight);
  fn("min_weight", o.tsdf.min_weight);
  fn("evict_distance_m", o.tsdf.evict_distance_m);
  fn("keyframe_distance_m", o.keyframe_distance_m);
  fn("keyframe_angle_deg", o.keyframe_angle_deg);
  fn("keyframe_interval_s", o.keyframe_interval_s);
  fn("handoff_slots", o.handoff_slots);
  fn("archive_budget_mb", o.archive.budget_mb);
  fn("archive_stride_px", o.archive.stride_px);
  fn("live_reanchor", o.live_reanchor);
  fn("reanchor_min_shift_m", o.reanchor_min_shift_m);
  fn("reanchor_min_angle_deg", o.reanchor_min_angle_deg);
  fn("reanchor_cpu_s_per_s", o.reanchor_cpu_s_per_s);
  fn("reanchor_burst_cpu_s", o.reanchor_burst_cpu_s);
}
}  // namespace

DenseOptions dense_options_from_node(const YAML::Node& d, const std::string& where) {
  DenseOptions o;
  if (!d.IsDefined() || d.IsNull()) return o;
  if (!d.IsMap()) throw std::runtime_error(where + ": dense: expected a mapping of keys");
  std::string keys;
  visit(o, [&](const char* k, auto&) { keys += keys.empty() ? k : std::string(", ") + k; });
  for (const auto& kv : d) {
    bool known = false;
    visit(o, [&](const char* k, auto&) { known = known || kv.first.Scalar() == k; });
    if (!known) {
      throw std::runtime_error(where + ":" + std::to_string(kv.first.Mark().line + 1) + ": dense." +
                               kv.first.Scalar() + ": unknown key (expected one of: " + keys + ")");
    }
  }
  visit(o, [&](const char* k, auto& v) {
    if (!d[k]) return;
    try {
      v = d[k].as<std::decay_t<decltype(v)>>();
    } catch (const YAML::Exception&) {
      throw std::runtime_error(where + ":" + std::to_string(d[k].Mark().line + 1) + ": dense." + k +
                               ": bad value '" + d[k].Scalar() + "'");
    }
  });
  try {
    o.validate();
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(where + ": " + e.what());
  }
  return o;
}

namespace {
YAML::Node parse_document(const std::string& text, const std::string& where) {
  try {
    return YAML::Load(text);
  } catch (const YAML::ParserException& e) {
    throw std::runtime_error(where + ":" + std::to_string(e.mark.line + 1) + ": YAML syntax error: " + e.msg);
  }
}
}  // namespace

DenseOptions dense_options_from_yaml(const std::string& text, const std::string& where) {
  const YAML::Node root = parse_document(text, where);
  return root.IsMap() ? dense_options_from_node(root["dense"], where) : DenseOptions{};
}

std::vector<std::pair<std::string, std::string>> dense_options_table(const DenseOptions& in) {
  DenseOptions o = in;
  std::vector<std::pair<std::string, std::string>> out;
  visit(o, [&](const char* k, auto& v) {
    std::ostringstream s;
    if constexpr (std::is_same_v<std::decay_t<decltype(v)>, bool>) {
      s << (v ? "true" : "false");
    } else {
      s << v;
    }
    out.emplace_back(std::string("dense.") + k, s.str());
  });
  return out;
}

DenseViewOptions dense_view_options_from_node(const YAML::Node& v, const std::string& where) {
  DenseViewOptions o;
  if (!v.IsDefined() || v.IsNull()) return o;
  if (!v.IsMap()) throw std::runtime_error(where + ": viewer: expected a mapping of keys");
  for (const auto& kv : v) {
    if (kv.first.Scalar() != "dense_max_kbps" && kv.first.Scalar() != "dense_period_s") {
      throw std::runtime_error(where + ":" + std::to_string(kv.first.Mark().line + 1) + ": viewer." +
                               kv.first.Scalar() +
                               ": unknown key (expected one of: dense_max_kbps, dense_period_s)");
    }
  }
  for (auto [key, value] : {std::pair<const char*, double*>{"dense_max_kbps", &o.max_kbps},
                            std::pair<const char*, double*>{"dense_period_s", &o.period_s}}) {
    const YAML::Node k = v[key];
    if (!k) continue;
    try {
      *value = k.as<double>();
    } catch (const YAML::Exception&) {
      throw std::runtime_error(where + ":" + std::to_string(k.Mark().line + 1) + ": viewer." + key +
                               ": bad value '" + k.Scalar() + "'");
    }
  }
  try {
    o.validate();
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(where + ": " + e.what());
  }
  return o;
}

DenseViewOptions dense_view_options_from_yaml(const std::string& text, const std::string& where) {
  const YAML::Node root = parse_document(text, where);
  return root.IsMap() ? dense_view_options_from_node(root["viewer"], where) : DenseViewOptions{};
}

std::string dense_sections_yaml(const DenseOptions& o, const DenseViewOptions& v) {
  std::ostringstream s;
  s << "dense:\n";
  for (const auto& [k, value] : dense_options_table(o)) s << "  " << k.substr(6) << ": " << value << "\n";
  s << "viewer:\n  dense_max_kbps: " << v.max_kbps << "\n  dense_period_s: " << v.period_s << "\n";
  return s.str();
}

}  // namespace kestrel::dense

#include "kestrel/tools/estimator_config_yaml.hpp"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <limits>
#include <optional>
#include <set>
#include <sstream>
#include <stdexcept>

#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/drivers/text.hpp"
#include "kestrel/tools/vocabulary_files.hpp"

namespace kestrel::tools {

namespace {

// Shortest text that reads back to the same value (a float as a float:
// 0.85f prints 0.85, not 0.8500000238418579).
template <typename F>
std::string num(F v) {
  if (std::isnan(v)) return ".nan";
  if (std::isinf(v)) return v > 0 ? ".inf" : "-.inf";
  char buf[64];
  const auto r = std::to_chars(buf, buf + sizeof buf, v);
  std::string s(buf, r.ptr);
  if (s.find_first_of(".e") == std::string::npos) s += ".0";
  return s;
}

// A string as YAML that reads back to the same string: bare when it is a
// plain word or path (what every default is, so the printed config and
// docs/config.md stay unquoted), else double-quoted with escapes. Bare text
// with ": ", " #" or a leading indicator would change the document's
// structure (found by fuzzing); an empty string bare would read back as null.
std::string yaml_string(const std::string& v) {
  bool plain = !v.empty() && (std::isalnum(static_cast<unsigned char>(v[0])) || v[0] == '/' || v[0] == '_');
  for (const char ch : v) {
    if (!std::isalnum(static_cast<unsigned char>(ch)) && std::string("_./+-").find(ch) == std::string::npos)
      plain = false;
  }
  if (plain) return v;
  YAML::Emitter e;
  e << YAML::DoubleQuoted << v;
  return e.c_str();
}

// Walks the table and calls one function per key with its dotted path: the
// base of every visitor below except the loader.
class PathVisitor : public core::OptionVisitor {
 public:
  void begin_section(const char* name, const char* doc) override {
    path_.push_back(name);
    section(name, doc);
  }
  void end_section() override {
    path_.pop_back();
    section_end();
  }
  void value(const char* k, double& v, const char* d) override { key(k, num(v), d); }
  void value(const char* k, float& v, const char* d) override { key(k, num(v), d); }
  void value(const char* k, int& v, const char* d) override { key(k, std::to_string(v), d); }
  void value(const char* k, int64_t& v, const char* d) override { key(k, std::to_string(v), d); }
  void value(const char* k, uint64_t& v, const char* d) override { key(k, std::to_string(v), d); }
  void value(const char* k, bool& v, const char* d) override { key(k, v ? "true" : "false", d); }
  void value(const char* k, std::string& v, const char* d) override { key(k, yaml_string(v), d); }
  void choice(const char* k, int& i, const std::vector<const char*>& names, const char* d) override {
    std::string doc = d;
    doc += " (";
    for (size_t n = 0; n < names.size(); ++n) doc += (n ? " | " : "") + std::string(names[n]);
    doc += ")";
    key(k, names.at(static_cast<size_t>(i)), doc.c_str());
  }

 protected:
  virtual void section(const char*, const char*) {}
  virtual void section_end() {}
  virtual void key(const char* k, const std::string& value, const char* doc) = 0;
  std::string dotted(const char* k) const {
    std::string s;
    for (const std::string& p : path_) s += p + ".";
    return s + k;
  }
  size_t depth() const { return path_.size(); }

 private:
  std::vector<std::string> path_;
};

class YamlPrinter final : public PathVisitor {
 public:
  std::ostringstream out;

 private:
  void section(const char* name, const char* doc) override {
    const std::string ind(2 * (depth() - 1), ' ');
    if (depth() == 1) out << "\n";
    out << ind << "# " << doc << "\n" << ind << name << ":\n";
  }
  void key(const char* k, const std::string& value, const char* doc) override {
    out << std::string(2 * depth(), ' ') << k << ": " << value << "  # " << doc << "\n";
  }
};

class EntryCollector final : public PathVisitor {
 public:
  std::vector<std::pair<std::string, std::string>> entries;

 private:
  void key(const char* k, const std::string& value, const char*) override {
    entries.emplace_back(dotted(k), value);
  }
};

class MarkdownTable final : public PathVisitor {
 public:
  std::ostringstream out;

 private:
  void section(const char* name, const char* doc) override {
    (void)name;
    out << "\n### `" << current() << "`\n" << doc << "\n\n| key | default | what |\n|---|---|---|\n";
  }
  void section_end() override {}
  void key(const char* k, const std::string& value, const char* doc) override {
    out << "| `" << k << "` | `" << value << "` | " << doc << " |\n";
  }
  std::string current() const {
    std::string d = dotted("");
    return d.empty() ? d : d.substr(0, d.size() - 1);
  }
};

// Applies a YAML document onto the table. Every mapping the table has a
// section for is checked for keys the table does not have.
class YamlLoader final : public core::OptionVisitor {
 public:
  YamlLoader(const YAML::Node& root, std::string where) : where_(std::move(where)) { nodes_.push_back(root); }

  void begin_section(const char* name, const char* /*doc*/) override {
    if (!seen_.empty()) seen_.back().insert(name);  // a nested section is a key of its parent
    path_.push_back(name);
    const YAML::Node& parent = nodes_.back();
    // const access: operator[] on a non-const node would insert the key.
    const YAML::Node n = parent.IsMap() ? static_cast<const YAML::Node&>(parent)[name] : YAML::Node();
    if (n.IsDefined() && !n.IsNull() && !n.IsMap()) fail(n, "", "expected a mapping of keys");
    nodes_.push_back(n.IsDefined() && n.IsMap() ? n : YAML::Node());
    seen_.emplace_back();
  }
  void end_section() override {
    const YAML::Node n = nodes_.back();
    const std::set<std::string> seen = seen_.back();
    if (n.IsMap()) {
      for (const auto& kv : n) {
        const std::string k = kv.first.Scalar();
        if (!seen.count(k)) {
          std::string list;
          for (const std::string& s : seen) list += (list.empty() ? "" : ", ") + s;
          fail(kv.first, k, "unknown key (expected one of: " + list + ")");
        }
      }
    }
    nodes_.pop_back();
    seen_.pop_back();
    path_.pop_back();
  }
  void value(const char* k, double& v, const char*) override {
    if (const auto n = get(k)) v = as_double(*n, k);
  }
  void value(const char* k, float& v, const char*) override {
    if (const auto o = get(k)) {
      const YAML::Node& n = *o;
      const double d = as_double(n, k);
      if (std::isfinite(d) && std::fabs(d) > std::numeric_limits<float>::max())
        fail(n, k, "out of float range");
      v = static_cast<float>(d);
    }
  }
  void value(const char* k, int& v, const char*) override {
    if (const auto o = get(k)) {
      const YAML::Node& n = *o;
      const int64_t i = as_int(n, k);
      if (i < std::numeric_limits<int>::min() || i > std::numeric_limits<int>::max())
        fail(n, k, "out of range");
      v = static_cast<int>(i);
    }
  }
  void value(const char* k, int64_t& v, const char*) override {
    if (const auto n = get(k)) v = as_int(*n, k);
  }
  void value(const char* k, uint64_t& v, const char*) override {
    if (const auto o = get(k)) {
      const YAML::Node& n = *o;
      const std::string& s = n.Scalar();
      uint64_t x = 0;
      const auto r = std::from_chars(s.data(), s.data() + s.size(), x);
      if (r.ec != std::errc() || r.ptr != s.data() + s.size()) fail(n, k, "expected an unsigned integer");
      v = x;
    }
  }
  void value(const char* k, bool& v, const char*) override {
    if (const auto o = get(k)) {
      const YAML::Node& n = *o;
      const std::string& s = n.Scalar();
      if (s == "true" || s == "on" || s == "yes") {
        v = true;
      } else if (s == "false" || s == "off" || s == "no") {
        v = false;
      } else {
        fail(n, k, "expected true or false");
      }
    }
  }
  void value(const char* k, std::string& v, const char*) override {
    if (const auto o = get(k)) {
      const YAML::Node& n = *o;
      // Empty is a value only where it is the default (a file name meaning "the built-in one").
      if (n.Scalar().empty() && !v.empty()) fail(n, k, "expected a non-empty name");
      // Names and paths: a control character or a byte that is not UTF-8 is
      // a damaged file, and could not be printed back as the same text.
      if (!drivers::text::is_utf8(n.Scalar()) ||
          std::any_of(n.Scalar().begin(), n.Scalar().end(),
                      [](char ch) { return static_cast<unsigned char>(ch) < 0x20; }))
        fail(n, k, "expected printable UTF-8 text");
      v = n.Scalar();
    }
  }
  void choice(const char* k, int& i, const std::vector<const char*>& names, const char*) override {
    if (const auto o = get(k)) {
      const YAML::Node& n = *o;
      std::string list;
      for (size_t j = 0; j < names.size(); ++j) {
        if (n.Scalar() == names[j]) {
          i = static_cast<int>(j);
          return;
        }
        list += (j ? ", " : "") + std::string(names[j]);
      }
      fail(n, k, "expected one of " + list);
    }
  }

 private:
  // The key's scalar node, or nothing when the key is absent (a default
  // YAML::Node is a defined null, so absence needs its own flag).
  std::optional<YAML::Node> get(const char* k) {
    seen_.back().insert(k);
    const YAML::Node& n = nodes_.back();
    if (!n.IsMap()) return std::nullopt;
    const YAML::Node v = n[k];
    if (!v.IsDefined()) return std::nullopt;
    if (!v.IsScalar()) fail(v, k, "expected a single value");
    return v;
  }
  double as_double(const YAML::Node& n, const char* k) {
    const std::string& s = n.Scalar();
    // YAML spells the non-finite numbers .nan / .inf; strtod spells them nan / inf.
    for (const char* nf :
         {".nan", ".NaN", ".NAN", ".inf", ".Inf", ".INF", "-.inf", "-.Inf", "-.INF", "+.inf"})
      if (s == nf) fail(n, k, "expected a finite number");
    char* end = nullptr;
    const double d = std::strtod(s.c_str(), &end);
    if (s.empty() || end != s.c_str() + s.size()) fail(n, k, "expected a number");
    if (!std::isfinite(d)) fail(n, k, "expected a finite number");
    return d;
  }
  int64_t as_int(const YAML::Node& n, const char* k) {
    const std::string& s = n.Scalar();
    int64_t x = 0;
    const char* b = s.data();
    if (!s.empty() && s[0] == '+') ++b;
    const auto r = std::from_chars(b, s.data() + s.size(), x);
    if (s.empty() || r.ec != std::errc() || r.ptr != s.data() + s.size()) fail(n, k, "expected an integer");
    return x;
  }
  [[noreturn]] void fail(const YAML::Node& n, const std::string& k, const std::string& what) const {
    std::string key;
    for (const std::string& p : path_) key += (key.empty() ? "" : ".") + p;
    if (!k.empty()) key += "." + k;
    const YAML::Mark m = n.Mark();
    const std::string line = m.is_null() ? "" : ":" + std::to_string(m.line + 1);
    throw std::runtime_error(where_ + line + ": " + key + ": " + what);
  }

  std::string where_;
  std::vector<YAML::Node> nodes_;
  std::vector<std::set<std::string>> seen_;
  std::vector<std::string> path_;
};

std::string scalar_at(const YAML::Node& root, const char* section, const char* key) {
  if (!root.IsMap() || !root[section] || !root[section].IsMap()) return "";
  const YAML::Node n = root[section][key];
  return n && n.IsScalar() ? n.Scalar() : "";
}

}  // namespace

std::vector<std::string> estimator_config_sections() {
  struct Top final : core::OptionVisitor {
    std::vector<std::string> names;
    int depth = 0;
    void begin_section(const char* n, const char*) override {
      if (depth++ == 0) names.emplace_back(n);
    }
    void end_section() override { --depth; }
    void value(const char*, double&, const char*) override {}
    void value(const char*, float&, const char*) override {}
    void value(const char*, int&, const char*) override {}
    void value(const char*, int64_t&, const char*) override {}
    void value(const char*, uint64_t&, const char*) override {}
    void value(const char*, bool&, const char*) override {}
    void value(const char*, std::string&, const char*) override {}
    void choice(const char*, int&, const std::vector<const char*>&, const char*) override {}
  } top;
  core::EstimatorConfig c;
  core::visit_options(c, top);
  return top.names;
}

core::EstimatorConfig estimator_config_from_node(const YAML::Node& document, const std::string& where,
                                                 const std::string& backend_override) {
  YAML::Node root = document;
  if (!root.IsDefined() || root.IsNull()) root = YAML::Node(YAML::NodeType::Map);
  if (!root.IsMap()) throw std::runtime_error(where + ": expected a mapping of sections");
  // The two keys that select defaults come first, then everything on top.
  std::string backend = scalar_at(root, "estimator", "backend");
  if (backend.empty()) backend = "auto";
  if (!backend_override.empty()) backend = backend_override;
  const std::string variant = scalar_at(root, "frontend", "lonsc_variant");
  if (!variant.empty() && variant != "tuned" && variant != "paper")
    throw std::runtime_error(where + ": frontend.lonsc_variant: expected one of tuned, paper");
  if (!core::estimator_known(backend)) {
    throw std::runtime_error(where + ": estimator.backend: unknown backend '" + backend +
                             "' (expected one of: " + core::estimator_names() + ")");
  }
  core::EstimatorConfig c = core::EstimatorConfig::defaults(
      backend, variant == "paper" ? core::LonscVariant::kPaper : core::LonscVariant::kTuned);
  YamlLoader loader(root, where);
  core::visit_options(c, loader);
  if (!backend_override.empty()) c.backend = backend_override;
  const std::string err = core::validate(c);
  if (!err.empty()) throw std::runtime_error(where + ": " + err);
  return c;
}

YAML::Node yaml_document(const std::string& text, const std::string& where) {
  try {
    return YAML::Load(text);
  } catch (const YAML::ParserException& e) {
    throw std::runtime_error(where + ":" + std::to_string(e.mark.line + 1) + ": YAML syntax error: " + e.msg);
  }
}

core::EstimatorConfig estimator_config_from_yaml(const std::string& text, const std::string& where,
                                                 const std::string& backend_override) {
  return estimator_config_from_node(yaml_document(text, where), where, backend_override);
}

std::string estimator_config_to_yaml(const core::EstimatorConfig& c) {
  core::EstimatorConfig copy = c;
  YamlPrinter p;
  p.out << "# Kestrel estimator settings (docs/config.md). Units are in the key names.\n";
  core::visit_options(copy, p);
  return p.out.str();
}

std::vector<std::pair<std::string, std::string>> estimator_config_entries(const core::EstimatorConfig& c) {
  core::EstimatorConfig copy = c;
  EntryCollector e;
  core::visit_options(copy, e);
  return e.entries;
}

std::string estimator_config_reference_markdown() {
  core::EstimatorConfig c = core::EstimatorConfig::defaults("auto");
  MarkdownTable m;
  core::visit_options(c, m);
  return m.out.str();
}

void apply_map_switches(core::EstimatorConfig& c, const std::string& mapping, const std::string& loop) {
  auto parse = [](const std::string& v, const char* opt) {
    if (v == "on") return true;
    if (v == "off") return false;
    throw std::invalid_argument(std::string(opt) + " '" + v + "': expected on or off");
  };
  if (!mapping.empty()) c.window.map.mapping = c.ekf.mapping = parse(mapping, "--mapping");
  if (!loop.empty()) c.window.map.loop = parse(loop, "--loop");
  if (loop == "on" && !c.window.map.mapping)
    throw std::invalid_argument("--loop on needs the map (--mapping on)");
  resolve_vocabulary(c);
}

}  // namespace kestrel::tools

// The config's `dense:` section (docs/dense.md lists every key, its unit and
// default). Unknown keys and bad values are errors naming the file and key.
#pragma once

#include <yaml-cpp/node/node.h>

#include <string>
#include <utility>
#include <vector>

#include "kestrel/dense/dense_mapper.hpp"
#include "kestrel/dense/dense_view.hpp"

namespace kestrel::dense {

// The `dense:` section's node (absent: the defaults, enabled = false). `where`
// names the file in errors. A config file is read by tools::load_config,
// which hands this section here.
DenseOptions dense_options_from_node(const YAML::Node& dense, const std::string& where);
// `dense:` of YAML text (the fuzzers' and tests' entry).
DenseOptions dense_options_from_yaml(const std::string& text, const std::string& where);
// Every key as ("dense.key", value), for --print-config and the metrics.
std::vector<std::pair<std::string, std::string>> dense_options_table(const DenseOptions& o);

// The `viewer:` section (docs/dense.md): the dense map's stream to the live
// viewer, `dense_max_kbps` [kbit/s] and `dense_period_s` [s]. Unknown keys and
// bad values are errors naming the file, line and key.
DenseViewOptions dense_view_options_from_node(const YAML::Node& viewer, const std::string& where);
DenseViewOptions dense_view_options_from_yaml(const std::string& text, const std::string& where);
// The `dense:` and `viewer:` sections as YAML that the parsers above (and tools::load_config) read back
// (`--print-config`, `kestrel config`: the tool-side sections beside the
// estimator's).
std::string dense_sections_yaml(const DenseOptions& o, const DenseViewOptions& v);

}  // namespace kestrel::dense

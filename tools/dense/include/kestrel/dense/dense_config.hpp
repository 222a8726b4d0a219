// The config's `dense:` section (docs/dense.md lists every key, its unit and
// default). Unknown keys and bad values are errors naming the file and key.
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "kestrel/dense/dense_mapper.hpp"

namespace kestrel::dense {

// `dense:` of the YAML text (absent: the defaults, enabled = false). `where` names the file in errors.
DenseOptions dense_options_from_yaml(const std::string& text, const std::string& where);
// The same from a file; "" gives the defaults.
DenseOptions load_dense_options(const std::string& path);
// Every key as ("dense.key", value), for --print-config and the metrics.
std::vector<std::pair<std::string, std::string>> dense_options_table(const DenseOptions& o);

// `viewer.dense_max_kbps` [kbit/s]: the cap of the dense map's stream to the
// live viewer (docs/dense.md). The `viewer:` section holds only this key.
inline constexpr double kDefaultDenseViewMaxKbps = 2000;
double dense_view_max_kbps_from_yaml(const std::string& text, const std::string& where);
double load_dense_view_max_kbps(const std::string& path);

}  // namespace kestrel::dense

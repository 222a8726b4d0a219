// The conventions every JSON report of the tools shares (`kestrel eval --json`,
// `kestrel replay --metrics-out`, `kestrel bench --json`), on nlohmann::json.
// Scripts and tests read these files by key, so keys keep the order they are
// written in (ordered_json) and the layout is one member per line.
#pragma once

#include <nlohmann/json.hpp>
#include <string>

namespace kestrel::tools {

using Json = nlohmann::ordered_json;

// A measured figure: null when it does not exist (JSON has no NaN, and a
// figure that was not measured must read as missing, not as zero), else the
// value at 10 significant digits, the precision the reports have always had
// (more digits would be noise in timings and would make every diff of a
// report differ in the last place).
Json json_figure(double v);

// The file text: two-space indentation and a final newline. Bytes that are not
// UTF-8 (a path can hold anything) become U+FFFD rather than failing the report.
std::string json_text(const Json& j);

}  // namespace kestrel::tools

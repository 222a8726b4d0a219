// The one text layer: what every reader of a CSV / whitespace table needs
// (dataset readers, trajectory files for eval, ground truth and IMU tables for
// the simulator). Pure functions over strings, no allocation beyond the
// returned strings; not for real-time threads.
//
// Numbers are parsed from the whole token: "12abc" is not 12. Leading white
// space is skipped as strtod/strtoll do, trailing white space is not (fields
// from split() are already trimmed).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace kestrel::drivers::text {

// What read_lines() found; converts to true only when every line was read.
struct LinesRead {
  bool opened = false;  // false: the file could not be opened
  bool ok = false;      // opened and read to the end
  int error = 0;        // errno of the failure (0 when ok)
  explicit operator bool() const { return ok; }
};

// Lines of a file without their end of line ("\n" or "\r\n"). `lines` is
// replaced; line k (1-based, as errors name it) is lines[k - 1].
LinesRead read_lines(const std::string& path, std::vector<std::string>& lines);

// Without leading and trailing white space (isspace: " \t\r\n\v\f").
std::string trim(const std::string& s);
// Fields between `sep`, each trimmed. Never empty: "" gives one empty field,
// "a," gives "a" and "" (an empty field is a field, the caller decides).
std::vector<std::string> split(const std::string& s, char sep);
// Runs of non-space characters; no empty fields.
std::vector<std::string> split_ws(const std::string& s);

// Base-10 integer; false on anything else or when it does not fit (19+ digits).
bool parse_i64(const std::string& s, int64_t& v);
// Any number strtod accepts, nan and inf included, an overflow giving +-inf
// and an underflow 0 or a subnormal: callers decide what they tolerate.
bool parse_f64(const std::string& s, double& v);
// A finite number that strtod converted without range error: no nan, no inf,
// no overflow, no underflow.
bool parse_finite_f64(const std::string& s, double& v);

// Decimal seconds to integer nanoseconds without a double in between, so a
// 1e9 s stamp keeps every digit ("1305031102.175304" -> 1305031102175304000).
// Syntax: [+-] digits [. digits] with at least one digit, optionally (when
// `exponent`) followed by e/E [+-] digits, still exact ("1.5e3" -> 1.5e12).
// False when the result does not fit int64 nanoseconds (|t| < 9223372036.85 s).
enum class BelowNs {
  kTruncate,  // digits below a nanosecond are dropped (toward zero)
  kRound,     // rounded half away from zero
  kReject,    // a non-zero digit below a nanosecond makes the token invalid
};
struct SecondsSyntax {
  BelowNs below_ns = BelowNs::kTruncate;
  bool exponent = false;
};
bool parse_seconds_ns(const std::string& s, int64_t& t_ns, const SecondsSyntax& syntax = {});

// 1305031102175304000 -> "1305031102.175304000": the exact inverse of parse_seconds_ns.
std::string seconds_from_ns(int64_t t_ns);
// %.17g: a double that reads back bit-identical.
std::string fmt17(double v);
// A double as an ostream prints it (6 significant digits): for messages.
std::string fmt6(double v);

// Well-formed UTF-8 (RFC 3629: no overlong forms, surrogates or code points
// past U+10FFFF). YAML text must be UTF-8, and an emitter rewrites what is not.
bool is_utf8(const std::string& s);

// Path helpers the readers share.
std::string file_name(const std::string& path);  // after the last '/'
bool is_file(const std::string& path);
bool is_dir(const std::string& path);
// "a/b//" -> "a/b"; "/" stays.
std::string strip_trailing_slashes(std::string path);
// The whole file; std::runtime_error "PATH: cannot open" (+ hint) when it cannot be read.
std::string read_file(const std::string& path, const std::string& hint = "");

}  // namespace kestrel::drivers::text

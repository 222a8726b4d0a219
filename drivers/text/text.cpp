#include "kestrel/drivers/text.hpp"

#include <sys/stat.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <sstream>
#include <stdexcept>

namespace kestrel::drivers::text {
namespace {

bool is_space(char c) { return std::isspace(static_cast<unsigned char>(c)) != 0; }
bool is_digit(char c) { return c >= '0' && c <= '9'; }

}  // namespace

LinesRead read_lines(const std::string& path, std::vector<std::string>& lines) {
  LinesRead r;
  errno = 0;
  std::ifstream f(path, std::ios::binary);
  if (!f) {
    r.error = errno;
    return r;
  }
  r.opened = true;
  lines.clear();
  std::string l;
  while (std::getline(f, l)) {
    if (!l.empty() && l.back() == '\r') l.pop_back();
    lines.push_back(std::move(l));
  }
  if (f.bad()) {
    r.error = errno;
    return r;
  }
  r.ok = true;
  return r;
}

std::string trim(const std::string& s) {
  size_t a = 0, b = s.size();
  while (a < b && is_space(s[a])) ++a;
  while (b > a && is_space(s[b - 1])) --b;
  return s.substr(a, b - a);
}

std::vector<std::string> split(const std::string& s, char sep) {
  std::vector<std::string> out;
  size_t start = 0;
  for (;;) {
    const size_t k = s.find(sep, start);
    out.push_back(trim(s.substr(start, k == std::string::npos ? std::string::npos : k - start)));
    if (k == std::string::npos) break;
    start = k + 1;
  }
  return out;
}

std::vector<std::string> split_ws(const std::string& s) {
  std::vector<std::string> out;
  size_t i = 0;
  while (i < s.size()) {
    while (i < s.size() && is_space(s[i])) ++i;
    const size_t j0 = i;
    while (i < s.size() && !is_space(s[i])) ++i;
    if (i > j0) out.push_back(s.substr(j0, i - j0));
  }
  return out;
}

bool parse_i64(const std::string& s, int64_t& v) {
  if (s.empty()) return false;
  errno = 0;
  char* end = nullptr;
  const long long x = std::strtoll(s.c_str(), &end, 10);
  if (end != s.c_str() + s.size() || errno == ERANGE) return false;
  v = x;
  return true;
}

bool parse_f64(const std::string& s, double& v) {
  if (s.empty()) return false;
  char* end = nullptr;
  const double x = std::strtod(s.c_str(), &end);
  if (end != s.c_str() + s.size()) return false;
  v = x;
  return true;
}

bool parse_finite_f64(const std::string& s, double& v) {
  if (s.empty()) return false;
  errno = 0;
  char* end = nullptr;
  const double x = std::strtod(s.c_str(), &end);
  if (end != s.c_str() + s.size() || errno != 0 || !std::isfinite(x)) return false;
  v = x;
  return true;
}

bool parse_seconds_ns(const std::string& s, int64_t& t_ns, const SecondsSyntax& syntax) {
  const size_t n = s.size();
  size_t i = 0;
  bool neg = false;
  if (i < n && (s[i] == '+' || s[i] == '-')) neg = s[i++] == '-';
  const size_t int_begin = i;
  while (i < n && is_digit(s[i])) ++i;
  const size_t n_int = i - int_begin;
  size_t frac_begin = i, n_frac = 0;
  if (i < n && s[i] == '.') {
    frac_begin = ++i;
    while (i < n && is_digit(s[i])) ++i;
    n_frac = i - frac_begin;
  }
  if (n_int + n_frac == 0) return false;
  // Saturated: past a million the answer (overflow, or every digit below a
  // nanosecond) no longer depends on the value.
  constexpr int64_t kExpCap = 1000000;
  int64_t exp10 = 0;
  if (syntax.exponent && i < n && (s[i] == 'e' || s[i] == 'E')) {
    ++i;
    bool exp_neg = false;
    if (i < n && (s[i] == '+' || s[i] == '-')) exp_neg = s[i++] == '-';
    const size_t exp_begin = i;
    for (; i < n && is_digit(s[i]); ++i) exp10 = std::min(kExpCap, exp10 * 10 + (s[i] - '0'));
    if (i == exp_begin) return false;
    if (exp_neg) exp10 = -exp10;
  }
  if (i != n) return false;

  // The mantissa's digits d_0 .. d_{N-1} (point removed); d_j is worth
  // 10^(n_int - 1 - j + exp10 + 9) ns, so digits up to index `last` are whole
  // nanoseconds and the rest lie below one.
  const size_t n_digits = n_int + n_frac;
  auto digit = [&](size_t j) { return s[j < n_int ? int_begin + j : frac_begin + (j - n_int)] - '0'; };
  const int64_t last = static_cast<int64_t>(n_int) + 8 + exp10;
  const size_t kept = last < 0 ? 0 : std::min(n_digits, static_cast<size_t>(last) + 1);
  constexpr uint64_t kMax = static_cast<uint64_t>(std::numeric_limits<int64_t>::max());
  uint64_t mag = 0;
  for (size_t j = 0; j < kept; ++j) {
    const auto d = static_cast<uint64_t>(digit(j));
    if (mag > (kMax - d) / 10) return false;
    mag = mag * 10 + d;
  }
  // Every digit kept and the last one still worth 10^k ns: scale.
  if (kept == n_digits && mag != 0) {
    for (int64_t k = last - static_cast<int64_t>(n_digits) + 1; k > 0; --k) {
      if (mag > kMax / 10) return false;
      mag *= 10;
    }
  }
  if (kept < n_digits) {
    // Index of the digit worth 0.1 ns; before the first digit it is a leading zero.
    const int64_t tenth = last + 1;
    const int first_dropped = tenth >= 0 ? digit(static_cast<size_t>(tenth)) : 0;
    switch (syntax.below_ns) {
      case BelowNs::kTruncate:
        break;
      case BelowNs::kRound:
        if (first_dropped >= 5) {
          if (mag == kMax) return false;
          ++mag;
        }
        break;
      case BelowNs::kReject:
        for (size_t j = kept; j < n_digits; ++j)
          if (digit(j) != 0) return false;
        break;
    }
  }
  t_ns = neg ? -static_cast<int64_t>(mag) : static_cast<int64_t>(mag);
  return true;
}

std::string seconds_from_ns(int64_t t_ns) {
  char b[48];
  const bool neg = t_ns < 0;
  const uint64_t a = neg ? 0 - static_cast<uint64_t>(t_ns) : static_cast<uint64_t>(t_ns);
  std::snprintf(b, sizeof b, "%s%llu.%09llu", neg ? "-" : "",
                static_cast<unsigned long long>(a / 1000000000u),
                static_cast<unsigned long long>(a % 1000000000u));
  return b;
}

std::string fmt17(double v) {
  char b[40];
  std::snprintf(b, sizeof b, "%.17g", v);
  return b;
}

std::string file_name(const std::string& path) {
  const size_t k = path.find_last_of('/');
  return k == std::string::npos ? path : path.substr(k + 1);
}

bool is_file(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0 && S_ISREG(st.st_mode);
}

bool is_dir(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0 && S_ISDIR(st.st_mode);
}

std::string strip_trailing_slashes(std::string path) {
  while (path.size() > 1 && path.back() == '/') path.pop_back();
  return path;
}

std::string read_file(const std::string& path, const std::string& hint) {
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error(path + ": cannot open" + hint);
  std::ostringstream s;
  s << f.rdbuf();
  return s.str();
}

std::string fmt6(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

bool is_utf8(const std::string& s) {
  const auto* p = reinterpret_cast<const unsigned char*>(s.data());
  const size_t n = s.size();
  for (size_t i = 0; i < n;) {
    const unsigned c = p[i];
    size_t len = 0;
    unsigned lo = 0x80, hi = 0xBF;  // the allowed range of the second byte
    if (c < 0x80) {
      ++i;
      continue;
    } else if (c >= 0xC2 && c <= 0xDF) {
      len = 2;
    } else if (c >= 0xE0 && c <= 0xEF) {
      len = 3;
      if (c == 0xE0) lo = 0xA0;  // overlong
      if (c == 0xED) hi = 0x9F;  // surrogates
    } else if (c >= 0xF0 && c <= 0xF4) {
      len = 4;
      if (c == 0xF0) lo = 0x90;  // overlong
      if (c == 0xF4) hi = 0x8F;  // past U+10FFFF
    } else {
      return false;
    }
    if (i + len > n || p[i + 1] < lo || p[i + 1] > hi) return false;
    for (size_t k = 2; k < len; ++k)
      if (p[i + k] < 0x80 || p[i + k] > 0xBF) return false;
    i += len;
  }
  return true;
}

}  // namespace kestrel::drivers::text

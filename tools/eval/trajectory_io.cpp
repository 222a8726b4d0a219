// Trajectory files in and out: TUM text, EuRoC CSV, and every LogSource format.
#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/tools/trajectory_eval.hpp"

namespace kestrel::tools {
namespace {

namespace fs = std::filesystem;

// Past this many per-line messages a file's problems are only counted: a
// corrupt million-line file must not bury the summary.
constexpr int kMaxListedProblems = 20;

// Collects problems for one file. Without a warnings sink the caller asked for
// strictness, so the first loss throws.
class Reporter {
 public:
  Reporter(std::string path, std::vector<std::string>* sink) : path_(std::move(path)), sink_(sink) {}

  // A line or record that will not make it into the trajectory.
  void loss(const std::string& where, const std::string& what) {
    const std::string msg = where + ": " + what;
    if (sink_ == nullptr) throw std::runtime_error(msg);
    if (first_.empty()) first_ = msg;
    if (listed_ < kMaxListedProblems) {
      sink_->push_back(msg);
      ++listed_;
    } else {
      ++suppressed_;
    }
  }
  // A repair that loses nothing (sorting, exact duplicates).
  void note(const std::string& msg) {
    if (sink_ != nullptr) sink_->push_back(msg);
  }
  void finish() {
    if (suppressed_ > 0 && sink_ != nullptr)
      sink_->push_back(path_ + ": " + std::to_string(suppressed_) + " more skipped lines not listed");
  }
  const std::string& first() const { return first_; }
  int losses() const { return listed_ + suppressed_; }

 private:
  std::string path_;
  std::vector<std::string>* sink_;
  std::string first_;
  int listed_ = 0;
  int suppressed_ = 0;
};

struct Row {
  TimedPose pose;
  std::string where;   // "file:line" it came from
};

std::string trim(const std::string& s) {
  size_t b = 0, e = s.size();
  while (b < e && std::isspace(static_cast<unsigned char>(s[b]))) ++b;
  while (e > b && std::isspace(static_cast<unsigned char>(s[e - 1]))) --e;
  return s.substr(b, e - b);
}

std::string lower_extension(const std::string& path) {
  std::string ext = fs::path(path).extension().string();
  for (char& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return ext;
}

// strtod on the whole token; NaN/Inf parse (and are rejected later as non-finite).
bool parse_double(const std::string& tok, double* out) {
  if (tok.empty()) return false;
  errno = 0;
  char* end = nullptr;
  const double v = std::strtod(tok.c_str(), &end);
  if (end != tok.c_str() + tok.size()) return false;
  if (errno == ERANGE && std::isfinite(v) && v != 0.0) return false;
  *out = v;
  return true;
}

bool parse_int64(const std::string& tok, int64_t* out) {
  if (tok.empty()) return false;
  errno = 0;
  char* end = nullptr;
  const long long v = std::strtoll(tok.c_str(), &end, 10);
  if (end != tok.c_str() + tok.size() || errno == ERANGE) return false;
  *out = static_cast<int64_t>(v);
  return true;
}

// Decimal seconds to nanoseconds without going through a double, so TUM stamps
// such as 1305031098.6659 keep every digit (a double has ~100 ns there).
bool parse_seconds_ns(const std::string& tok, int64_t* out) {
  if (tok.find_first_of("eE") != std::string::npos) {   // rare exponent form: double is all we have
    double s = 0;
    if (!parse_double(tok, &s) || !std::isfinite(s) || std::fabs(s) > 9.2e9) return false;
    *out = static_cast<int64_t>(std::llround(s * 1e9));
    return true;
  }
  size_t i = 0;
  bool neg = false;
  if (i < tok.size() && (tok[i] == '+' || tok[i] == '-')) neg = tok[i++] == '-';
  int64_t whole = 0;
  int whole_digits = 0;
  while (i < tok.size() && std::isdigit(static_cast<unsigned char>(tok[i]))) {
    if (whole > 9'200'000'000LL / 10) return false;
    whole = whole * 10 + (tok[i++] - '0');
    ++whole_digits;
  }
  int64_t frac = 0;
  int frac_digits = 0;
  bool round_up = false;
  if (i < tok.size() && tok[i] == '.') {
    ++i;
    while (i < tok.size() && std::isdigit(static_cast<unsigned char>(tok[i]))) {
      if (frac_digits < 9) {
        frac = frac * 10 + (tok[i] - '0');
      } else if (frac_digits == 9) {
        round_up = tok[i] >= '5';
      }
      ++frac_digits;
      ++i;
    }
  }
  if (i != tok.size() || whole_digits + frac_digits == 0 || whole > 9'200'000'000LL) return false;
  for (int d = std::min(frac_digits, 9); d < 9; ++d) frac *= 10;
  int64_t ns = whole * 1'000'000'000LL + frac + (round_up ? 1 : 0);
  *out = neg ? -ns : ns;
  return true;
}

std::vector<std::string> split_csv(const std::string& line) {
  std::vector<std::string> out;
  size_t start = 0;
  while (true) {
    const size_t comma = line.find(',', start);
    out.push_back(trim(line.substr(start, comma == std::string::npos ? std::string::npos : comma - start)));
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  return out;
}

std::vector<std::string> split_ws(const std::string& line) {
  std::vector<std::string> out;
  size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && std::isspace(static_cast<unsigned char>(line[i]))) ++i;
    const size_t b = i;
    while (i < line.size() && !std::isspace(static_cast<unsigned char>(line[i]))) ++i;
    if (i > b) out.push_back(line.substr(b, i - b));
  }
  return out;
}

enum class TextFormat { kTum, kEurocCsv };

// Fields 1..7 of either format into a pose, or a message naming the bad field.
// `order` maps pose slots (px py pz qw qx qy qz) to field indices.
bool fill_pose(const std::vector<std::string>& f, const char* const* names, const int* order, TimedPose* pose,
               std::string* err) {
  double v[7];
  for (int k = 0; k < 7; ++k) {
    const int idx = order[k];
    if (!parse_double(f[idx], &v[k])) {
      *err = std::string("field '") + names[idx] + "' (column " + std::to_string(idx + 1) + "): not a number '" +
             f[idx] + "'";
      return false;
    }
    if (!std::isfinite(v[k])) {
      *err = std::string("field '") + names[idx] + "' (column " + std::to_string(idx + 1) +
             "): non-finite value '" + f[idx] + "'";
      return false;
    }
  }
  pose->p = Eigen::Vector3d(v[0], v[1], v[2]);
  Eigen::Quaterniond q(v[3], v[4], v[5], v[6]);
  const double n = q.norm();
  if (!(n > 1e-6)) {
    *err = "quaternion has zero norm";
    return false;
  }
  q.coeffs() /= n;
  pose->q = q;
  return true;
}

std::vector<Row> read_text(const std::string& path, Reporter& rep, int* non_unit_quats) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open '" + path + "': " + std::strerror(errno));

  static const char* const kTumNames[8] = {"timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"};
  static const char* const kCsvNames[8] = {"timestamp", "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z"};
  static const int kTumOrder[7] = {1, 2, 3, 7, 4, 5, 6};
  static const int kCsvOrder[7] = {1, 2, 3, 4, 5, 6, 7};

  TextFormat format = TextFormat::kTum;

  std::vector<Row> rows;
  std::string raw;
  int line_no = 0;
  bool first_data_line = true;
  while (std::getline(in, raw)) {
    ++line_no;
    const std::string line = trim(raw);
    if (line.empty() || line[0] == '#') continue;
    const std::string where = path + ":" + std::to_string(line_no);
    if (first_data_line) {
      // By content, not extension (.txt files hold either): TUM never has a comma.
      format = line.find(',') != std::string::npos ? TextFormat::kEurocCsv : TextFormat::kTum;
    }
    const bool csv = format == TextFormat::kEurocCsv;
    const std::vector<std::string> f = csv ? split_csv(line) : split_ws(line);
    if (first_data_line) {
      first_data_line = false;
      // A header without '#' ("timestamp,p_x,..."): its first field is no number.
      double dummy = 0;
      if (!f.empty() && !parse_double(f[0], &dummy)) continue;
    }
    if (f.size() < 8 || (!csv && f.size() > 8)) {
      rep.loss(where, std::string(csv ? "EuRoC CSV" : "TUM") + " line has " + std::to_string(f.size()) +
                          " fields, expected " + (csv ? "at least 8 (t[ns],px,py,pz,qw,qx,qy,qz)"
                                                      : "8 (t[s] x y z qx qy qz qw)"));
      continue;
    }
    Row row;
    row.where = where;
    if (csv) {
      if (!parse_int64(f[0], &row.pose.t_ns)) {
        rep.loss(where, "field 'timestamp' (column 1): not integer nanoseconds '" + f[0] + "'");
        continue;
      }
    } else if (!parse_seconds_ns(f[0], &row.pose.t_ns)) {
      rep.loss(where, "field 'timestamp' (column 1): not a time in seconds '" + f[0] + "'");
      continue;
    }
    std::string err;
    double raw_norm = 0;
    {
      // Norm before normalisation, to flag files whose quaternion columns are likely misordered/garbage.
      double qv[4];
      const int* order = csv ? kCsvOrder : kTumOrder;
      bool ok = true;
      for (int k = 0; k < 4; ++k) ok = ok && parse_double(f[order[3 + k]], &qv[k]);
      if (ok) raw_norm = std::sqrt(qv[0] * qv[0] + qv[1] * qv[1] + qv[2] * qv[2] + qv[3] * qv[3]);
    }
    if (!fill_pose(f, csv ? kCsvNames : kTumNames, csv ? kCsvOrder : kTumOrder, &row.pose, &err)) {
      rep.loss(where, err);
      continue;
    }
    if (std::fabs(raw_norm - 1.0) > 0.01) ++*non_unit_quats;
    rows.push_back(std::move(row));
  }
  if (in.bad()) throw std::runtime_error("error reading '" + path + "': " + std::strerror(errno));
  return rows;
}

std::vector<Row> read_log(const std::string& path, Reporter& rep, std::vector<std::string>* warnings) {
  auto source = drivers::open_log(path);   // throws naming the path
  const bool byte_offsets = source->format_name().find("klog") != std::string::npos;
  std::vector<Row> rows;
  drivers::LogRecord rec;
  while (source->next(rec)) {
    if (rec.type != drivers::RecordType::kGroundTruth) continue;
    const std::string where = path + (byte_offsets ? "@" : ":") + std::to_string(rec.offset);
    const auto& g = rec.gt;
    Row row;
    row.where = where;
    row.pose.t_ns = g.t_ns;
    row.pose.p = Eigen::Vector3d(g.p_WB[0], g.p_WB[1], g.p_WB[2]);
    Eigen::Quaterniond q(g.q_WB[0], g.q_WB[1], g.q_WB[2], g.q_WB[3]);
    if (!row.pose.p.allFinite() || !q.coeffs().allFinite()) {
      rep.loss(where, "ground-truth record with non-finite p_WB or q_WB");
      continue;
    }
    if (!(q.norm() > 1e-6)) {
      rep.loss(where, "ground-truth record with zero-norm q_WB");
      continue;
    }
    q.normalize();
    row.pose.q = q;
    rows.push_back(std::move(row));
  }
  // The reader's own findings belong with ours, but eval only reads ground truth:
  // problems about ground-truth files (or binary offsets, which could be anything)
  // are listed, the rest (missing images, no depth...) are summarised in one line.
  if (warnings != nullptr) {
    int other = 0;
    std::string first_other;
    for (const auto& p : source->problems()) {
      const std::string msg = p.where + ": " + p.kind + ": " + p.detail;
      const bool about_gt = byte_offsets || p.where.find("groundtruth") != std::string::npos ||
                            p.where.find("gt_") != std::string::npos || p.kind.find("gt") != std::string::npos ||
                            p.kind.find("ground") != std::string::npos;
      if (about_gt) {
        warnings->push_back(msg);
      } else if (other++ == 0) {
        first_other = msg;
      }
    }
    if (other > 0)
      warnings->push_back(path + ": the " + source->format_name() + " reader reported " + std::to_string(other) +
                          " problems with non-ground-truth data (not used by eval; first: " + first_other + ")");
  }
  if (rows.empty())
    throw std::runtime_error("'" + path + "' (" + source->format_name() + " log) holds no ground-truth records");
  return rows;
}

// .klog files are binary; the magic catches one renamed without its extension.
bool looks_like_klog(const std::string& path) {
  if (lower_extension(path) == ".klog") return true;
  std::ifstream f(path, std::ios::binary);
  char magic[4] = {};
  return f.read(magic, 4) && std::memcmp(magic, "KLOG", 4) == 0;
}

bool same_pose(const TimedPose& a, const TimedPose& b) {
  return a.p == b.p && a.q.coeffs() == b.q.coeffs();
}

}  // namespace

Trajectory load_trajectory(const std::string& path, std::vector<std::string>* warnings) {
  std::error_code ec;
  const bool is_dir = fs::is_directory(path, ec);
  if (!is_dir && !fs::exists(path, ec)) throw std::runtime_error("cannot open '" + path + "': no such file or directory");

  Reporter rep(path, warnings);
  int non_unit_quats = 0;
  std::vector<Row> rows = (is_dir || looks_like_klog(path)) ? read_log(path, rep, warnings)
                                                                       : read_text(path, rep, &non_unit_quats);
  if (rows.empty()) {
    throw std::runtime_error("'" + path + "' holds no pose" +
                             (rep.first().empty() ? std::string() : " (first problem: " + rep.first() + ")"));
  }
  if (non_unit_quats > 0)
    rep.note(path + ": " + std::to_string(non_unit_quats) +
             " quaternions were more than 1% off unit norm (normalised; check the column order)");

  // Out-of-order input is repaired, but said out loud: it often means two files were concatenated.
  int unsorted = 0;
  std::string first_unsorted;
  for (size_t i = 1; i < rows.size(); ++i) {
    if (rows[i].pose.t_ns < rows[i - 1].pose.t_ns) {
      if (unsorted++ == 0) first_unsorted = rows[i].where;
    }
  }
  if (unsorted > 0) {
    rep.note(first_unsorted + ": timestamp earlier than the previous line; " + std::to_string(unsorted) +
             " such lines, trajectory sorted by time");
    std::stable_sort(rows.begin(), rows.end(),
                     [](const Row& a, const Row& b) { return a.pose.t_ns < b.pose.t_ns; });
  }

  Trajectory out;
  out.reserve(rows.size());
  int exact_dups = 0;
  std::string first_dup;
  const std::string* kept_where = nullptr;
  for (const Row& r : rows) {
    if (!out.empty() && out.back().t_ns == r.pose.t_ns) {
      if (same_pose(out.back(), r.pose)) {
        if (exact_dups++ == 0) first_dup = r.where;
      } else {
        rep.loss(r.where, "timestamp " + std::to_string(r.pose.t_ns) + " ns repeats " + *kept_where +
                              " with a different pose; kept the first");
      }
      continue;
    }
    out.push_back(r.pose);
    kept_where = &r.where;
  }
  if (exact_dups > 0)
    rep.note(first_dup + ": exact duplicate pose; " + std::to_string(exact_dups) + " exact duplicates dropped");
  rep.finish();
  return out;
}

void write_tum(const std::string& path, const Trajectory& trajectory) {
  std::FILE* f = std::fopen(path.c_str(), "w");
  if (f == nullptr) throw std::runtime_error("cannot write '" + path + "': " + std::strerror(errno));
  std::fprintf(f, "# timestamp[s] tx ty tz qx qy qz qw  (T_WB: body pose in world)\n");
  for (const TimedPose& p : trajectory) {
    // Seconds printed from the integer so no nanosecond is rounded away.
    const bool neg = p.t_ns < 0;
    const uint64_t mag = neg ? 0ULL - static_cast<uint64_t>(p.t_ns) : static_cast<uint64_t>(p.t_ns);
    std::fprintf(f, "%s%llu.%09llu %.9f %.9f %.9f %.12f %.12f %.12f %.12f\n", neg ? "-" : "",
                 static_cast<unsigned long long>(mag / 1'000'000'000ULL),
                 static_cast<unsigned long long>(mag % 1'000'000'000ULL), p.p.x(), p.p.y(), p.p.z(), p.q.x(),
                 p.q.y(), p.q.z(), p.q.w());
  }
  const bool write_failed = std::ferror(f) != 0;
  if (std::fclose(f) != 0 || write_failed)
    throw std::runtime_error("error writing '" + path + "': " + std::strerror(errno));
}

}  // namespace kestrel::tools

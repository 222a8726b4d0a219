// Trajectory files in and out: TUM text, EuRoC CSV, and every LogSource format.
#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/text.hpp"
#include "kestrel/tools/trajectory_eval.hpp"

namespace kestrel::tools {
namespace {

namespace fs = std::filesystem;
namespace text = drivers::text;

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
  std::string where;  // "file:line" it came from
};

std::string lower_extension(const std::string& path) {
  std::string ext = fs::path(path).extension().string();
  for (char& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return ext;
}

// Any strtod number, NaN/Inf included (rejected later as non-finite, which
// names the problem better), but not a subnormal: an underflowing coordinate
// is garbage, not a pose.
bool parse_double(const std::string& tok, double* out) {
  double v = 0;
  if (!text::parse_f64(tok, v) || std::fpclassify(v) == FP_SUBNORMAL) return false;
  *out = v;
  return true;
}

// TUM stamps such as 1305031098.6659 keep every digit (a double has ~100 ns
// there); a rare exponent form is exact too. Sub-nanosecond digits round.
bool parse_seconds_ns(const std::string& tok, int64_t* out) {
  return text::parse_seconds_ns(tok, *out, text::SecondsSyntax{text::BelowNs::kRound, true});
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
      *err = std::string("field '") + names[idx] + "' (column " + std::to_string(idx + 1) +
             "): not a number '" + f[idx] + "'";
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
  std::vector<std::string> lines;
  const text::LinesRead read = text::read_lines(path, lines);
  if (!read.opened) throw std::runtime_error("cannot open '" + path + "': " + std::strerror(read.error));
  if (!read) throw std::runtime_error("error reading '" + path + "': " + std::strerror(read.error));

  static const char* const kTumNames[8] = {"timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"};
  static const char* const kCsvNames[8] = {"timestamp", "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z"};
  static const int kTumOrder[7] = {1, 2, 3, 7, 4, 5, 6};
  static const int kCsvOrder[7] = {1, 2, 3, 4, 5, 6, 7};

  TextFormat format = TextFormat::kTum;

  std::vector<Row> rows;
  bool first_data_line = true;
  for (size_t k = 0; k < lines.size(); ++k) {
    const size_t line_no = k + 1;
    const std::string line = text::trim(lines[k]);
    if (line.empty() || line[0] == '#') continue;
    const std::string where = path + ":" + std::to_string(line_no);
    if (first_data_line) {
      // By content, not extension (.txt files hold either): TUM never has a comma.
      format = line.find(',') != std::string::npos ? TextFormat::kEurocCsv : TextFormat::kTum;
    }
    const bool csv = format == TextFormat::kEurocCsv;
    const std::vector<std::string> f = csv ? text::split(line, ',') : text::split_ws(line);
    if (first_data_line) {
      first_data_line = false;
      // A header without '#' ("timestamp,p_x,..."): its first field is no number.
      double dummy = 0;
      if (!f.empty() && !parse_double(f[0], &dummy)) continue;
    }
    if (f.size() < 8 || (!csv && f.size() > 8)) {
      rep.loss(where, std::string(csv ? "EuRoC CSV" : "TUM") + " line has " + std::to_string(f.size()) +
                          " fields, expected " +
                          (csv ? "at least 8 (t[ns],px,py,pz,qw,qx,qy,qz)" : "8 (t[s] x y z qx qy qz qw)"));
      continue;
    }
    Row row;
    row.where = where;
    if (csv) {
      if (!text::parse_i64(f[0], row.pose.t_ns)) {
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
  return rows;
}

std::vector<Row> read_log(const std::string& path, Reporter& rep, std::vector<std::string>* warnings) {
  auto source = drivers::open_log(path);  // throws naming the path
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
                            p.where.find("gt_") != std::string::npos ||
                            p.kind.find("gt") != std::string::npos ||
                            p.kind.find("ground") != std::string::npos;
      if (about_gt) {
        warnings->push_back(msg);
      } else if (other++ == 0) {
        first_other = msg;
      }
    }
    if (other > 0) {
      warnings->push_back(
          path + ": the " + source->format_name() + " reader reported " + std::to_string(other) +
          " problems with non-ground-truth data (not used by eval; first: " + first_other + ")");
    }
  }
  if (rows.empty()) {
    throw std::runtime_error("'" + path + "' (" + source->format_name() +
                             " log) holds no ground-truth records");
  }
  return rows;
}

// .klog files are binary; the magic catches one renamed without its extension.
bool looks_like_klog(const std::string& path) {
  if (lower_extension(path) == ".klog") return true;
  std::ifstream f(path, std::ios::binary);
  char magic[4] = {};
  return f.read(magic, 4) && std::memcmp(magic, "KLOG", 4) == 0;
}

bool same_pose(const TimedPose& a, const TimedPose& b) { return a.p == b.p && a.q.coeffs() == b.q.coeffs(); }

}  // namespace

Trajectory load_trajectory(const std::string& path, std::vector<std::string>* warnings) {
  std::error_code ec;
  const bool is_dir = fs::is_directory(path, ec);
  if (!is_dir && !fs::exists(path, ec))
    throw std::runtime_error("cannot open '" + path + "': no such file or directory");

  Reporter rep(path, warnings);
  int non_unit_quats = 0;
  std::vector<Row> rows = (is_dir || looks_like_klog(path)) ? read_log(path, rep, warnings)
                                                            : read_text(path, rep, &non_unit_quats);
  if (rows.empty()) {
    throw std::runtime_error("'" + path + "' holds no pose" +
                             (rep.first().empty() ? std::string() : " (first problem: " + rep.first() + ")"));
  }
  if (non_unit_quats > 0) {
    rep.note(path + ": " + std::to_string(non_unit_quats) +
             " quaternions were more than 1% off unit norm (normalised; check the column order)");
  }

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
  if (exact_dups > 0) {
    rep.note(first_dup + ": exact duplicate pose; " + std::to_string(exact_dups) +
             " exact duplicates dropped");
  }
  rep.finish();
  return out;
}

void write_tum(const std::string& path, const Trajectory& trajectory) {
  std::FILE* f = std::fopen(path.c_str(), "w");
  if (f == nullptr) throw std::runtime_error("cannot write '" + path + "': " + std::strerror(errno));
  std::fprintf(f, "# timestamp[s] tx ty tz qx qy qz qw  (T_WB: body pose in world)\n");
  for (const TimedPose& p : trajectory) {
    // Seconds printed from the integer so no nanosecond is rounded away.
    std::fprintf(f, "%s %.9f %.9f %.9f %.12f %.12f %.12f %.12f\n", text::seconds_from_ns(p.t_ns).c_str(),
                 p.p.x(), p.p.y(), p.p.z(), p.q.x(), p.q.y(), p.q.z(), p.q.w());
  }
  const bool write_failed = std::ferror(f) != 0;
  if (std::fclose(f) != 0 || write_failed)
    throw std::runtime_error("error writing '" + path + "': " + std::strerror(errno));
}

}  // namespace kestrel::tools

#include "dataset_common.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <opencv2/imgcodecs.hpp>
#include <stdexcept>

namespace kestrel::drivers::ds {

Mat4d mat_mul(const Mat4d& a, const Mat4d& b) {
  Mat4d c{};
  for (int i = 0; i < 4; ++i) {
    for (int j = 0; j < 4; ++j) {
      double s = 0;
      for (int k = 0; k < 4; ++k) s += a[i * 4 + k] * b[k * 4 + j];
      c[i * 4 + j] = s;
    }
  }
  return c;
}

Mat4d mat_inv(const Mat4d& t) {
  Mat4d r = kIdentity4;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r[i * 4 + j] = t[j * 4 + i];
  for (int i = 0; i < 3; ++i)
    r[i * 4 + 3] = -(r[i * 4 + 0] * t[3] + r[i * 4 + 1] * t[7] + r[i * 4 + 2] * t[11]);
  return r;
}

bool is_identity(const Mat4d& t) { return t == kIdentity4; }

Mat4d pose_to_mat(const Vec3d& p, const Quatd& q) {
  const double n = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const double w = q[0] / n, x = q[1] / n, y = q[2] / n, z = q[3] / n;
  return {1 - 2 * (y * y + z * z),
          2 * (x * y - w * z),
          2 * (x * z + w * y),
          p[0],
          2 * (x * y + w * z),
          1 - 2 * (x * x + z * z),
          2 * (y * z - w * x),
          p[1],
          2 * (x * z - w * y),
          2 * (y * z + w * x),
          1 - 2 * (x * x + y * y),
          p[2],
          0,
          0,
          0,
          1};
}

void mat_to_pose(const Mat4d& t, Vec3d& p, Quatd& q) {
  p = {t[3], t[7], t[11]};
  const double m00 = t[0], m11 = t[5], m22 = t[10];
  const double tr = m00 + m11 + m22;
  double w, x, y, z;
  // Shepperd: divide by the largest of the four candidates for accuracy.
  if (tr > 0) {
    const double s = std::sqrt(tr + 1.0) * 2;
    w = 0.25 * s, x = (t[9] - t[6]) / s, y = (t[2] - t[8]) / s, z = (t[4] - t[1]) / s;
  } else if (m00 > m11 && m00 > m22) {
    const double s = std::sqrt(1.0 + m00 - m11 - m22) * 2;
    w = (t[9] - t[6]) / s, x = 0.25 * s, y = (t[1] + t[4]) / s, z = (t[2] + t[8]) / s;
  } else if (m11 > m22) {
    const double s = std::sqrt(1.0 + m11 - m00 - m22) * 2;
    w = (t[2] - t[8]) / s, x = (t[1] + t[4]) / s, y = 0.25 * s, z = (t[6] + t[9]) / s;
  } else {
    const double s = std::sqrt(1.0 + m22 - m00 - m11) * 2;
    w = (t[4] - t[1]) / s, x = (t[2] + t[8]) / s, y = (t[6] + t[9]) / s, z = 0.25 * s;
  }
  if (w < 0) w = -w, x = -x, y = -y, z = -z;
  q = {w, x, y, z};
}

GroundTruthPose compose(const GroundTruthPose& g, const Mat4d& T_XB) {
  if (is_identity(T_XB)) return g;
  GroundTruthPose out = g;
  mat_to_pose(mat_mul(pose_to_mat(g.p_WB, g.q_WB), T_XB), out.p_WB, out.q_WB);
  // Velocity of the point B = v_X + w x r; the angular rate is unknown here,
  // so a velocity is only carried when the origin does not move.
  if (g.has_velocity && !(T_XB[3] == 0 && T_XB[7] == 0 && T_XB[11] == 0)) {
    out.has_velocity = false;
    out.v_WB = {};
  }
  return out;
}

std::vector<Listed> read_list(const std::string& path, text::StreamLogSource& s) {
  std::vector<Listed> out;
  std::vector<std::string> lines;
  if (!text::read_lines(path, lines)) return out;
  for (size_t i = 0; i < lines.size(); ++i) {
    const std::string t = text::trim(lines[i]);
    if (t.empty() || t[0] == '#') continue;
    const auto f = text::split_ws(t);
    Listed l;
    if (f.size() != 2 || !text::parse_seconds_ns(f[0], l.t_ns)) {
      s.problem(path + ":" + std::to_string(i + 1), "bad-row",
                "expected \"timestamp[s] filename\", got " + std::to_string(f.size()) + " fields");
      continue;
    }
    l.file = f[1];
    l.line = i + 1;
    out.push_back(std::move(l));
  }
  for (size_t i = 1; i < out.size(); ++i) {
    if (out[i].t_ns <= out[i - 1].t_ns) {
      s.problem(path + ":" + std::to_string(out[i].line),
                out[i].t_ns == out[i - 1].t_ns ? "duplicate" : "time-order",
                "timestamp not after the previous row's (line " + std::to_string(out[i - 1].line) +
                    "); replayed in sorted order");
    }
  }
  std::stable_sort(out.begin(), out.end(), [](const Listed& a, const Listed& b) { return a.t_ns < b.t_ns; });
  // A repeated stamp would make two frames of one instant; the later row is dropped.
  std::vector<Listed> unique;
  for (auto& l : out)
    if (unique.empty() || unique.back().t_ns != l.t_ns) unique.push_back(std::move(l));
  return unique;
}

std::vector<long> associate(const std::vector<Listed>& rgb, const std::vector<Listed>& depth,
                            int64_t max_dt_ns, size_t& pairs) {
  struct Pair {
    int64_t dt;
    size_t r, d;
  };
  std::vector<Pair> cand;
  size_t lo = 0;
  // A listed stamp may be any int64 (a sign included): the window's ends saturate.
  auto shifted = [](int64_t t, int64_t dt) {
    int64_t v = 0;
    return __builtin_add_overflow(t, dt, &v)
               ? (dt < 0 ? std::numeric_limits<int64_t>::min() : std::numeric_limits<int64_t>::max())
               : v;
  };
  for (size_t r = 0; r < rgb.size(); ++r) {
    while (lo < depth.size() && depth[lo].t_ns < shifted(rgb[r].t_ns, -max_dt_ns)) ++lo;
    for (size_t d = lo; d < depth.size() && depth[d].t_ns <= shifted(rgb[r].t_ns, max_dt_ns); ++d)
      cand.push_back({std::abs(depth[d].t_ns - rgb[r].t_ns), r, d});
  }
  std::stable_sort(cand.begin(), cand.end(), [](const Pair& a, const Pair& b) { return a.dt < b.dt; });
  std::vector<long> depth_of(rgb.size(), -1);
  std::vector<bool> used(depth.size(), false);
  pairs = 0;
  for (const Pair& p : cand) {
    if (depth_of[p.r] < 0 && !used[p.d]) {
      depth_of[p.r] = static_cast<long>(p.d);
      used[p.d] = true;
      ++pairs;
    }
  }
  return depth_of;
}

void add_pairs(const std::string& root, const std::vector<Listed>& rgb, const std::string& rgb_list,
               const std::vector<Listed>& depth, const std::string& depth_list,
               const std::vector<long>& depth_of, text::StreamLogSource& s) {
  std::vector<bool> used(depth.size(), false);
  size_t no_depth = 0;
  std::string first_no_depth;
  for (size_t r = 0; r < rgb.size(); ++r) {
    text::ImageEntry e;
    e.t_ns = e.t_recv_ns = rgb[r].t_ns;
    e.seq = static_cast<uint32_t>(r);
    e.path = root + "/" + rgb[r].file;
    e.line = rgb[r].line;
    e.where = rgb_list + ":" + std::to_string(rgb[r].line);
    if (!text::is_file(e.path)) {
      s.problem(e.where, "missing-file", e.path + " listed but absent; frame skipped");
      continue;
    }
    s.rgb_.push_back(e);
    if (depth_of[r] < 0) {
      if (!depth.empty() && no_depth++ == 0) first_no_depth = e.where;
      continue;
    }
    const Listed& d = depth[static_cast<size_t>(depth_of[r])];
    used[static_cast<size_t>(depth_of[r])] = true;
    text::ImageEntry de;
    de.t_ns = rgb[r].t_ns;
    de.t_recv_ns = d.t_ns;
    de.seq = static_cast<uint32_t>(depth_of[r]);
    de.path = root + "/" + d.file;
    de.line = d.line;
    de.where = depth_list + ":" + std::to_string(d.line);
    if (!text::is_file(de.path)) {
      s.problem(de.where, "missing-file", de.path + " listed but absent; depth frame skipped");
      continue;
    }
    s.depth_.push_back(de);
  }
  if (no_depth > 0) {
    s.problem(
        first_no_depth, "no-depth",
        std::to_string(no_depth) + " colour frames without a depth frame in the window; replayed alone");
  }
  size_t unassoc = 0;
  std::string first;
  for (size_t d = 0; d < depth.size(); ++d)
    if (!used[d] && unassoc++ == 0) first = depth_list + ":" + std::to_string(depth[d].line);
  if (unassoc > 0) {
    s.problem(first, "unassociated",
              std::to_string(unassoc) + " depth frames without a colour partner; skipped");
  }
}

void read_tum_poses(const std::string& path, text::StreamLogSource& s,
                    std::vector<text::Row<GroundTruthPose>>& out) {
  std::vector<std::string> lines;
  if (!text::read_lines(path, lines)) return;
  for (size_t i = 0; i < lines.size(); ++i) {
    const std::string t = text::trim(lines[i]);
    if (t.empty() || t[0] == '#') continue;
    const auto f = text::split_ws(t);
    const std::string where = path + ":" + std::to_string(i + 1);
    GroundTruthPose g;
    double v[7];
    if (f.size() != 8 || !text::parse_seconds_ns(f[0], g.t_ns)) {
      s.problem(where, "bad-row",
                "expected \"t[s] tx ty tz qx qy qz qw\" (8 fields), got " + std::to_string(f.size()));
      continue;
    }
    bool ok = true;
    for (int k = 0; k < 7 && ok; ++k) ok = text::parse_f64(f[k + 1], v[k]) && std::isfinite(v[k]);
    if (!ok) {
      s.problem(where, "bad-row", "a pose field is not a finite number");
      continue;
    }
    const double qn = std::sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5] + v[6] * v[6]);
    if (std::abs(qn - 1.0) > 1e-2) {
      s.problem(where, "bad-row", "quaternion norm " + text::fmt17(qn) + " is not 1");
      continue;
    }
    g.p_WB = {v[0], v[1], v[2]};
    g.q_WB = {v[6], v[3], v[4], v[5]};
    out.push_back({g, i + 1});
  }
}

void drop_duplicate_imu(text::StreamLogSource& s, const std::string& file) {
  std::vector<text::Row<ImuSample>> kept;
  kept.reserve(s.imu_.size());
  for (auto& r : s.imu_) {
    if (!kept.empty() && kept.back().value.t_ns == r.value.t_ns) {
      s.problem(file + ":" + std::to_string(r.line), "duplicate",
                "IMU timestamp repeats line " + std::to_string(kept.back().line) + "; sample dropped");
      continue;
    }
    kept.push_back(r);
  }
  s.imu_.swap(kept);
}

void assume_imu_noise(Rig& r, text::StreamLogSource* s, std::vector<LogProblem>* problems,
                      const std::string& where) {
  // BMX055 / BMI055 datasheet densities (gyro 0.014 deg/s/sqrt(Hz), accel 150 ug/sqrt(Hz)) and the
  // random walks Kestrel's simulator uses for that part.
  r.imu.gyro_noise_density_rad_s_sqrthz = 2.4434609527920612e-04;
  r.imu.gyro_random_walk_rad_s2_sqrthz = 2.0e-05;
  r.imu.acc_noise_density_mps2_sqrthz = 1.4709975e-03;
  r.imu.acc_random_walk_mps3_sqrthz = 3.2028384781419539e-03;
  LogProblem p{where, "assumed",
               "no IMU noise densities in the dataset: BMI055/BMX055-class figures assumed (gyro 2.44e-4 "
               "rad/s/sqrt(Hz), "
               "acc 1.47e-3 m/s^2/sqrt(Hz)); give yours with --rig"};
  if (s) s->problems_.push_back(p);
  if (problems) problems->push_back(p);
}

YAML::Node load_cv_yaml(const std::string& path) {
  std::vector<std::string> lines;
  if (!text::read_lines(path, lines)) throw std::runtime_error(path + ": cannot read");
  std::string body;
  for (size_t i = 0; i < lines.size(); ++i) {
    // OpenCV writes "%YAML:1.0", which yaml-cpp rejects; blanked, so error lines stay right.
    if (i == 0 && lines[i].rfind("%YAML", 0) == 0) {
      body += "\n";
      continue;
    }
    body += lines[i] + "\n";
  }
  try {
    return YAML::Load(body);
  } catch (const YAML::Exception& e) {
    throw std::runtime_error(path + ":" + std::to_string(e.mark.line + 1) + ": YAML syntax error: " + e.msg);
  }
}

bool image_size(const std::string& path, int& w, int& h) {
  try {
    const cv::Mat m = cv::imread(path, cv::IMREAD_UNCHANGED);
    if (m.empty()) return false;
    w = m.cols;
    h = m.rows;
    return true;
  } catch (const cv::Exception&) {
    return false;
  }
}

}  // namespace kestrel::drivers::ds

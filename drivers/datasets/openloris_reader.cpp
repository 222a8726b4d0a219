// OpenLORIS-Scene reader (the RealSense D435i streams of a sequence folder).
#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <queue>
#include <stdexcept>

#include "dataset_common.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "text_log.hpp"

namespace kestrel::drivers {
namespace {

using ds::Listed;
using text::StreamLogSource;

constexpr const char* kColorFrame = "d400_color_optical_frame";

// An OpenCV matrix node (!!opencv-matrix {rows, cols, data}) or a plain list.
bool cv_numbers(const YAML::Node& n, std::vector<double>& out) {
  const YAML::Node d = n && n.IsMap() ? n["data"] : n;
  if (!d || !d.IsSequence()) return false;
  out.clear();
  for (size_t i = 0; i < d.size(); ++i) {
    double v = 0;
    if (!d[i].IsScalar() || !text::parse_f64(d[i].Scalar(), v) || !std::isfinite(v)) return false;
    out.push_back(v);
  }
  return true;
}

bool cv_number(const YAML::Node& n, double& v) {
  return n && n.IsScalar() && text::parse_f64(n.Scalar(), v) && std::isfinite(v);
}

// trans_matrix.yaml as a graph: each entry gives T_parent_child; T_a_b is
// found by walking the entries (either direction) from a to b.
class FrameGraph {
 public:
  void load(const std::string& path, StreamLogSource& s) {
    const YAML::Node root = ds::load_cv_yaml(path);
    const YAML::Node list = root["trans_matrix"];
    if (!list || !list.IsSequence())
      throw std::runtime_error(path + ": trans_matrix: missing (expected a list)");
    for (size_t i = 0; i < list.size(); ++i) {
      const YAML::Node e = list[i];
      const std::string field = "trans_matrix[" + std::to_string(i) + "]";
      std::vector<double> m;
      if (!e.IsMap() || !e["parent_frame"] || !e["child_frame"] || !cv_numbers(e["matrix"], m) ||
          m.size() != 16) {
        s.problem(path, "bad-row",
                  field + ": expected parent_frame, child_frame and a 4x4 matrix; entry skipped");
        continue;
      }
      Mat4d t;
      std::copy(m.begin(), m.end(), t.begin());
      const std::string a = e["parent_frame"].Scalar(), b = e["child_frame"].Scalar();
      edges_[a].push_back({b, t});
      edges_[b].push_back({a, ds::mat_inv(t)});
    }
  }
  bool has(const std::string& f) const { return edges_.count(f) > 0; }
  // T_ab (b coordinates into a).
  bool find(const std::string& a, const std::string& b, Mat4d& T_ab) const {
    if (a == b) return T_ab = kIdentity4, true;
    std::map<std::string, Mat4d> seen{{a, kIdentity4}};
    std::queue<std::string> q;
    q.push(a);
    while (!q.empty()) {
      const std::string f = q.front();
      q.pop();
      const auto it = edges_.find(f);
      if (it == edges_.end()) continue;
      for (const auto& [to, T_f_to] : it->second) {
        if (seen.count(to)) continue;
        seen[to] = ds::mat_mul(seen[f], T_f_to);
        if (to == b) return T_ab = seen[to], true;
        q.push(to);
      }
    }
    return false;
  }
  std::string first_of(std::initializer_list<const char*> names) const {
    for (const char* n : names)
      if (has(n)) return n;
    return "";
  }

 private:
  std::map<std::string, std::vector<std::pair<std::string, Mat4d>>> edges_;
};

struct Vec3Row {
  int64_t t_ns;
  Vec3d v;
  uint64_t line;
};

std::vector<Vec3Row> read_vec3(const std::string& path, const char* what, StreamLogSource& s) {
  std::vector<Vec3Row> out;
  std::vector<std::string> lines;
  if (!text::read_lines(path, lines)) return out;
  for (size_t i = 0; i < lines.size(); ++i) {
    const std::string t = text::trim(lines[i]);
    if (t.empty() || t[0] == '#') continue;
    const std::string where = path + ":" + std::to_string(i + 1);
    const auto f = text::split_ws(t);
    Vec3Row r{0, {}, i + 1};
    bool ok = f.size() == 4 && text::parse_seconds_ns(f[0], r.t_ns);
    for (int k = 0; k < 3 && ok; ++k) ok = text::parse_f64(f[k + 1], r.v[k]) && std::isfinite(r.v[k]);
    if (!ok) {
      s.problem(where, "bad-row",
                std::string("expected \"t[s] ") + what + "\" (4 finite numbers), got " +
                    std::to_string(f.size()) + " fields");
      continue;
    }
    out.push_back(r);
  }
  for (size_t i = 1; i < out.size(); ++i) {
    if (out[i].t_ns <= out[i - 1].t_ns) {
      s.problem(path + ":" + std::to_string(out[i].line),
                out[i].t_ns == out[i - 1].t_ns ? "duplicate" : "time-order",
                "timestamp not after the previous row's; sorted, repeats dropped");
    }
  }
  std::stable_sort(out.begin(), out.end(),
                   [](const Vec3Row& a, const Vec3Row& b) { return a.t_ns < b.t_ns; });
  std::vector<Vec3Row> u;
  for (const auto& r : out)
    if (u.empty() || u.back().t_ns != r.t_ns) u.push_back(r);
  return u;
}

// Stamps are any int64 a file can spell (a sign included), so the span of
// two of them may not fit int64: differences saturate (found by fuzz_openloris_folder).
int64_t span_ns(int64_t later, int64_t earlier) {
  int64_t d = 0;
  return __builtin_sub_overflow(later, earlier, &d) ? std::numeric_limits<int64_t>::max() : d;
}

double rate_of(const std::vector<Vec3Row>& v) {
  return v.size() > 1 && v.back().t_ns > v.front().t_ns
             ? static_cast<double>(v.size() - 1) * 1e9 /
                   static_cast<double>(span_ns(v.back().t_ns, v.front().t_ns))
             : 0.0;
}

int64_t median_dt(const std::vector<Vec3Row>& v) {
  std::vector<int64_t> d;
  for (size_t i = 1; i < v.size(); ++i) d.push_back(span_ns(v[i].t_ns, v[i - 1].t_ns));
  if (d.empty()) return 0;
  std::nth_element(d.begin(), d.begin() + static_cast<long>(d.size() / 2), d.end());
  return d[d.size() / 2];
}

}  // namespace

bool is_openloris_folder(const std::string& path) {
  return text::is_file(path + "/color.txt") || text::is_file(path + "/d400_accelerometer.txt") ||
         (text::is_file(path + "/sensors.yaml") && text::is_file(path + "/trans_matrix.yaml"));
}

OpenLorisReader::OpenLorisReader(const std::string& path_in, const Rig* rig) {
  const std::string path = text::strip_trailing_slashes(path_in);
  StreamLogSource& s = *impl_;
  if (!text::is_dir(path)) throw std::runtime_error(path + ": no such folder");
  if (!is_openloris_folder(path)) {
    throw std::runtime_error(
        path + ": not an OpenLORIS-Scene folder (no color.txt, d400_accelerometer.txt or sensors.yaml)");
  }

  Rig r = rig ? *rig : Rig{};
  if (!rig) r.name = text::file_name(path);

  // ---- sensors.yaml: the colour camera (intrinsics stored fx, cx, fy, cy) and the IMU rates.
  const std::string sensors = path + "/sensors.yaml";
  double acc_fps = 0, gyro_fps = 0;
  bool have_intrinsics = false;
  if (text::is_file(sensors)) {
    try {
      const YAML::Node y = ds::load_cv_yaml(sensors);
      const YAML::Node c = y[kColorFrame];
      if (c && c.IsMap()) {
        std::vector<double> k, d;
        double w = 0, h = 0, fps = 0;
        if (!cv_numbers(c["intrinsics"], k) || k.size() != 4 || k[0] <= 0 || k[2] <= 0) {
          throw std::runtime_error(sensors + ": " + kColorFrame +
                                   ".intrinsics: expected 4 numbers fx cx fy cy (fx, fy > 0)");
        }
        if (!cv_number(c["width"], w) || !cv_number(c["height"], h) || w < 1 || h < 1 || w > 32768 ||
            h > 32768) {
          throw std::runtime_error(sensors + ": " + kColorFrame +
                                   ".width/height: expected two positive integers");
        }
        r.rgb.width = static_cast<int>(w);
        r.rgb.height = static_cast<int>(h);
        r.rgb.fx = k[0], r.rgb.cx = k[1], r.rgb.fy = k[2], r.rgb.cy = k[3];
        const std::string model = c["distortion_model"] && c["distortion_model"].IsScalar()
                                      ? c["distortion_model"].Scalar()
                                      : "none";
        r.rgb.dist = {};
        if (model == "radial-tangential" || model == "plumb_bob" || model == "radtan") {
          r.rgb.distortion = DistortionModel::kRadTan;
        } else if (model == "equidistant" || model == "Kannala-Brandt") {
          r.rgb.distortion = DistortionModel::kEquidistant;
        } else if (model == "none") {
          r.rgb.distortion = DistortionModel::kNone;
        } else {
          throw std::runtime_error(sensors + ": " + kColorFrame + ".distortion_model: \"" + model +
                                   "\" is not supported");
        }
        if (c["distortion_coefficients"]) {
          if (!cv_numbers(c["distortion_coefficients"], d) || d.size() > 5) {
            throw std::runtime_error(sensors + ": " + kColorFrame +
                                     ".distortion_coefficients: expected up to 5 numbers");
          }
          std::copy(d.begin(), d.end(), r.rgb.dist.begin());
        }
        if (cv_number(c["fps"], fps)) r.camera_rate_hz = fps;
        have_intrinsics = true;
      }
      // Depth units: the RealSense z16 unit is 1 mm unless the file says otherwise.
      double scale = 0;
      const YAML::Node dnode = y["d400_depth_optical_frame"];
      if (dnode && dnode.IsMap() && cv_number(dnode["depth_scale"], scale) && scale > 0) {
        r.depth.scale_m_per_unit = scale;
      } else {
        r.depth.scale_m_per_unit = 0.001;
        s.problem(
            sensors, "assumed",
            "no d400_depth_optical_frame.depth_scale: aligned depth taken as 1 mm per unit (RealSense z16)");
      }
      if (y["d400_accelerometer"]) cv_number(y["d400_accelerometer"]["fps"], acc_fps);
      if (y["d400_gyroscope"]) cv_number(y["d400_gyroscope"]["fps"], gyro_fps);
    } catch (const YAML::Exception& e) {
      // A node of the wrong kind (a scalar where a map belongs) surfaces here.
      throw std::runtime_error(sensors + ": unexpected structure: " + e.what());
    }
  } else {
    r.depth.scale_m_per_unit = 0.001;
  }
  if (!have_intrinsics) {
    if (!rig) {
      throw std::runtime_error(sensors + ": " + kColorFrame +
                               ".intrinsics missing: camera intrinsics (fx fy cx cy, width, height) are "
                               "needed; give them with --rig FILE.yaml");
    }
    s.problem(sensors, "missing-file",
              std::string("no ") + kColorFrame + " entry: camera intrinsics taken from the --rig file");
  }

  // ---- trans_matrix.yaml: extrinsics. The body frame is the gyroscope's.
  FrameGraph g;
  const std::string trans = path + "/trans_matrix.yaml";
  if (text::is_file(trans)) {
    try {
      g.load(trans, s);
    } catch (const YAML::Exception& e) {
      throw std::runtime_error(trans + ": unexpected structure: " + e.what());
    }
  }
  const std::string gyro_frame =
      g.first_of({"d400_gyroscope", "d400_gyro_optical_frame", "d400_imu_optical_frame", "d400_imu"});
  const std::string acc_frame =
      g.first_of({"d400_accelerometer", "d400_accel_optical_frame", "d400_imu_optical_frame", "d400_imu"});
  Mat4d T_BC;
  if (!gyro_frame.empty() && g.find(gyro_frame, kColorFrame, T_BC)) {
    r.T_BC = T_BC;
    r.T_BI = kIdentity4;
  } else if (!rig) {
    throw std::runtime_error(trans + ": no transform chain from the IMU (d400_gyroscope) to " + kColorFrame +
                             ": T_BC missing; give it with --rig FILE.yaml");
  } else {
    s.problem(trans, "missing-file", "no IMU-to-camera chain: T_BC taken from the --rig file");
  }
  // Accelerometer axes into the gyroscope frame (rotation only: the lever arm
  // between two sensors on one chip is negligible).
  Mat4d T_GA = kIdentity4;
  if (!acc_frame.empty() && !gyro_frame.empty() && !g.find(gyro_frame, acc_frame, T_GA)) T_GA = kIdentity4;

  // ---- images: color.txt + aligned_depth.txt (depth registered to colour).
  const std::string color_txt = path + "/color.txt", depth_txt = path + "/aligned_depth.txt";
  const auto rgb = ds::read_list(color_txt, s);
  std::vector<Listed> depth;
  if (text::is_file(depth_txt)) {
    depth = ds::read_list(depth_txt, s);
  } else if (text::is_file(path + "/depth.txt")) {
    s.problem(path + "/depth.txt", "unregistered",
              "depth.txt is not registered to colour; only aligned_depth.txt is replayed");
  }
  const auto depth_of = ds::associate(rgb, depth, 20'000'000, pairs_);
  ds::add_pairs(path, rgb, color_txt, depth, depth_txt, depth_of, s);
  if (r.camera_rate_hz <= 0 && rgb.size() > 1 && rgb.back().t_ns > rgb.front().t_ns) {
    r.camera_rate_hz = static_cast<double>(rgb.size() - 1) * 1e9 /
                       static_cast<double>(span_ns(rgb.back().t_ns, rgb.front().t_ns));
  }

  // ---- IMU: merge the two streams at the faster one's stamps.
  const std::string acc_txt = path + "/d400_accelerometer.txt", gyro_txt = path + "/d400_gyroscope.txt";
  const auto acc = read_vec3(acc_txt, "ax ay az", s);
  const auto gyr = read_vec3(gyro_txt, "gx gy gz", s);
  if (!acc.empty() && !gyr.empty()) {
    const double ra = acc_fps > 0 ? acc_fps : rate_of(acc), rg = gyro_fps > 0 ? gyro_fps : rate_of(gyr);
    const bool gyro_fast = rg >= ra;
    const auto& fast = gyro_fast ? gyr : acc;
    const auto& slow = gyro_fast ? acc : gyr;
    imu_file_ = gyro_fast ? gyro_txt : acc_txt;
    // Interpolating across a gap would invent motion: a bracket wider than 4 slow periods is not bridged.
    const int64_t slow_dt = std::max<int64_t>(median_dt(slow), 1);
    const int64_t max_gap =
        slow_dt > std::numeric_limits<int64_t>::max() / 4 ? std::numeric_limits<int64_t>::max() : 4 * slow_dt;
    size_t j = 0, outside = 0, gap = 0;
    uint32_t seq = 0;
    for (const auto& f : fast) {
      if (f.t_ns < slow.front().t_ns || f.t_ns > slow.back().t_ns) {
        ++outside;
        continue;
      }
      while (j + 1 < slow.size() && slow[j + 1].t_ns <= f.t_ns) ++j;
      Vec3d v;
      if (slow[j].t_ns == f.t_ns) {
        v = slow[j].v;
      } else {
        const auto& a = slow[j];
        const auto& b = slow[j + 1];
        if (span_ns(b.t_ns, a.t_ns) > max_gap) {
          ++gap;
          continue;
        }
        const double u =
            static_cast<double>(span_ns(f.t_ns, a.t_ns)) / static_cast<double>(span_ns(b.t_ns, a.t_ns));
        for (int k = 0; k < 3; ++k) v[k] = a.v[k] + u * (b.v[k] - a.v[k]);
      }
      ImuSample m;
      m.t_ns = m.t_recv_ns = f.t_ns;
      m.seq = seq++;
      const Vec3d& gv = gyro_fast ? f.v : v;
      const Vec3d& av = gyro_fast ? v : f.v;
      m.gyro_rps = gv;
      for (int k = 0; k < 3; ++k)
        m.acc_mps2[k] = T_GA[k * 4] * av[0] + T_GA[k * 4 + 1] * av[1] + T_GA[k * 4 + 2] * av[2];
      s.imu_.push_back({m, f.line});
    }
    imu_dropped_ = outside + gap;
    if (outside > 0) {
      s.problem(imu_file_, "imu-merge",
                std::to_string(outside) + " samples outside the " +
                    (gyro_fast ? "accelerometer" : "gyroscope") +
                    " stream's time span; dropped (no extrapolation)");
    }
    if (gap > 0) {
      s.problem(imu_file_, "imu-merge",
                std::to_string(gap) + " samples inside a gap of the slower stream (> 4 periods); dropped");
    }
    if (!rig || r.imu_rate_hz <= 0) r.imu_rate_hz = gyro_fast ? rg : ra;
    if (!rig) ds::assume_imu_noise(r, &s, nullptr, sensors);
  } else if (!acc.empty() || !gyr.empty()) {
    s.problem(acc.empty() ? acc_txt : gyro_txt, "missing-file",
              "one IMU stream only: no IMU samples replayed");
  }

  // ---- ground truth: base_link in the world; Kestrel's is the body: T_WB = T_W,base * T_base,B.
  const std::string gt_txt = path + "/groundtruth.txt";
  if (text::is_file(gt_txt)) {
    gt_file_ = gt_txt;
    ds::read_tum_poses(gt_txt, s, s.gt_);
    Mat4d T_base_B;
    if (!gyro_frame.empty() && g.find("base_link", gyro_frame, T_base_B)) {
      for (auto& row : s.gt_) row.value = ds::compose(row.value, T_base_B);
    } else {
      s.problem(gt_txt, "assumed",
                "no base_link-to-IMU chain in trans_matrix.yaml: ground truth kept as base_link's pose");
    }
  }
  s.rig_ = r;
  s.order_streams(imu_file_, gt_file_);
}

}  // namespace kestrel::drivers

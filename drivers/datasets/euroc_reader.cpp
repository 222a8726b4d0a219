// EuRoC MAV reader: the ASL folder layout (mav0/<sensor>/data.csv) and the
// flat layout of ../shared/data/euroc/<seq>/ (imu0.csv, gt_*.csv, *_sensor.yaml).
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <cstdint>
#include <stdexcept>

#include "asl_tables.hpp"
#include "dataset_common.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "text_log.hpp"

namespace kestrel::drivers {
namespace {

using text::ImageEntry;
using text::StreamLogSource;

double yaml_number(const YAML::Node& n, const std::string& path, const std::string& field) {
  double v = 0;
  if (!n || !n.IsScalar() || !text::parse_f64(n.Scalar(), v) || !std::isfinite(v))
    throw std::runtime_error(path + ": " + field + ": expected a finite number");
  return v;
}

std::vector<double> yaml_numbers(const YAML::Node& n, const std::string& path, const std::string& field,
                                 size_t min_n, size_t max_n) {
  if (!n || !n.IsSequence() || n.size() < min_n || n.size() > max_n) {
    throw std::runtime_error(path + ": " + field + ": expected a list of " + std::to_string(min_n) +
                             (min_n == max_n ? "" : ".." + std::to_string(max_n)) + " numbers");
  }
  std::vector<double> v;
  for (size_t i = 0; i < n.size(); ++i)
    v.push_back(yaml_number(n[i], path, field + "[" + std::to_string(i) + "]"));
  return v;
}

void camera_from_sensor(const std::string& path, Rig& rig) {
  const EurocSensorYaml y = read_euroc_sensor_yaml(path);
  if (!y.resolution_px) throw std::runtime_error(path + ": resolution: expected a list of 2 numbers");
  if (!y.intrinsics_px) throw std::runtime_error(path + ": intrinsics: expected a list of 4 numbers");
  rig.rgb.width = (*y.resolution_px)[0];
  rig.rgb.height = (*y.resolution_px)[1];
  rig.rgb.fx = (*y.intrinsics_px)[0];
  rig.rgb.fy = (*y.intrinsics_px)[1];
  rig.rgb.cx = (*y.intrinsics_px)[2];
  rig.rgb.cy = (*y.intrinsics_px)[3];
  rig.rgb.distortion = y.distortion;
  rig.rgb.dist = {};
  for (size_t i = 0; i < y.distortion_coefficients.size(); ++i)
    rig.rgb.dist[i] = y.distortion_coefficients[i];
  rig.T_BC = y.T_BS;
  if (y.rate_hz) rig.camera_rate_hz = *y.rate_hz;
}

// cam1 of an ASL folder: the right camera of a stereo pair (rig.stereo).
void right_camera_from_sensor(const std::string& path, Rig& rig) {
  const EurocSensorYaml y = read_euroc_sensor_yaml(path);
  if (!y.resolution_px) throw std::runtime_error(path + ": resolution: expected a list of 2 numbers");
  if (!y.intrinsics_px) throw std::runtime_error(path + ": intrinsics: expected a list of 4 numbers");
  CameraIntrinsics& k = rig.stereo.intrinsics;
  k.width = (*y.resolution_px)[0];
  k.height = (*y.resolution_px)[1];
  k.fx = (*y.intrinsics_px)[0];
  k.fy = (*y.intrinsics_px)[1];
  k.cx = (*y.intrinsics_px)[2];
  k.cy = (*y.intrinsics_px)[3];
  k.distortion = y.distortion;
  k.dist = {};
  for (size_t i = 0; i < y.distortion_coefficients.size(); ++i) k.dist[i] = y.distortion_coefficients[i];
  rig.stereo.T_BC1 = y.T_BS;
  rig.stereo.present = true;
}

void imu_from_sensor(const std::string& path, Rig& rig) {
  const EurocSensorYaml y = read_euroc_sensor_yaml(path);
  rig.T_BI = y.T_BS;
  if (y.rate_hz) rig.imu_rate_hz = *y.rate_hz;
  if (y.gyro_noise_density_rad_s_sqrthz)
    rig.imu.gyro_noise_density_rad_s_sqrthz = *y.gyro_noise_density_rad_s_sqrthz;
  if (y.gyro_random_walk_rad_s2_sqrthz)
    rig.imu.gyro_random_walk_rad_s2_sqrthz = *y.gyro_random_walk_rad_s2_sqrthz;
  if (y.acc_noise_density_mps2_sqrthz)
    rig.imu.acc_noise_density_mps2_sqrthz = *y.acc_noise_density_mps2_sqrthz;
  if (y.acc_random_walk_mps3_sqrthz) rig.imu.acc_random_walk_mps3_sqrthz = *y.acc_random_walk_mps3_sqrthz;
}

}  // namespace

// The ASL tables, shared with the TUM-VI reader (asl_tables.hpp).
namespace asl {

std::string where(const std::string& file, size_t line) { return file + ":" + std::to_string(line); }

bool data_line(const std::string& l) {
  const std::string t = text::trim(l);
  return !t.empty() && t[0] != '#';
}

void read_imu_csv(const std::string& path, StreamLogSource& s) {
  std::vector<std::string> lines;
  if (!text::read_lines(path, lines)) throw std::runtime_error(path + ": cannot read the IMU table");
  uint32_t seq = 0;
  for (size_t i = 0; i < lines.size(); ++i) {
    if (!data_line(lines[i])) continue;
    const auto f = text::split(lines[i], ',');
    if (f.size() != 7) {
      s.problem(
          where(path, i + 1), "bad-row",
          "expected 7 comma-separated fields (t_ns, gyro x y z, acc x y z), got " + std::to_string(f.size()));
      continue;
    }
    ImuSample m;
    if (!text::parse_i64(f[0], m.t_ns)) {
      s.problem(where(path, i + 1), "bad-row", "timestamp \"" + f[0] + "\" is not an integer of nanoseconds");
      continue;
    }
    double v[6];
    bool ok = true;
    for (int k = 0; k < 6 && ok; ++k) {
      if (!text::parse_f64(f[k + 1], v[k])) {
        s.problem(where(path, i + 1), "bad-row",
                  "field " + std::to_string(k + 2) + " \"" + f[k + 1] + "\" is not a number");
        ok = false;
      }
    }
    if (!ok) continue;
    for (int k = 0; k < 3; ++k) {
      m.gyro_rps[k] = v[k];
      m.acc_mps2[k] = v[k + 3];
    }
    bool finite = true;
    for (double x : v) finite = finite && std::isfinite(x);
    if (!finite) {
      // Kept and flagged: the estimator counts and survives such samples.
      m.flags |= kImuNonFinite;
      s.problem(where(path, i + 1), "non-finite", "NaN or Inf in an IMU sample; kept with kImuNonFinite");
    }
    m.t_recv_ns = m.t_ns;
    m.seq = seq++;
    s.imu_.push_back({m, i + 1});
  }
}

// t_ns, p_WB xyz, q_WB wxyz [, v_WB xyz [, biases...]] (8, 11 or 17 columns).
void read_gt_csv(const std::string& path, StreamLogSource& s) {
  std::vector<std::string> lines;
  if (!text::read_lines(path, lines)) {
    s.problem(path, "missing-file", "cannot read the ground-truth table");
    return;
  }
  for (size_t i = 0; i < lines.size(); ++i) {
    if (!data_line(lines[i])) continue;
    const auto f = text::split(lines[i], ',');
    if (f.size() < 8) {
      s.problem(where(path, i + 1), "bad-row",
                "expected at least 8 comma-separated fields (t_ns, p_WB x y z, q_WB w x y z), got " +
                    std::to_string(f.size()));
      continue;
    }
    GroundTruthPose g;
    if (!text::parse_i64(f[0], g.t_ns)) {
      s.problem(where(path, i + 1), "bad-row", "timestamp \"" + f[0] + "\" is not an integer of nanoseconds");
      continue;
    }
    const size_t n = f.size() >= 11 ? 10 : 7;
    double v[10];
    bool ok = true;
    for (size_t k = 0; k < n && ok; ++k) {
      if (!text::parse_f64(f[k + 1], v[k]) || !std::isfinite(v[k])) {
        s.problem(where(path, i + 1), "bad-row",
                  "field " + std::to_string(k + 2) + " \"" + f[k + 1] + "\" is not a finite number");
        ok = false;
      }
    }
    if (!ok) continue;
    const double qn = std::sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5] + v[6] * v[6]);
    if (std::abs(qn - 1.0) > 1e-2) {
      s.problem(where(path, i + 1), "bad-row", "quaternion norm " + text::fmt17(qn) + " is not 1");
      continue;
    }
    g.p_WB = {v[0], v[1], v[2]};
    g.q_WB = {v[3], v[4], v[5], v[6]};
    if (n == 10) {
      g.has_velocity = true;
      g.v_WB = {v[7], v[8], v[9]};
    }
    s.gt_.push_back({g, i + 1});
  }
}

// data.csv of a camera: t_ns, file name; the files live in `data_dir`.
void read_image_csv(const std::string& csv, const std::string& data_dir, StreamLogSource& s,
                    std::vector<ImageEntry>& out) {
  std::vector<std::string> lines;
  if (!text::read_lines(csv, lines)) {
    s.problem(csv, "missing-file", "cannot read the image table");
    return;
  }
  const bool dir_ok = text::is_dir(data_dir);
  size_t listed = 0;
  uint32_t seq = 0;
  for (size_t i = 0; i < lines.size(); ++i) {
    if (!data_line(lines[i])) continue;
    const auto f = text::split(lines[i], ',');
    ImageEntry e;
    if (f.size() != 2 || !text::parse_i64(f[0], e.t_ns) || f[1].empty()) {
      s.problem(where(csv, i + 1), "bad-row", "expected \"t_ns,filename\"");
      continue;
    }
    ++listed;
    e.t_recv_ns = e.t_ns;
    e.seq = seq++;
    e.path = data_dir + "/" + f[1];
    e.where = where(csv, i + 1);
    e.line = i + 1;
    if (!dir_ok) continue;
    if (!text::is_file(e.path)) {
      s.problem(e.where, "missing-file", e.path + " listed but absent; row skipped");
      continue;
    }
    out.push_back(std::move(e));
  }
  if (!dir_ok && listed > 0) {
    s.problem(data_dir, "missing-file",
              "image folder absent: " + std::to_string(listed) + " images listed in " + csv + " skipped");
  }
}

}  // namespace asl

namespace {

using asl::data_line;
using asl::where;

// kestrel_events.csv (written by export_euroc): t_ns,code,text (text may hold commas).
void read_events_csv(const std::string& path, StreamLogSource& s) {
  std::vector<std::string> lines;
  if (!text::read_lines(path, lines)) return;
  for (size_t i = 0; i < lines.size(); ++i) {
    if (!data_line(lines[i])) continue;
    const std::string& l = lines[i];
    const size_t a = l.find(',');
    const size_t b = a == std::string::npos ? a : l.find(',', a + 1);
    Event e;
    int64_t code = 0;
    if (b == std::string::npos || !text::parse_i64(text::trim(l.substr(0, a)), e.t_ns) ||
        !text::parse_i64(text::trim(l.substr(a + 1, b - a - 1)), code) || code < 0 || code > UINT32_MAX) {
      s.problem(where(path, i + 1), "bad-row", "expected \"t_ns,code,text\"");
      continue;
    }
    e.code = static_cast<EventCode>(code);
    e.text = l.substr(b + 1);
    s.events_.push_back({e, i + 1});
  }
}

}  // namespace

EurocSensorYaml read_euroc_sensor_yaml(const std::string& path) {
  const YAML::Node n = ds::load_cv_yaml(path);
  if (!n.IsMap()) throw std::runtime_error(path + ": expected a mapping");
  EurocSensorYaml y;
  // Cameras: both lists are read before either is judged, so a bad number is named first.
  if (n["resolution"] || n["intrinsics"]) {
    const auto res =
        n["resolution"] ? yaml_numbers(n["resolution"], path, "resolution", 2, 2) : std::vector<double>{};
    const auto k =
        n["intrinsics"] ? yaml_numbers(n["intrinsics"], path, "intrinsics", 4, 4) : std::vector<double>{};
    if (!res.empty()) {
      if (res[0] < 1 || res[1] < 1 || res[0] != std::floor(res[0]) || res[1] != std::floor(res[1]) ||
          res[0] > 32768 || res[1] > 32768)
        throw std::runtime_error(path + ": resolution: expected two positive integers");
      y.resolution_px = std::array<int, 2>{static_cast<int>(res[0]), static_cast<int>(res[1])};
    }
    if (!k.empty()) {
      if (k[0] <= 0 || k[1] <= 0) throw std::runtime_error(path + ": intrinsics: focal lengths must be > 0");
      y.intrinsics_px = std::array<double, 4>{k[0], k[1], k[2], k[3]};
    }
  }
  const std::string model =
      n["distortion_model"] && n["distortion_model"].IsScalar() ? n["distortion_model"].Scalar() : "none";
  if (model == "radial-tangential" || model == "radtan") {
    y.distortion = DistortionModel::kRadTan;
  } else if (model == "equidistant") {
    y.distortion = DistortionModel::kEquidistant;
  } else if (model == "none") {
    y.distortion = DistortionModel::kNone;
  } else {
    throw std::runtime_error(
        path + ": distortion_model: expected radial-tangential, equidistant or none, got \"" + model + "\"");
  }
  if (n["distortion_coefficients"]) {
    y.distortion_coefficients =
        yaml_numbers(n["distortion_coefficients"], path, "distortion_coefficients", 0, 5);
  }
  const YAML::Node t = n["T_BS"];
  if (!t || !(t.IsMap() || t.IsSequence()))
    throw std::runtime_error(path + ": T_BS: missing (expected rows, cols, data)");
  const auto d =
      t.IsMap() ? yaml_numbers(t["data"], path, "T_BS.data", 16, 16) : yaml_numbers(t, path, "T_BS", 16, 16);
  for (size_t i = 0; i < 16; ++i) y.T_BS[i] = d[i];
  if (n["rate_hz"]) y.rate_hz = yaml_number(n["rate_hz"], path, "rate_hz");
  const std::pair<const char*, std::optional<double>*> noise[] = {
      {"gyroscope_noise_density", &y.gyro_noise_density_rad_s_sqrthz},
      {"gyroscope_random_walk", &y.gyro_random_walk_rad_s2_sqrthz},
      {"accelerometer_noise_density", &y.acc_noise_density_mps2_sqrthz},
      {"accelerometer_random_walk", &y.acc_random_walk_mps3_sqrthz}};
  for (const auto& [key, dst] : noise)
    if (n[key]) *dst = yaml_number(n[key], path, key);
  return y;
}

bool is_euroc_folder(const std::string& path) {
  return text::is_dir(path + "/mav0") || text::is_file(path + "/imu0/data.csv") ||
         text::is_file(path + "/imu0.csv");
}

EurocReader::EurocReader(const std::string& path_in) {
  const std::string path = text::strip_trailing_slashes(path_in);
  StreamLogSource& s = *impl_;
  std::string root;
  std::string name = text::file_name(path);
  if (text::is_dir(path + "/mav0")) {
    root = path + "/mav0";
  } else if (text::is_file(path + "/imu0/data.csv")) {
    root = path;
    const size_t k = path.find_last_of('/');
    if (text::file_name(path) == "mav0" && k != std::string::npos) name = text::file_name(path.substr(0, k));
  } else if (text::is_file(path + "/imu0.csv")) {
    root = path;
    flat_ = true;
  } else {
    throw std::runtime_error(path + ": not an EuRoC folder (no mav0/, imu0/data.csv or imu0.csv)");
  }

  // The rig: Kestrel's own file when present (it also holds the depth model), else the ASL sensor files.
  const std::string cam_yaml = flat_ ? root + "/cam0_sensor.yaml" : root + "/cam0/sensor.yaml";
  const std::string imu_yaml = flat_ ? root + "/imu0_sensor.yaml" : root + "/imu0/sensor.yaml";
  if (text::is_file(root + "/kestrel_rig.yaml")) {
    s.rig_ = load_rig_file(root + "/kestrel_rig.yaml");
  } else {
    s.rig_.name = name;
    if (text::is_file(cam_yaml)) {
      camera_from_sensor(cam_yaml, s.rig_);
    } else {
      s.problem(cam_yaml, "missing-file", "no camera calibration; the rig keeps default intrinsics");
    }
    if (text::is_file(imu_yaml)) {
      imu_from_sensor(imu_yaml, s.rig_);
    } else {
      s.problem(imu_yaml, "missing-file", "no IMU noise figures; the rig keeps defaults");
    }
    // A second camera makes the folder a stereo log: depth from matching cam0 against cam1 (docs/stereo.md).
    const std::string cam1_yaml = root + "/cam1/sensor.yaml";
    if (!flat_ && text::is_file(root + "/cam1/data.csv")) {
      if (text::is_file(cam1_yaml)) {
        right_camera_from_sensor(cam1_yaml, s.rig_);
      } else {
        s.problem(cam1_yaml, "missing-file",
                  "cam1 images without a calibration; replayed as a monocular log");
      }
    }
  }

  imu_file_ = flat_ ? root + "/imu0.csv" : root + "/imu0/data.csv";
  asl::read_imu_csv(imu_file_, s);

  if (flat_) {
    // The official estimate carries v_WB (and biases); the 20 Hz body file exists for every sequence.
    for (const char* f : {"gt_official_200hz.csv", "gt_body_20hz.csv"}) {
      if (text::is_file(root + "/" + f)) {
        gt_file_ = root + "/" + f;
        break;
      }
    }
  } else {
    if (text::is_file(root + "/cam0/data.csv")) {
      asl::read_image_csv(root + "/cam0/data.csv", root + "/cam0/data", s, s.rgb_);
    } else {
      s.problem(root + "/cam0/data.csv", "missing-file", "no cam0 table; no images replayed");
    }
    // Only with a stereo rig (cam1/sensor.yaml or the rig file's stereo:): uncalibrated images are no use.
    if (s.rig_.stereo.present && text::is_file(root + "/cam1/data.csv"))
      asl::read_image_csv(root + "/cam1/data.csv", root + "/cam1/data", s, s.right_);
    if (text::is_file(root + "/depth0/data.csv"))
      asl::read_image_csv(root + "/depth0/data.csv", root + "/depth0/data", s, s.depth_);
    if (text::is_file(root + "/state_groundtruth_estimate0/data.csv"))
      gt_file_ = root + "/state_groundtruth_estimate0/data.csv";
    if (text::is_file(root + "/kestrel_events.csv")) read_events_csv(root + "/kestrel_events.csv", s);
  }
  if (!gt_file_.empty()) asl::read_gt_csv(gt_file_, s);
  s.order_streams(imu_file_, gt_file_);
}

}  // namespace kestrel::drivers

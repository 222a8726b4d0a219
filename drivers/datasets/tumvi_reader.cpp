// TUM-VI reader: the "dataset-<name>_512_16" export (mav0/ as EuRoC's ASL
// layout, the Kalibr camera chain in dso/camchain.yaml, ground truth from the
// motion capture in mav0/mocap0/data.csv). docs/datasets.md, docs/stereo.md.
#include <algorithm>
#include <cstdint>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "asl_tables.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/kalibr.hpp"
#include "text_log.hpp"

namespace kestrel::drivers {
namespace {

std::string read_text(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error(path + ": cannot open");
  std::ostringstream s;
  s << f.rdbuf();
  return s.str();
}

// Kalibr's importer wants an IMU file; without dso/imu_config.yaml the base
// rig's figures stand in, written in Kalibr's keys (and reported by the caller).
std::string default_imu_yaml(const Rig& base) {
  std::ostringstream s;
  s.precision(17);
  s << "accelerometer_noise_density: " << base.imu.acc_noise_density_mps2_sqrthz << "\n"
    << "accelerometer_random_walk: " << base.imu.acc_random_walk_mps3_sqrthz << "\n"
    << "gyroscope_noise_density: " << base.imu.gyro_noise_density_rad_s_sqrthz << "\n"
    << "gyroscope_random_walk: " << base.imu.gyro_random_walk_rad_s2_sqrthz << "\n"
    << "update_rate: " << base.imu_rate_hz << "\n";
  return s.str();
}

// Each right image should have a left one at the same stamp (TUM-VI's cameras
// are triggered together); those that do not are named here, and the replay
// counts and drops them (ReplaySource: right_unpaired).
void check_pairs(text::StreamLogSource& s, int64_t tolerance_ns) {
  std::vector<int64_t> left;
  left.reserve(s.rgb_.size());
  for (const auto& e : s.rgb_) left.push_back(e.t_ns);
  std::sort(left.begin(), left.end());
  std::vector<int64_t> right;
  right.reserve(s.right_.size());
  auto has = [tolerance_ns](const std::vector<int64_t>& v, int64_t t) {
    const auto it = std::lower_bound(v.begin(), v.end(), t - tolerance_ns);
    return it != v.end() && *it <= t + tolerance_ns;
  };
  size_t unmatched = 0;
  constexpr size_t kNamed = 10;  // then one summary line: a shifted table must not flood the report
  for (const auto& e : s.right_) {
    right.push_back(e.t_ns);
    if (has(left, e.t_ns)) continue;
    if (++unmatched <= kNamed) {
      s.problem(e.where, "stamp-mismatch",
                "right image at " + std::to_string(e.t_ns) + " ns has no left image within " +
                    std::to_string(tolerance_ns / 1000) + " us; it will be dropped");
    }
  }
  if (unmatched > kNamed) {
    s.problem("cam1/data.csv", "stamp-mismatch",
              std::to_string(unmatched) + " right images in all have no left image");
  }
  std::sort(right.begin(), right.end());
  size_t lonely = 0;
  std::string first;
  for (const auto& e : s.rgb_)
    if (!has(right, e.t_ns) && ++lonely == 1) first = e.where;
  if (lonely > 0) {
    s.problem(first, "missing-right",
              std::to_string(lonely) +
                  " left images (the first here) have no right image; they are tracked "
                  "without stereo depth");
  }
}

}  // namespace

bool is_tumvi_folder(const std::string& path_in) {
  const std::string path = text::strip_trailing_slashes(path_in);
  return text::is_dir(path + "/mav0") &&
         (text::is_file(path + "/dso/camchain.yaml") || text::is_dir(path + "/mav0/mocap0"));
}

TumviReader::TumviReader(const std::string& path_in) {
  const std::string path = text::strip_trailing_slashes(path_in);
  if (!text::is_dir(path + "/mav0")) throw std::runtime_error(path + ": not a TUM-VI folder (no mav0/)");
  text::StreamLogSource& s = *impl_;
  const std::string root = path + "/mav0";

  // The rig: the Kalibr chain TUM-VI ships for DSO (cam0 left, cam1 right,
  // equidistant); the rates are the dataset's (20 Hz cameras, 200 Hz IMU).
  Rig base;
  base.name = text::file_name(path);
  base.camera_rate_hz = 20.0;
  base.imu_rate_hz = 200.0;
  // Without dso/imu_config.yaml: the BMI160 figures TUM-VI's calibration states
  // (the values of that file), not a zero the importer would refuse.
  base.imu.acc_noise_density_mps2_sqrthz = 0.0028;
  base.imu.acc_random_walk_mps3_sqrthz = 0.00086;
  base.imu.gyro_noise_density_rad_s_sqrthz = 0.00016;
  base.imu.gyro_random_walk_rad_s2_sqrthz = 0.000022;
  camchain_file_ = path + "/dso/camchain.yaml";
  const std::string imu_yaml = path + "/dso/imu_config.yaml";
  if (text::is_file(camchain_file_)) {
    std::string imu_text, imu_name = imu_yaml;
    if (text::is_file(imu_yaml)) {
      imu_text = read_text(imu_yaml);
    } else {
      s.problem(imu_yaml, "missing-file", "no IMU noise figures; TUM-VI's published BMI160 figures are used");
      imu_text = default_imu_yaml(base);
      imu_name = "TUM-VI's BMI160 figures";
    }
    // A malformed chain throws, naming the file and the field (a guess at the
    // calibration would replay without saying it is wrong).
    s.rig_ =
        import_kalibr_text(read_text(camchain_file_), camchain_file_, imu_text, imu_name, "cam0", base).rig;
    s.rig_.name = base.name;
    if (!s.rig_.stereo.present)
      s.problem(camchain_file_, "no-cam1", "the chain has no cam1; replayed as a monocular log");
  } else {
    s.rig_ = base;
    s.problem(camchain_file_, "missing-file",
              "no camera calibration; the rig keeps default intrinsics and the log replays without stereo");
  }

  imu_file_ = root + "/imu0/data.csv";
  asl::read_imu_csv(imu_file_, s);
  if (text::is_file(root + "/cam0/data.csv")) {
    asl::read_image_csv(root + "/cam0/data.csv", root + "/cam0/data", s, s.rgb_);
  } else {
    s.problem(root + "/cam0/data.csv", "missing-file", "no cam0 table; no images replayed");
  }
  if (s.rig_.stereo.present) {
    if (text::is_file(root + "/cam1/data.csv")) {
      asl::read_image_csv(root + "/cam1/data.csv", root + "/cam1/data", s, s.right_);
    } else {
      s.problem(root + "/cam1/data.csv", "missing-file", "no cam1 table; tracked without stereo depth");
    }
  }
  for (const char* gt : {"/mocap0/data.csv", "/state_groundtruth_estimate0/data.csv"}) {
    if (text::is_file(root + gt)) {
      gt_file_ = root + gt;
      break;
    }
  }
  if (!gt_file_.empty()) asl::read_gt_csv(gt_file_, s);
  s.order_streams(imu_file_, gt_file_);
  if (s.rig_.stereo.present && !s.rgb_.empty()) check_pairs(s, kStereoPairToleranceNs);
}

}  // namespace kestrel::drivers

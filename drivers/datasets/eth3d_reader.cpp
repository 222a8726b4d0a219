// ETH3D SLAM reader (TUM-style RGB-D folder plus calibration.txt and imu.txt).
#include <algorithm>
#include <cctype>
#include <cmath>
#include <optional>
#include <stdexcept>

#include "dataset_common.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "text_log.hpp"

namespace kestrel::drivers {
namespace {

using ds::Listed;
using text::StreamLogSource;

// "fx fy cx cy" on the first data line; throws naming file:line.
void read_calibration(const std::string& path, Rig& r) {
  std::vector<std::string> lines;
  if (!text::read_lines(path, lines)) throw std::runtime_error(path + ": cannot read");
  for (size_t i = 0; i < lines.size(); ++i) {
    const std::string t = text::trim(lines[i]);
    if (t.empty() || t[0] == '#') continue;
    const auto f = text::split_ws(t);
    double v[4];
    bool ok = f.size() == 4;
    for (int k = 0; k < 4 && ok; ++k) ok = text::parse_f64(f[k], v[k]) && std::isfinite(v[k]);
    if (!ok || v[0] <= 0 || v[1] <= 0) {
      throw std::runtime_error(path + ":" + std::to_string(i + 1) +
                               ": expected \"fx fy cx cy\" (4 finite numbers, focal lengths > 0)");
    }
    r.rgb.fx = v[0], r.rgb.fy = v[1], r.rgb.cx = v[2], r.rgb.cy = v[3];
    // ETH3D publishes undistorted pinhole images.
    r.rgb.distortion = DistortionModel::kNone;
    r.rgb.dist = {};
    return;
  }
  throw std::runtime_error(path + ": no \"fx fy cx cy\" line: camera intrinsics missing");
}

// Column order of imu.txt: gyro then accelerometer, unless a '#' header names
// the accelerometer first.
bool accel_first(const std::vector<std::string>& lines) {
  for (const auto& l : lines) {
    const std::string t = text::trim(l);
    if (t.empty()) continue;
    if (t[0] != '#') return false;
    std::string low = t;
    for (char& c : low) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    auto first_of = [&](std::initializer_list<const char*> keys) {
      size_t best = std::string::npos;
      for (const char* k : keys) best = std::min(best, low.find(k));
      return best;
    };
    const size_t a = first_of({"acc", "linear", " ax"});
    const size_t g = first_of({"gyr", "angular", " gx", " wx"});
    if (a != std::string::npos && g != std::string::npos) return a < g;
  }
  return false;
}

void read_imu(const std::string& path, StreamLogSource& s) {
  std::vector<std::string> lines;
  if (!text::read_lines(path, lines)) return;
  const bool acc_first = accel_first(lines);
  uint32_t seq = 0;
  for (size_t i = 0; i < lines.size(); ++i) {
    const std::string t = text::trim(lines[i]);
    if (t.empty() || t[0] == '#') continue;
    const std::string where = path + ":" + std::to_string(i + 1);
    const auto f = text::split_ws(t);
    ImuSample m;
    if (f.size() != 7 || !text::parse_seconds_ns(f[0], m.t_ns)) {
      s.problem(where, "bad-row",
                "expected \"t[s] gx gy gz ax ay az\" (7 fields), got " + std::to_string(f.size()));
      continue;
    }
    double v[6];
    bool ok = true;
    for (int k = 0; k < 6 && ok; ++k) ok = text::parse_f64(f[k + 1], v[k]);
    if (!ok) {
      s.problem(where, "bad-row", "an IMU field is not a number");
      continue;
    }
    for (int k = 0; k < 3; ++k) {
      m.gyro_rps[k] = acc_first ? v[k + 3] : v[k];
      m.acc_mps2[k] = acc_first ? v[k] : v[k + 3];
    }
    bool finite = true;
    for (double x : v) finite = finite && std::isfinite(x);
    if (!finite) {
      m.flags |= kImuNonFinite;
      s.problem(where, "non-finite", "NaN or Inf in an IMU sample; kept with kImuNonFinite");
    }
    m.t_recv_ns = m.t_ns;
    m.seq = seq++;
    s.imu_.push_back({m, i + 1});
  }
}

double rate_hz(int64_t first, int64_t last, size_t n) {
  return n > 1 && last > first ? static_cast<double>(n - 1) * 1e9 / static_cast<double>(last - first) : 0.0;
}

}  // namespace

bool is_eth3d_folder(const std::string& path) {
  // rgb.txt alone is TUM; ETH3D adds calibration.txt (and associated.txt, imu.txt).
  return text::is_file(path + "/rgb.txt") &&
         (text::is_file(path + "/calibration.txt") || text::is_file(path + "/associated.txt") ||
          text::is_file(path + "/imu.txt"));
}

Eth3dReader::Eth3dReader(const std::string& path_in, const Rig* rig) {
  const std::string path = text::strip_trailing_slashes(path_in);
  StreamLogSource& s = *impl_;
  if (!text::is_dir(path)) throw std::runtime_error(path + ": no such folder");
  if (!text::is_file(path + "/rgb.txt") && !text::is_file(path + "/associated.txt"))
    throw std::runtime_error(path + ": not an ETH3D SLAM folder (no rgb.txt or associated.txt)");

  // Kestrel's own exports leave the full rig beside the ETH3D files (as export_euroc does): it stands in
  // for --rig when none is given.
  std::optional<Rig> own;
  if (!rig && text::is_file(path + "/kestrel_rig.yaml")) {
    own = load_rig_file(path + "/kestrel_rig.yaml");
    rig = &*own;
  }
  Rig r = rig ? *rig : Rig{};
  if (!rig) r.name = text::file_name(path);
  const std::string calib = path + "/calibration.txt";
  if (text::is_file(calib)) {
    read_calibration(calib, r);
  } else if (!rig) {
    throw std::runtime_error(
        calib + ": missing: camera intrinsics (fx fy cx cy) are needed; give them with --rig FILE.yaml");
  } else {
    s.problem(calib, "missing-file", "no calibration.txt: camera intrinsics taken from the --rig file");
  }
  // ETH3D depth: 16-bit PNG, 5000 units per metre, registered to the colour camera.
  r.depth.scale_m_per_unit = 1.0 / 5000.0;

  // Frames: associated.txt pairs when present, else rgb.txt and depth.txt associated by time.
  std::vector<Listed> rgb, depth;
  std::string rgb_list = path + "/rgb.txt", depth_list = path + "/depth.txt";
  std::vector<long> depth_of;
  const std::string assoc = path + "/associated.txt";
  if (text::is_file(assoc)) {
    rgb_list = depth_list = assoc;
    std::vector<std::string> lines;
    text::read_lines(assoc, lines);
    for (size_t i = 0; i < lines.size(); ++i) {
      const std::string t = text::trim(lines[i]);
      if (t.empty() || t[0] == '#') continue;
      const auto f = text::split_ws(t);
      Listed a, b;
      if (f.size() != 4 || !text::parse_seconds_ns(f[0], a.t_ns) || !text::parse_seconds_ns(f[2], b.t_ns)) {
        s.problem(assoc + ":" + std::to_string(i + 1), "bad-row",
                  "expected \"t_rgb[s] rgb_file t_depth[s] depth_file\", got " + std::to_string(f.size()) +
                      " fields");
        continue;
      }
      a.file = f[1], b.file = f[3];
      a.line = b.line = i + 1;
      if (!rgb.empty() && a.t_ns <= rgb.back().t_ns) {
        s.problem(assoc + ":" + std::to_string(i + 1), a.t_ns == rgb.back().t_ns ? "duplicate" : "time-order",
                  a.t_ns == rgb.back().t_ns ? "colour timestamp repeats the previous row's; row skipped"
                                            : "colour timestamp before the previous row's; row skipped");
        continue;
      }
      rgb.push_back(a);
      depth.push_back(b);
      depth_of.push_back(static_cast<long>(depth.size() - 1));
    }
    pairs_ = depth.size();
  } else {
    rgb = ds::read_list(rgb_list, s);
    if (text::is_file(depth_list)) {
      depth = ds::read_list(depth_list, s);
    } else {
      s.problem(depth_list, "missing-file", "no depth listing; colour only");
    }
    depth_of = ds::associate(rgb, depth, 20'000'000, pairs_);
  }
  ds::add_pairs(path, rgb, rgb_list, depth, depth_list, depth_of, s);

  // The image size is not in calibration.txt: the first colour image says it.
  if (!s.rgb_.empty()) {
    int w = 0, h = 0;
    if (ds::image_size(s.rgb_.front().path, w, h)) {
      r.rgb.width = w, r.rgb.height = h;
    } else {
      s.problem(s.rgb_.front().where, "bad-image",
                s.rgb_.front().path + ": cannot be decoded to read the image size");
    }
  }
  if (!rig && !rgb.empty()) r.camera_rate_hz = rate_hz(rgb.front().t_ns, rgb.back().t_ns, rgb.size());

  const std::string imu_txt = path + "/imu.txt";
  if (text::is_file(imu_txt)) {
    imu_file_ = imu_txt;
    read_imu(imu_txt, s);
    if (!rig) {
      // The RGB-D download has no camera-IMU extrinsic; without a rig the IMU is taken to sit at the camera.
      s.problem(calib, "assumed",
                "no camera-IMU extrinsic in the ETH3D folder: T_BC = identity assumed (give --rig)");
      if (!s.imu_.empty())
        r.imu_rate_hz = rate_hz(s.imu_.front().value.t_ns, s.imu_.back().value.t_ns, s.imu_.size());
      ds::assume_imu_noise(r, &s, nullptr, imu_txt);
    }
  }

  // groundtruth.txt: the colour camera's pose T_WC; Kestrel's ground truth is the body: T_WB = T_WC * T_CB.
  const std::string gt_txt = path + "/groundtruth.txt";
  if (text::is_file(gt_txt)) {
    gt_file_ = gt_txt;
    ds::read_tum_poses(gt_txt, s, s.gt_);
    const Mat4d T_CB = ds::mat_inv(r.T_BC);
    for (auto& g : s.gt_) g.value = ds::compose(g.value, ds::is_identity(r.T_BC) ? kIdentity4 : T_CB);
  }
  s.rig_ = r;
  s.order_streams(imu_file_, gt_file_);
  if (!imu_file_.empty()) ds::drop_duplicate_imu(s, imu_file_);
}

}  // namespace kestrel::drivers

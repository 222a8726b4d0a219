// TUM RGB-D reader (rgb.txt, depth.txt, groundtruth.txt, accelerometer.txt).
#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "dataset_common.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "text_log.hpp"

namespace kestrel::drivers {
namespace {

using text::ImageEntry;
using text::StreamLogSource;

using ds::Listed;
using ds::read_list;

// Published calibrations of the three Kinects (TUM RGB-D "intrinsic calibration" page);
// depth is registered to the colour camera and scaled 5000 units per metre.
Rig default_rig(const std::string& name) {
  Rig r;
  r.name = name;
  r.rgb.width = 640;
  r.rgb.height = 480;
  r.rgb.distortion = DistortionModel::kRadTan;
  if (name.find("freiburg2") != std::string::npos) {
    r.rgb.fx = 520.9, r.rgb.fy = 521.0, r.rgb.cx = 325.1, r.rgb.cy = 249.7;
    r.rgb.dist = {0.2312, -0.7849, -0.0033, -0.0001, 0.9172};
  } else if (name.find("freiburg3") != std::string::npos) {
    // fr3 images were recorded already undistorted.
    r.rgb.fx = 535.4, r.rgb.fy = 539.2, r.rgb.cx = 320.1, r.rgb.cy = 247.6;
    r.rgb.distortion = DistortionModel::kNone;
  } else {
    r.rgb.fx = 517.3, r.rgb.fy = 516.5, r.rgb.cx = 318.6, r.rgb.cy = 255.3;
    r.rgb.dist = {0.2624, -0.9531, -0.0054, 0.0026, 1.1633};
  }
  r.camera_rate_hz = 30;
  r.depth.scale_m_per_unit = 1.0 / 5000.0;
  // No IMU: the body frame is the colour camera, whose pose groundtruth.txt gives.
  r.T_BC = kIdentity4;
  r.imu_rate_hz = 0;
  return r;
}

}  // namespace

bool is_tum_folder(const std::string& path) { return text::is_file(path + "/rgb.txt"); }

TumReader::TumReader(const std::string& path) : TumReader(path, Options{}) {}

TumReader::TumReader(const std::string& path_in, const Options& options) {
  std::string path = path_in;
  while (path.size() > 1 && path.back() == '/') path.pop_back();
  StreamLogSource& s = *impl_;
  if (!is_tum_folder(path)) throw std::runtime_error(path + ": not a TUM RGB-D folder (no rgb.txt)");
  s.rig_ = text::is_file(path + "/kestrel_rig.yaml") ? load_rig_file(path + "/kestrel_rig.yaml")
                                                     : default_rig(text::file_name(path));

  const std::string rgb_txt = path + "/rgb.txt";
  const std::string depth_txt = path + "/depth.txt";
  const auto rgb = read_list(rgb_txt, s);
  const auto depth = text::is_file(depth_txt) ? read_list(depth_txt, s) : std::vector<Listed>{};
  if (!text::is_file(depth_txt)) s.problem(depth_txt, "missing-file", "no depth listing; RGB only");

  // Like TUM's associate.py: candidate pairs within the window, the closest
  // first, each frame used once.
  const std::vector<long> depth_of = ds::associate(rgb, depth, options.max_association_dt_ns, pairs_);
  std::vector<bool> depth_used(depth.size(), false);
  for (long d : depth_of)
    if (d >= 0) depth_used[static_cast<size_t>(d)] = true;

  const bool rgb_dir =
      text::is_dir(path + "/rgb") || rgb.empty() || rgb[0].file.find('/') == std::string::npos;
  const bool depth_dir =
      text::is_dir(path + "/depth") || depth.empty() || depth[0].file.find('/') == std::string::npos;
  size_t rgb_missing = 0, depth_missing = 0;
  auto add = [&](const Listed& l, const std::string& listing, int64_t t_ns, int64_t t_recv_ns, uint32_t seq,
                 bool dir_ok, size_t& missing, std::vector<ImageEntry>& out) {
    ImageEntry e;
    e.t_ns = t_ns;
    e.t_recv_ns = t_recv_ns;
    e.seq = seq;
    e.path = path + "/" + l.file;
    e.where = listing + ":" + std::to_string(l.line);
    e.line = l.line;
    if (!dir_ok) {
      ++missing;
      return;
    }
    if (!text::is_file(e.path)) {
      s.problem(e.where, "missing-file", e.path + " listed but absent; skipped");
      return;
    }
    out.push_back(std::move(e));
  };
  for (size_t r = 0; r < rgb.size(); ++r) {
    add(rgb[r], rgb_txt, rgb[r].t_ns, rgb[r].t_ns, static_cast<uint32_t>(r), rgb_dir, rgb_missing, s.rgb_);
    if (depth_of[r] < 0) {
      if (!depth.empty()) {
        s.problem(rgb_txt + ":" + std::to_string(rgb[r].line), "no-depth",
                  "no depth frame within " + std::to_string(options.max_association_dt_ns / 1000000) +
                      " ms; RGB replayed alone");
      }
      continue;
    }
    // The pair shares the colour time stamp so consumers pair by equal t_ns;
    // the depth frame's own stamp is kept in t_recv_ns.
    const Listed& d = depth[static_cast<size_t>(depth_of[r])];
    add(d, depth_txt, rgb[r].t_ns, d.t_ns, static_cast<uint32_t>(depth_of[r]), depth_dir, depth_missing,
        s.depth_);
  }
  for (size_t d = 0; d < depth.size(); ++d) {
    if (!depth_used[d]) {
      s.problem(depth_txt + ":" + std::to_string(depth[d].line), "unassociated",
                "no RGB frame within the association window; depth frame skipped");
    }
  }
  if (rgb_missing > 0) {
    s.problem(
        path + "/rgb", "missing-file",
        "image folder absent: " + std::to_string(rgb_missing) + " RGB frames listed in rgb.txt skipped");
  }
  if (depth_missing > 0) {
    s.problem(path + "/depth", "missing-file",
              "image folder absent: " + std::to_string(depth_missing) +
                  " depth frames listed in depth.txt skipped");
  }

  // groundtruth.txt: t tx ty tz qx qy qz qw (TUM stores the quaternion x y z w; ours is w x y z).
  const std::string gt_txt = path + "/groundtruth.txt";
  std::vector<std::string> lines;
  if (text::read_lines(gt_txt, lines)) {
    gt_file_ = gt_txt;
    for (size_t i = 0; i < lines.size(); ++i) {
      const std::string t = text::trim(lines[i]);
      if (t.empty() || t[0] == '#') continue;
      const auto f = text::split_ws(t);
      GroundTruthPose g;
      double v[7];
      bool ok = f.size() == 8 && text::parse_seconds_ns(f[0], g.t_ns);
      for (int k = 0; k < 7 && ok; ++k) ok = text::parse_f64(f[k + 1], v[k]) && std::isfinite(v[k]);
      if (!ok) {
        s.problem(gt_txt + ":" + std::to_string(i + 1), "bad-row",
                  "expected \"t[s] tx ty tz qx qy qz qw\" (8 finite numbers)");
        continue;
      }
      const double qn = std::sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5] + v[6] * v[6]);
      if (std::abs(qn - 1.0) > 1e-2) {
        s.problem(gt_txt + ":" + std::to_string(i + 1), "bad-row",
                  "quaternion norm " + text::fmt17(qn) + " is not 1");
        continue;
      }
      g.p_WB = {v[0], v[1], v[2]};
      g.q_WB = {v[6], v[3], v[4], v[5]};
      s.gt_.push_back({g, i + 1});
    }
  }

  // The Kinect's tilt accelerometer has no gyroscope, and ImuSample has no
  // way to say "gyro absent"; replaying zeros or NaNs as rates would lie, so
  // the samples are counted and reported, not replayed.
  const std::string acc_txt = path + "/accelerometer.txt";
  if (text::read_lines(acc_txt, lines)) {
    size_t n = 0;
    for (const auto& l : lines) {
      const std::string t = text::trim(l);
      if (!t.empty() && t[0] != '#') ++n;
    }
    s.problem(acc_txt, "no-gyro",
              std::to_string(n) +
                  " accelerometer-only samples (Kinect tilt sensor, no gyroscope): not replayed as IMU");
  }
  s.order_streams(imu_file_, gt_file_);
}

}  // namespace kestrel::drivers

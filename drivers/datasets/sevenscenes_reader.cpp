// Microsoft 7-Scenes reader (frame-NNNNNN.{color.png|color.jpg, depth.png, pose.txt}).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <optional>
#include <stdexcept>

#include "dataset_common.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/depth_registration.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "text_log.hpp"

namespace kestrel::drivers {
namespace {

namespace fs = std::filesystem;
using text::StreamLogSource;

std::string frame_stem(const std::string& dir, long i) {
  char b[32];
  std::snprintf(b, sizeof b, "/frame-%06ld", i);
  return dir + b;
}

// "frame-000123.pose.txt" -> 123, else -1.
long frame_index(const std::string& name, std::string& rest) {
  if (name.rfind("frame-", 0) != 0 || name.size() < 13) return -1;
  long v = 0;
  for (size_t k = 6; k < 12; ++k) {
    if (name[k] < '0' || name[k] > '9') return -1;
    v = v * 10 + (name[k] - '0');
  }
  rest = name.substr(12);
  return v;
}

// The depth camera's intrinsics: "fx 0 cx / 0 fy cy / 0 0 1". Throws naming file:line.
CameraIntrinsics read_intrinsics(const std::string& path) {
  std::vector<std::string> lines;
  if (!text::read_lines(path, lines)) throw std::runtime_error(path + ": cannot read");
  double m[9];
  int n = 0;
  size_t line = 0;
  for (size_t i = 0; i < lines.size() && n < 9; ++i) {
    const std::string t = text::trim(lines[i]);
    if (t.empty() || t[0] == '#') continue;
    const auto f = text::split_ws(t);
    line = i + 1;
    if (f.size() != 3) {
      throw std::runtime_error(path + ":" + std::to_string(line) +
                               ": expected 3 numbers per row of the 3x3 camera matrix");
    }
    for (const auto& s : f) {
      if (!text::parse_f64(s, m[n++]) || !std::isfinite(m[n - 1])) {
        throw std::runtime_error(path + ":" + std::to_string(line) + ": \"" + s +
                                 "\" is not a finite number");
      }
    }
  }
  if (n < 9) throw std::runtime_error(path + ": expected a 3x3 camera matrix (3 rows of 3 numbers)");
  if (!(m[0] > 0) || !(m[4] > 0) || m[1] != 0 || m[3] != 0 || m[6] != 0 || m[7] != 0 || m[8] != 1) {
    throw std::runtime_error(path + ":" + std::to_string(line) +
                             ": not a pinhole camera matrix [fx 0 cx; 0 fy cy; 0 0 1] with fx, fy > 0");
  }
  CameraIntrinsics k;
  k.fx = m[0], k.fy = m[4], k.cx = m[2], k.cy = m[5];
  return k;
}

// A 4x4 camera-to-world pose; "" when it is a rigid transform, else what is
// wrong, with the 1-based line it is on in *bad_line.
std::string read_pose(const std::string& path, Mat4d& T, size_t* bad_line) {
  std::vector<std::string> lines;
  *bad_line = 1;
  if (!text::read_lines(path, lines)) return "cannot read";
  int row = 0;
  for (size_t i = 0; i < lines.size() && row < 4; ++i) {
    const std::string t = text::trim(lines[i]);
    if (t.empty()) continue;
    *bad_line = i + 1;
    const auto f = text::split_ws(t);
    if (f.size() != 4) return "expected 4 numbers per row of the 4x4 pose, got " + std::to_string(f.size());
    for (int c = 0; c < 4; ++c) {
      if (!text::parse_f64(f[c], T[4 * row + c]) || !std::isfinite(T[4 * row + c]))
        return "\"" + f[c] + "\" is not a finite number";
    }
    ++row;
  }
  if (row < 4) return "expected 4 rows of the 4x4 pose, got " + std::to_string(row);
  if (T[12] != 0 || T[13] != 0 || T[14] != 0 || T[15] != 1) return "last row must be 0 0 0 1";
  // KinectFusion's rotations are not quite orthonormal (their columns are
  // 6e-5 short of unit length in this sequence): within 1e-3 they are taken
  // as rotations and re-orthonormalised below; a real scale or shear is not.
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) {
      double dot = 0;
      for (int k = 0; k < 3; ++k) dot += T[4 * k + a] * T[4 * k + b];
      if (std::abs(dot - (a == b ? 1.0 : 0.0)) > 1e-3) {
        *bad_line = 1;
        return "not a rigid transform: the rotation's columns are not orthonormal (off by " +
               text::fmt17(dot) + " - " + (a == b ? "1" : "0") + ")";
      }
    }
  }
  const double det = T[0] * (T[5] * T[10] - T[6] * T[9]) - T[1] * (T[4] * T[10] - T[6] * T[8]) +
                     T[2] * (T[4] * T[9] - T[5] * T[8]);
  if (det < 0) {
    *bad_line = 1;
    return "not a rigid transform: the rotation is a reflection (determinant -1)";
  }
  // Re-orthonormalise the 1e-7 print rounding away so consumers get a rotation.
  Quatd q;
  Vec3d p;
  ds::mat_to_pose(T, p, q);
  T = ds::pose_to_mat(p, q);
  return "";
}

// Unit direction of gravity in the poses' world, "gx gy gz" on one or three
// lines. False with *where ("file" or "file:line") and *why when unusable.
bool read_gravity(const std::string& path, Vec3d& g, std::string* where, std::string* why) {
  std::vector<std::string> lines;
  *where = path;
  if (!text::read_lines(path, lines)) {
    *why = "missing";
    return false;
  }
  int n = 0;
  for (size_t i = 0; i < lines.size(); ++i) {
    for (const auto& s : text::split_ws(text::trim(lines[i]))) {
      if (n >= 3 || !text::parse_f64(s, g[n]) || !std::isfinite(g[n])) {
        *where = path + ":" + std::to_string(i + 1);
        *why = "expected three numbers (the direction of gravity), got \"" + s + "\"";
        return false;
      }
      ++n;
    }
  }
  const double norm = n == 3 ? std::sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]) : 0.0;
  if (n != 3 || std::abs(norm - 1.0) > 1e-2) {
    *why = "expected a unit vector of three numbers, got " + std::to_string(n) + " numbers of norm " +
           text::fmt17(norm);
    return false;
  }
  for (double& v : g) v /= norm;
  return true;
}

// R with R g = (0, 0, -1), the smallest such rotation: Kestrel's W has gravity along -z.
Mat4d levelling(const Vec3d& g) {
  const double a[3] = {g[0], g[1], g[2]}, b[3] = {0, 0, -1};
  const double v[3] = {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
  const double c = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const double s2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
  Mat4d T = kIdentity4;
  if (s2 < 1e-24) {
    if (c < 0) T[5] = T[10] = -1;  // gravity along +z: half a turn about x
    return T;
  }
  const double K[9] = {0, -v[2], v[1], v[2], 0, -v[0], -v[1], v[0], 0};
  double K2[9];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j)
      K2[3 * i + j] = K[3 * i] * K[j] + K[3 * i + 1] * K[3 + j] + K[3 * i + 2] * K[6 + j];
  }
  const double f = (1 - c) / s2;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) T[4 * i + j] = (i == j ? 1.0 : 0.0) + K[3 * i + j] + f * K2[3 * i + j];
  return T;
}

// Content hash of a file (FNV-1a 64), to find frames repeated byte for byte.
uint64_t file_hash(const std::string& path, uint64_t& size) {
  std::ifstream f(path, std::ios::binary);
  uint64_t h = 1469598103934665603ull;
  size = 0;
  char buf[65536];
  while (f.read(buf, sizeof buf) || f.gcount() > 0) {
    const std::streamsize n = f.gcount();
    for (std::streamsize i = 0; i < n; ++i) h = (h ^ static_cast<uint8_t>(buf[i])) * 1099511628211ull;
    size += static_cast<uint64_t>(n);
  }
  return h;
}

}  // namespace

// The colour camera of the 7-Scenes Kinect has no published calibration.
// These are the figures the visual relocalisation literature settled on
// (DSAC*/ACE's setup_7scenes.py): focal length 525 px at the image centre,
// and the depth -> colour transform of a Kinect v1 calibrated by LIRIS
// (projet.liris.cnrs.fr/voir/activities-dataset/kinect-calibration.html):
// 2.56 cm along x, under half a degree of rotation.
Rig SevenScenesReader::default_rig(const CameraIntrinsics& depth_intrinsics) {
  Rig r;
  r.name = "7scenes-kinect-v1";
  r.rgb.width = 640;
  r.rgb.height = 480;
  r.rgb.fx = r.rgb.fy = 525.0;
  r.rgb.cx = 320.0;
  r.rgb.cy = 240.0;
  r.camera_rate_hz = 30.0;
  r.depth.scale_m_per_unit = 0.001;
  r.depth.min_range_m = 0.4;  // Kinect v1 (structured light)
  r.depth.max_range_m = 4.5;
  r.depth_camera.present = true;
  r.depth_camera.intrinsics = depth_intrinsics;
  r.depth_camera.T_CD = {9.9996518012567637e-01,
                         2.6765126468950343e-03,
                         -7.9041012313000904e-03,
                         -2.5558943178152542e-02,
                         -2.7409311281316700e-03,
                         9.9996302803027592e-01,
                         -8.1504520778013286e-03,
                         1.0109636268061706e-04,
                         7.8819942130445332e-03,
                         8.1718328771890631e-03,
                         9.9993554558014031e-01,
                         2.0318321729487039e-03,
                         0,
                         0,
                         0,
                         1};
  // Printed to 17 digits but only orthonormal to 1e-5: made exact so the rig's YAML round-trips.
  Quatd q;
  Vec3d p;
  ds::mat_to_pose(r.depth_camera.T_CD, p, q);
  r.depth_camera.T_CD = ds::pose_to_mat(p, q);
  // No IMU: the body frame is the colour camera.
  r.T_BC = kIdentity4;
  r.imu_rate_hz = 0;
  return r;
}

bool is_sevenscenes_folder(const std::string& path) {
  const std::string s = frame_stem(text::strip_trailing_slashes(path), 0);
  return text::is_file(s + ".pose.txt") &&
         (text::is_file(s + ".color.png") || text::is_file(s + ".color.jpg"));
}

SevenScenesReader::SevenScenesReader(const std::string& path, const Rig* rig)
    : SevenScenesReader(path, rig, Options{}) {}

SevenScenesReader::SevenScenesReader(const std::string& path_in, const Rig* rig_in, const Options& opt) {
  const std::string path = text::strip_trailing_slashes(path_in);
  StreamLogSource& s = *impl_;
  if (!text::is_dir(path)) throw std::runtime_error(path + ": no such folder");
  if (!(opt.fps > 0 && opt.fps <= 1000))
    throw std::invalid_argument("7-Scenes reader: --fps must be in (0, 1000]");

  // Frames by index, from every file named frame-NNNNNN.<kind>.
  struct Files {
    std::string colour, depth, pose;
  };
  std::map<long, Files> frames;
  for (const auto& e : fs::directory_iterator(path)) {
    std::string rest;
    const long i = frame_index(e.path().filename().string(), rest);
    if (i < 0) continue;
    Files& f = frames[i];
    if (rest == ".color.png" || rest == ".color.jpg") {
      f.colour = e.path().string();
    } else if (rest == ".depth.png") {
      f.depth = e.path().string();
    } else if (rest == ".pose.txt") {
      f.pose = e.path().string();
    }
  }
  if (frames.empty()) throw std::runtime_error(path + ": not a 7-Scenes folder (no frame-NNNNNN.* files)");

  // Calibration: the depth camera's intrinsics from the folder (the
  // tsdf-fusion layout has them), else 7-Scenes' published figures.
  std::optional<Rig> own;
  if (!rig_in && text::is_file(path + "/kestrel_rig.yaml")) {
    own = load_rig_file(path + "/kestrel_rig.yaml");
    rig_in = &*own;
  }
  const std::string intr = path + "/camera-intrinsics.txt";
  CameraIntrinsics depth_k;
  depth_k.fx = depth_k.fy = 585.0;
  depth_k.cx = 320.0;
  depth_k.cy = 240.0;
  if (text::is_file(intr)) {
    depth_k = read_intrinsics(intr);
  } else {
    s.problem(intr, "assumed",
              "no camera-intrinsics.txt: 7-Scenes' published depth intrinsics (585, 585, 320, 240)");
  }
  Rig r = rig_in ? *rig_in : default_rig(depth_k);
  if (!rig_in) {
    s.problem(
        intr, "assumed",
        "7-Scenes publishes no colour calibration: colour camera 525 px at the image centre and a Kinect v1 "
        "depth -> colour transform (2.6 cm) assumed; the depth is registered to colour with them (--rig to "
        "override)");
  }
  r.camera_rate_hz = opt.fps;

  // Missing numbers and missing files of a frame.
  const long first = frames.begin()->first, last = frames.rbegin()->first;
  for (long i = first; i <= last; ++i) {
    const auto it = frames.find(i);
    if (it == frames.end()) {
      s.problem(frame_stem(path, i) + ".*", "missing-frame",
                "frame " + std::to_string(i) + " absent (no file of it)");
      continue;
    }
    const Files& f = it->second;
    if (f.colour.empty())
      s.problem(frame_stem(path, i) + ".color.png", "missing-file", "no colour image; frame skipped");
    if (f.depth.empty())
      s.problem(frame_stem(path, i) + ".depth.png", "missing-file", "no depth image; colour replayed alone");
    if (f.pose.empty())
      s.problem(frame_stem(path, i) + ".pose.txt", "missing-file", "no pose; no ground truth here");
  }

  // Sizes from the first images; the depth camera's size comes from its images.
  for (const auto& [i, f] : frames) {
    int w = 0, h = 0;
    if (!f.colour.empty() && ds::image_size(f.colour, w, h)) {
      if (!rig_in) {
        r.rgb.width = w, r.rgb.height = h;
      } else if (w != r.rgb.width || h != r.rgb.height) {
        s.problem(f.colour, "bad-image",
                  std::to_string(w) + "x" + std::to_string(h) + " colour image, the rig says " +
                      std::to_string(r.rgb.width) + "x" + std::to_string(r.rgb.height));
      }
      break;
    }
  }
  if (r.depth_camera.present) {
    for (const auto& [i, f] : frames) {
      int w = 0, h = 0;
      if (!f.depth.empty() && ds::image_size(f.depth, w, h)) {
        if (r.depth_camera.intrinsics.width <= 0) r.depth_camera.intrinsics.width = w;
        if (r.depth_camera.intrinsics.height <= 0) r.depth_camera.intrinsics.height = h;
        break;
      }
    }
    // Without a depth image there is nothing to register (and no size to register from).
    if (r.depth_camera.intrinsics.width > 0 && r.rgb.width > 0) {
      registration_ = std::make_unique<DepthRegistration>(r.depth_camera, r.rgb, r.depth.scale_m_per_unit);
      registered_.resize(static_cast<size_t>(r.rgb.width) * static_cast<size_t>(r.rgb.height));
    }
  }

  // Levelled world: gravity along -z.
  Mat4d T_LW = kIdentity4;
  Vec3d g{};
  std::string gwhere, gwhy;
  if (read_gravity(path + "/gravity-direction.txt", g, &gwhere, &gwhy)) {
    T_LW = levelling(g);
  } else {
    s.problem(
        gwhere, gwhy == "missing" ? "missing-file" : "bad-row",
        (gwhy == "missing" ? std::string() : gwhy + "; ") +
            "world frame not levelled: the ground truth's z is not up (an IMU synthesised along it would be "
            "wrong)");
  }
  // The poses are the depth camera's (KinectFusion tracks depth): T_WB = T_WD T_DC T_CB.
  const Mat4d T_DB = ds::mat_mul(r.depth_camera.present ? ds::mat_inv(r.depth_camera.T_CD) : kIdentity4,
                                 ds::mat_inv(r.T_BC));

  // Frames repeated byte for byte: the recorder wrote the previous capture
  // again. A stale image is withheld; a stale depth also withholds the
  // frame's ground truth, which KinectFusion computed from that same depth:
  // it belongs to the previous instant.
  uint64_t prev_c = 0, prev_d = 0, prev_cs = 0, prev_ds = 0;
  long prev_i = -2;
  auto entry = [](const std::string& file, int64_t t_ns, long i) {
    text::ImageEntry e;
    e.t_ns = e.t_recv_ns = t_ns;
    e.seq = static_cast<uint32_t>(i);
    e.path = e.where = file;
    e.line = static_cast<uint64_t>(i);
    return e;
  };
  for (const auto& [i, f] : frames) {
    const int64_t t_ns = static_cast<int64_t>(std::llround(static_cast<double>(i) * 1e9 / opt.fps));
    const bool consecutive = i == prev_i + 1;
    bool stale_depth = false;
    if (!f.colour.empty()) {
      uint64_t sz = 0;
      const uint64_t h = file_hash(f.colour, sz);
      if (consecutive && h == prev_c && sz == prev_cs) {
        ++repeated_colour_;
        s.problem(f.colour, "repeated-colour",
                  "byte-identical to the previous frame's colour image; withheld");
      } else {
        s.rgb_.push_back(entry(f.colour, t_ns, i));
      }
      prev_c = h, prev_cs = sz;
    } else {
      prev_c = prev_cs = 0;
    }
    if (!f.depth.empty()) {
      uint64_t sz = 0;
      const uint64_t h = file_hash(f.depth, sz);
      stale_depth = consecutive && h == prev_d && sz == prev_ds;
      if (stale_depth) {
        ++repeated_depth_;
        s.problem(
            f.depth, "repeated-depth",
            "byte-identical to the previous frame's depth image; withheld, and this frame's ground truth "
            "(KinectFusion's pose from that same depth) with it");
      } else if (!f.colour.empty()) {
        s.depth_.push_back(entry(f.depth, t_ns, i));
      }
      prev_d = h, prev_ds = sz;
    } else {
      prev_d = prev_ds = 0;
    }
    if (!f.pose.empty() && !stale_depth) {
      Mat4d T_WD{};
      size_t bad_line = 0;
      const std::string err = read_pose(f.pose, T_WD, &bad_line);
      if (!err.empty()) {
        s.problem(f.pose + ":" + std::to_string(bad_line), "bad-pose", err + "; no ground truth here");
      } else {
        GroundTruthPose gt;
        gt.t_ns = t_ns;
        ds::mat_to_pose(ds::mat_mul(ds::mat_mul(T_LW, T_WD), T_DB), gt.p_WB, gt.q_WB);
        s.gt_.push_back({gt, static_cast<uint64_t>(i)});
      }
    }
    prev_i = i;
  }
  if (!s.gt_.empty()) gt_file_ = path + "/frame-*.pose.txt";
  s.rig_ = r;
  s.order_streams(imu_file_, gt_file_);
}

SevenScenesReader::~SevenScenesReader() = default;

bool SevenScenesReader::next(LogRecord& out) {
  for (;;) {
    if (!FolderLogSource::next(out)) return false;
    if (out.type != RecordType::kDepth) return true;
    LogImage& img = out.image;
    // 7-Scenes marks no reading with 65535 as well as 0.
    auto* d = reinterpret_cast<uint16_t*>(img.pixels.data());
    const size_t n = static_cast<size_t>(img.width) * static_cast<size_t>(img.height);
    for (size_t k = 0; k < n; ++k)
      if (d[k] == 65535) d[k] = 0;
    if (!registration_) return true;
    if (!registration_->register_into(img.view(), registered_.data(), registration_->colour_width() * 2,
                                      &last_registration_)) {
      // Reported once per image across rewinds, like the decode failures.
      if (img.seq >= unregistered_reported_until_) {
        unregistered_reported_until_ = img.seq + 1;
        const auto& d = impl_->depth_;
        const auto it =
            std::find_if(d.begin(), d.end(), [&](const text::ImageEntry& e) { return e.seq == img.seq; });
        impl_->problem(it != d.end() ? it->where : std::to_string(img.seq), "bad-image",
                       "depth image " + std::to_string(img.width) + "x" + std::to_string(img.height) +
                           " does not match the depth camera (" +
                           std::to_string(registration_->depth_width()) + "x" +
                           std::to_string(registration_->depth_height()) + "); not registered, withheld");
      }
      continue;
    }
    img.width = registration_->colour_width();
    img.height = registration_->colour_height();
    img.pixels.resize(registered_.size() * 2);
    std::copy_n(reinterpret_cast<const uint8_t*>(registered_.data()), img.pixels.size(), img.pixels.data());
    return true;
  }
}

}  // namespace kestrel::drivers

// ROS 1 bag reader and writer over Debian's librosbag (KESTREL_WITH_ROSBAG).
#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <stdexcept>

#include "dataset_common.hpp"
#include "kestrel/drivers/camera_time_shift.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/log_export.hpp"
#include "kestrel/drivers/ros2_msgs.hpp"
#include "text_log.hpp"

#if KESTREL_WITH_ROSBAG
#include <geometry_msgs/PoseStamped.h>
#include <rosbag/bag.h>
#include <rosbag/view.h>
#include <sensor_msgs/CameraInfo.h>
#include <sensor_msgs/Image.h>
#include <sensor_msgs/Imu.h>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#endif

namespace kestrel::drivers {

bool rosbag_built() { return KESTREL_WITH_ROSBAG != 0; }

bool is_rosbag_file(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  char m[13] = {};
  return f.read(m, 13) && std::memcmp(m, "#ROSBAG V2.0\n", 13) == 0;
}

namespace {
[[noreturn]] [[maybe_unused]] void not_built(const std::string& path) {
  throw std::runtime_error(path +
                           ": ROS bag support not built (install librosbag-dev and libsensor-msgs-dev, "
                           "tools/install-deps.sh, and reconfigure with KESTREL_WITH_ROSBAG=ON)");
}
[[maybe_unused]] std::string camera_info_topic(const RosbagTopics& t) {
  if (!t.camera_info.empty()) return t.camera_info;
  const size_t k = t.rgb.find_last_of('/');
  return (k == std::string::npos ? std::string() : t.rgb.substr(0, k)) + "/camera_info";
}
}  // namespace

#if KESTREL_WITH_ROSBAG

namespace {

enum Kind : uint8_t { kImuK = 0, kRgbK = 1, kDepthK = 2, kGtK = 3, kRightK = 4 };

int64_t ns_of(const ros::Time& t) { return static_cast<int64_t>(t.sec) * 1000000000 + t.nsec; }
ros::Time time_of(int64_t t_ns) {
  // ros::Time is unsigned: stamps before 1970 cannot be written.
  if (t_ns < 0) {
    throw std::runtime_error("negative timestamp " + std::to_string(t_ns) +
                             " ns cannot be stored in a ROS bag");
  }
  return ros::Time(static_cast<uint32_t>(t_ns / 1000000000), static_cast<uint32_t>(t_ns % 1000000000));
}

}  // namespace

struct RosbagReader::Impl {
  std::string path;
  RosbagTopics topics;
  Rig rig;
  std::vector<LogProblem> problems;
  rosbag::Bag bag;
  struct Entry {
    int64_t t_ns;
    int64_t t_recv_ns;
    Kind kind;
    uint32_t idx;  // into imu / gt / images
    uint32_t seq;
  };
  std::vector<Entry> entries;
  std::vector<ImuSample> imu;
  std::vector<GroundTruthPose> gt;
  std::vector<rosbag::MessageInstance> images;
  std::vector<std::string> image_where;
  size_t pos = 0;
  size_t images_reported_until = 0, images_seen = 0;

  void problem(std::string where, std::string kind, std::string detail) {
    problems.push_back(LogProblem{std::move(where), std::move(kind), std::move(detail)});
  }

  bool load_image(size_t i, RecordType type, LogImage& img, bool report) {
    sensor_msgs::ImageConstPtr m;
    try {
      if (images[i].isType<sensor_msgs::Image>()) m = images[i].instantiate<sensor_msgs::Image>();
    } catch (const std::exception& e) {
      if (report) problem(image_where[i], "bad-image", std::string("cannot deserialize: ") + e.what());
      return false;
    }
    if (!m) {
      if (report)
        problem(image_where[i], "bad-type", "expected sensor_msgs/Image, got " + images[i].getDataType());
      return false;
    }
    const std::string& enc = m->encoding;
    PixelFormat fmt;
    int in_bpp;
    if (type == RecordType::kDepth) {
      if (enc == "16UC1" || enc == "mono16") {
        fmt = PixelFormat::kDepthU16, in_bpp = 2;
      } else if (enc == "32FC1") {
        fmt = PixelFormat::kDepthU16, in_bpp = 4;
      } else {
        if (report)
          problem(image_where[i], "bad-image", "depth encoding \"" + enc + "\" (expected 16UC1 or 32FC1)");
        return false;
      }
    } else if (enc == "rgb8") {
      fmt = PixelFormat::kRgb8, in_bpp = 3;
    } else if (enc == "bgr8") {
      fmt = PixelFormat::kBgr8, in_bpp = 3;
    } else if (enc == "mono8" || enc == "8UC1") {
      fmt = PixelFormat::kGray8, in_bpp = 1;
    } else {
      if (report) {
        problem(image_where[i], "bad-image",
                "colour encoding \"" + enc + "\" (expected rgb8, bgr8 or mono8)");
      }
      return false;
    }
    const uint64_t w = m->width, h = m->height;
    if (w == 0 || h == 0 || w > 32768 || h > 32768 || m->step < w * in_bpp ||
        m->data.size() < static_cast<uint64_t>(m->step) * h) {
      if (report) {
        problem(image_where[i], "bad-image",
                "size " + std::to_string(w) + "x" + std::to_string(h) + ", step " + std::to_string(m->step) +
                    " and " + std::to_string(m->data.size()) + " data bytes do not agree");
      }
      return false;
    }
    img.width = static_cast<int>(w);
    img.height = static_cast<int>(h);
    img.format = fmt;
    const size_t out_bpp = static_cast<size_t>(bytes_per_pixel(fmt));
    img.pixels.resize(w * h * out_bpp);
    const bool swap = m->is_bigendian != 0;
    for (uint64_t y = 0; y < h; ++y) {
      const uint8_t* src = m->data.data() + y * m->step;
      uint8_t* dst = img.pixels.data() + y * w * out_bpp;
      ros2::image_row_to_log(src, dst, w, static_cast<int>(in_bpp), static_cast<int>(out_bpp), swap);
    }
    return true;
  }
};

RosbagReader::RosbagReader(const std::string& path, const RosbagTopics& topics, const Rig* rig)
    : impl_(std::make_unique<Impl>()) {
  Impl& s = *impl_;
  s.path = path;
  s.topics = topics;
  if (!text::is_file(path)) throw std::runtime_error(path + ": no such file");
  try {
    s.bag.open(path, rosbag::bagmode::Read);
  } catch (const std::exception& e) {
    throw std::runtime_error(path + ": cannot open as a ROS 1 bag: " + e.what());
  }
  const std::string info_topic = camera_info_topic(topics);
  Rig r = rig ? *rig : Rig{};
  if (!rig) r.name = text::file_name(path);
  bool have_info = false;
  std::vector<ds::Listed> rgb_t, depth_t, right_t;  // for association (file = index as text)
  std::vector<uint32_t> rgb_idx, depth_idx, right_idx;
  std::vector<int64_t> rgb_recv, depth_recv, right_recv;
  const std::string right_info_topic = topics.right.empty() ? std::string() : [&] {
    const size_t k = topics.right.find_last_of('/');
    return (k == std::string::npos ? std::string() : topics.right.substr(0, k)) + "/camera_info";
  }();
  bool have_right_info = false;
  double right_baseline_m = 0;
  size_t n_imu = 0, n_skipped = 0;
  // Only an image's header is read now (its stamp); the pixels are read again when replayed.
  auto list_image = [&](const rosbag::MessageInstance& mi, const std::string& where, int64_t t_recv,
                        std::vector<ds::Listed>& t, std::vector<uint32_t>& idx, std::vector<int64_t>& recv) {
    auto m = mi.isType<sensor_msgs::Image>() ? mi.instantiate<sensor_msgs::Image>() : nullptr;
    if (!m) {
      s.problem(where, "bad-type", "expected sensor_msgs/Image, got " + mi.getDataType());
      return false;
    }
    ds::Listed l;
    l.t_ns = ns_of(m->header.stamp);
    l.line = s.images.size();
    t.push_back(l);
    idx.push_back(static_cast<uint32_t>(s.images.size()));
    recv.push_back(t_recv);
    s.images.push_back(mi);
    s.image_where.push_back(where);
    return true;
  };
  try {
    std::vector<std::string> wanted{topics.imu, topics.rgb, topics.depth, info_topic, topics.ground_truth};
    if (!topics.right.empty()) wanted.push_back(topics.right), wanted.push_back(right_info_topic);
    rosbag::View view(s.bag, rosbag::TopicQuery(wanted));
    size_t k = 0;
    for (const rosbag::MessageInstance& mi : view) {
      ++k;
      const std::string& topic = mi.getTopic();
      const std::string where = path + ":" + topic + "#" + std::to_string(k);
      const int64_t t_recv = ns_of(mi.getTime());
      try {
        if (topic == topics.imu) {
          auto m = mi.isType<sensor_msgs::Imu>() ? mi.instantiate<sensor_msgs::Imu>() : nullptr;
          if (!m) {
            s.problem(where, "bad-type", "expected sensor_msgs/Imu, got " + mi.getDataType());
            ++n_skipped;
            continue;
          }
          ImuSample x;
          x.t_ns = ns_of(m->header.stamp);
          x.t_recv_ns = t_recv;
          x.seq = static_cast<uint32_t>(n_imu++);
          x.gyro_rps = {m->angular_velocity.x, m->angular_velocity.y, m->angular_velocity.z};
          x.acc_mps2 = {m->linear_acceleration.x, m->linear_acceleration.y, m->linear_acceleration.z};
          bool finite = true;
          for (int j = 0; j < 3; ++j)
            finite = finite && std::isfinite(x.gyro_rps[j]) && std::isfinite(x.acc_mps2[j]);
          if (!finite) {
            x.flags |= kImuNonFinite;
            s.problem(where, "non-finite", "NaN or Inf in an IMU message; kept with kImuNonFinite");
          }
          s.entries.push_back({x.t_ns, t_recv, kImuK, static_cast<uint32_t>(s.imu.size()), x.seq});
          s.imu.push_back(x);
        } else if (!topics.right.empty() && topic == topics.right) {
          if (!list_image(mi, where, t_recv, right_t, right_idx, right_recv)) ++n_skipped;
        } else if (!topics.right.empty() && topic == right_info_topic) {
          if (have_right_info) continue;
          auto m = mi.isType<sensor_msgs::CameraInfo>() ? mi.instantiate<sensor_msgs::CameraInfo>() : nullptr;
          if (!m || m->K[0] <= 0 || m->K[4] <= 0 || m->width == 0 || m->height == 0) {
            s.problem(where, "bad-row", "the right camera's CameraInfo is not usable; ignored");
            continue;
          }
          CameraIntrinsics& k = r.stereo.intrinsics;
          k.width = static_cast<int>(m->width), k.height = static_cast<int>(m->height);
          k.fx = m->K[0], k.cx = m->K[2], k.fy = m->K[4], k.cy = m->K[5];
          k.dist = {};
          const bool zero = std::all_of(m->D.begin(), m->D.end(), [](double d) { return d == 0; });
          k.distortion = zero                                   ? DistortionModel::kNone
                         : m->distortion_model == "equidistant" ? DistortionModel::kEquidistant
                                                                : DistortionModel::kRadTan;
          if (k.distortion != DistortionModel::kNone)
            for (size_t j = 0; j < std::min<size_t>(5, m->D.size()); ++j) k.dist[j] = m->D[j];
          right_baseline_m = m->P[0] > 0 ? -m->P[3] / m->P[0] : 0.0;
          have_right_info = true;
        } else if (topic == topics.rgb || topic == topics.depth) {
          const bool rgb = topic == topics.rgb;
          if (!list_image(mi, where, t_recv, rgb ? rgb_t : depth_t, rgb ? rgb_idx : depth_idx,
                          rgb ? rgb_recv : depth_recv))
            ++n_skipped;
        } else if (topic == info_topic) {
          if (have_info) continue;
          auto m = mi.isType<sensor_msgs::CameraInfo>() ? mi.instantiate<sensor_msgs::CameraInfo>() : nullptr;
          if (!m) {
            s.problem(where, "bad-type", "expected sensor_msgs/CameraInfo, got " + mi.getDataType());
            continue;
          }
          if (m->K[0] <= 0 || m->K[4] <= 0 || m->width == 0 || m->height == 0 || m->width > 32768 ||
              m->height > 32768) {
            s.problem(where, "bad-row", "CameraInfo without a usable K / size; ignored");
            continue;
          }
          r.rgb.width = static_cast<int>(m->width);
          r.rgb.height = static_cast<int>(m->height);
          r.rgb.fx = m->K[0], r.rgb.cx = m->K[2], r.rgb.fy = m->K[4], r.rgb.cy = m->K[5];
          r.rgb.dist = {};
          const std::string& dm = m->distortion_model;
          const bool zero = std::all_of(m->D.begin(), m->D.end(), [](double d) { return d == 0; });
          if (zero) {
            r.rgb.distortion = DistortionModel::kNone;
          } else if (dm == "plumb_bob" || dm == "rational_polynomial") {
            r.rgb.distortion = DistortionModel::kRadTan;
          } else if (dm == "equidistant") {
            r.rgb.distortion = DistortionModel::kEquidistant;
          } else {
            s.problem(where, "bad-row",
                      "distortion model \"" + dm + "\" not supported; taken as undistorted");
            r.rgb.distortion = DistortionModel::kNone;
          }
          if (r.rgb.distortion != DistortionModel::kNone) {
            for (size_t j = 0; j < std::min<size_t>(5, m->D.size()); ++j) r.rgb.dist[j] = m->D[j];
            if (m->D.size() > 5)
              s.problem(where, "bad-row", "only the first 5 distortion coefficients are used");
          }
          have_info = true;
        } else if (topic == topics.ground_truth) {
          auto m = mi.isType<geometry_msgs::PoseStamped>() ? mi.instantiate<geometry_msgs::PoseStamped>()
                                                           : nullptr;
          if (!m) {
            s.problem(where, "bad-type", "expected geometry_msgs/PoseStamped, got " + mi.getDataType());
            continue;
          }
          GroundTruthPose g;
          g.t_ns = ns_of(m->header.stamp);
          g.p_WB = {m->pose.position.x, m->pose.position.y, m->pose.position.z};
          g.q_WB = {m->pose.orientation.w, m->pose.orientation.x, m->pose.orientation.y,
                    m->pose.orientation.z};
          const double qn = std::sqrt(g.q_WB[0] * g.q_WB[0] + g.q_WB[1] * g.q_WB[1] + g.q_WB[2] * g.q_WB[2] +
                                      g.q_WB[3] * g.q_WB[3]);
          if (!(std::abs(qn - 1.0) <= 1e-2)) {
            s.problem(where, "bad-row", "quaternion norm " + text::fmt17(qn) + " is not 1");
            continue;
          }
          s.entries.push_back({g.t_ns, t_recv, kGtK, static_cast<uint32_t>(s.gt.size()), 0});
          s.gt.push_back(g);
        }
      } catch (const std::exception& e) {
        s.problem(where, "bad-payload", std::string("cannot deserialize: ") + e.what());
        ++n_skipped;
      }
    }
  } catch (const std::exception& e) {
    throw std::runtime_error(path + ": cannot read the bag: " + e.what());
  }

  if (!have_info) {
    if (!rig) {
      throw std::runtime_error(
          path + ": no sensor_msgs/CameraInfo on " + info_topic +
          ": camera intrinsics (fx fy cx cy, width, height) missing; give them with --rig FILE.yaml "
          "or name the topic with --camera-info-topic");
    }
    s.problem(path + ":" + info_topic, "missing-file",
              "no CameraInfo: camera intrinsics taken from the --rig file");
  }
  // A stereo pair: --rig's stereo: section wins; else the right CameraInfo, placed by P's baseline
  // (a ROS 1 bag's tf is not read: the rotation between the cameras is taken as none, and said).
  if (!right_t.empty() && !(rig && rig->stereo.present)) {
    if (!have_right_info || !(right_baseline_m > 0)) {
      s.problem(path + ":" + right_info_topic, "missing-file",
                "no CameraInfo with a baseline (P[3] = -fx * baseline) for the right images of " +
                    topics.right + ": replayed as a monocular log (give the stereo rig with --rig)");
      right_t.clear(), right_idx.clear(), right_recv.clear();
      r.stereo = StereoCamera{};
    } else {
      Mat4d T_C0C1 = kIdentity4;
      T_C0C1[3] = right_baseline_m;
      r.stereo.T_BC1 = ds::mat_mul(r.T_BC, T_C0C1);
      r.stereo.present = true;
      s.problem(
          path + ":" + right_info_topic, "assumed",
          "the right camera placed by its CameraInfo's baseline (" + text::fmt17(right_baseline_m) +
              " m along x), rotation identity: ROS 1 tf is not read (give --rig for a calibrated pair)");
    }
  } else if (!topics.right.empty() && right_t.empty()) {
    s.problem(path + ":" + topics.right, "missing-file", "no right images on this topic");
  }
  // Depth from a bag: 16UC1 is millimetres (REP 118) and 32FC1 metres is converted to millimetres.
  r.depth.scale_m_per_unit = 0.001;

  // Colour/depth pairs share the colour stamp, as in the folder readers.
  auto sort_by_t = [](std::vector<ds::Listed>& l, std::vector<uint32_t>& idx, std::vector<int64_t>& recv) {
    std::vector<size_t> o(l.size());
    for (size_t i = 0; i < o.size(); ++i) o[i] = i;
    std::stable_sort(o.begin(), o.end(), [&](size_t a, size_t b) { return l[a].t_ns < l[b].t_ns; });
    std::vector<ds::Listed> l2;
    std::vector<uint32_t> i2;
    std::vector<int64_t> r2;
    for (size_t i : o) l2.push_back(l[i]), i2.push_back(idx[i]), r2.push_back(recv[i]);
    l.swap(l2), idx.swap(i2), recv.swap(r2);
  };
  sort_by_t(rgb_t, rgb_idx, rgb_recv);
  sort_by_t(depth_t, depth_idx, depth_recv);
  size_t pairs = 0;
  const auto depth_of = ds::associate(rgb_t, depth_t, 20'000'000, pairs);
  std::vector<bool> used(depth_t.size(), false);
  for (size_t i = 0; i < rgb_t.size(); ++i) {
    if (i > 0 && rgb_t[i].t_ns == rgb_t[i - 1].t_ns) {
      s.problem(s.image_where[rgb_idx[i]], "duplicate",
                "colour stamp repeats the previous frame's; frame dropped");
      continue;
    }
    s.entries.push_back({rgb_t[i].t_ns, rgb_recv[i], kRgbK, rgb_idx[i], static_cast<uint32_t>(i)});
    if (depth_of[i] >= 0) {
      const size_t d = static_cast<size_t>(depth_of[i]);
      used[d] = true;
      s.entries.push_back({rgb_t[i].t_ns, depth_t[d].t_ns, kDepthK, depth_idx[d], static_cast<uint32_t>(d)});
    }
  }
  if (!right_t.empty()) {
    sort_by_t(right_t, right_idx, right_recv);
    size_t right_pairs = 0;
    const auto right_of = ds::associate(rgb_t, right_t, 20'000'000, right_pairs);
    for (size_t i = 0; i < rgb_t.size(); ++i) {
      if ((i > 0 && rgb_t[i].t_ns == rgb_t[i - 1].t_ns) || right_of[i] < 0) continue;
      const size_t q = static_cast<size_t>(right_of[i]);
      s.entries.push_back({rgb_t[i].t_ns, right_t[q].t_ns, kRightK, right_idx[q], static_cast<uint32_t>(q)});
    }
    if (right_pairs < right_t.size()) {
      s.problem(path + ":" + topics.right, "unassociated",
                std::to_string(right_t.size() - right_pairs) +
                    " right images without a left image within 20 ms; skipped");
    }
  }
  const size_t unassoc = static_cast<size_t>(std::count(used.begin(), used.end(), false));
  if (unassoc > 0) {
    s.problem(path + ":" + topics.depth, "unassociated",
              std::to_string(unassoc) + " depth images without a colour image within 20 ms; skipped");
  }
  if (rgb_t.empty()) s.problem(path + ":" + topics.rgb, "missing-file", "no colour images on this topic");

  // Camera stamps onto the IMU's clock (the rig's time_offset_cam_imu_ns).
  for (auto& e : s.entries) {
    if (e.kind == kRgbK || e.kind == kDepthK || e.kind == kRightK)
      e.t_ns = camera_stamp_on_imu_clock(r, e.t_ns);
  }
  // Replayed in stamp order; at equal stamps IMU, colour, depth, ground truth.
  size_t late = 0;
  for (size_t i = 1; i < s.entries.size(); ++i) {
    if (s.entries[i].kind == kImuK && s.entries[i - 1].kind == kImuK &&
        s.entries[i].t_ns < s.entries[i - 1].t_ns)
      ++late;
  }
  if (late > 0) {
    s.problem(path + ":" + topics.imu, "time-order",
              std::to_string(late) + " IMU messages stamped before the previous one; replayed sorted");
  }
  std::stable_sort(s.entries.begin(), s.entries.end(), [](const Impl::Entry& a, const Impl::Entry& b) {
    return a.t_ns != b.t_ns ? a.t_ns < b.t_ns : a.kind < b.kind;
  });
  // Two IMU samples at one instant would give a zero time step.
  std::vector<Impl::Entry> kept;
  kept.reserve(s.entries.size());
  int64_t last_imu = INT64_MIN;
  size_t dups = 0;
  for (const auto& e : s.entries) {
    if (e.kind == kImuK) {
      if (e.t_ns == last_imu) {
        ++dups;
        continue;
      }
      last_imu = e.t_ns;
    }
    kept.push_back(e);
  }
  if (dups > 0) {
    s.problem(path + ":" + topics.imu, "duplicate",
              std::to_string(dups) + " IMU messages repeat a stamp; dropped");
  }
  s.entries.swap(kept);

  if (!s.imu.empty() && !rig) {
    s.problem(path + ":" + topics.imu, "assumed",
              "no camera-IMU extrinsic read from the bag: T_BC = identity assumed (give --rig)");
  }
  if (!rig) {
    auto rate = [](int64_t a, int64_t b, size_t n) {
      return n > 1 && b > a ? (n - 1) * 1e9 / static_cast<double>(b - a) : 0.0;
    };
    if (!s.imu.empty()) {
      ds::assume_imu_noise(r, nullptr, &s.problems, path + ":" + topics.imu);
      int64_t lo = INT64_MAX, hi = INT64_MIN;
      for (const auto& m : s.imu) lo = std::min(lo, m.t_ns), hi = std::max(hi, m.t_ns);
      r.imu_rate_hz = rate(lo, hi, s.imu.size());
    }
    if (!rgb_t.empty()) r.camera_rate_hz = rate(rgb_t.front().t_ns, rgb_t.back().t_ns, rgb_t.size());
  }
  s.rig = r;
}

RosbagReader::~RosbagReader() = default;
const Rig& RosbagReader::rig() const { return impl_->rig; }
const std::vector<LogProblem>& RosbagReader::problems() const { return impl_->problems; }
void RosbagReader::rewind() {
  impl_->pos = 0;
  impl_->images_seen = 0;
}

bool RosbagReader::next(LogRecord& out) {
  Impl& s = *impl_;
  while (s.pos < s.entries.size()) {
    const Impl::Entry& e = s.entries[s.pos++];
    out.offset = s.pos;
    switch (e.kind) {
      case kImuK:
        out.type = RecordType::kImu;
        out.imu = s.imu[e.idx];
        return true;
      case kGtK:
        out.type = RecordType::kGroundTruth;
        out.gt = s.gt[e.idx];
        return true;
      case kRgbK:
      case kDepthK:
      case kRightK: {
        ++s.images_seen;
        const bool report = s.images_seen > s.images_reported_until;
        if (report) s.images_reported_until = s.images_seen;
        out.type = e.kind == kRgbK     ? RecordType::kRgb
                   : e.kind == kDepthK ? RecordType::kDepth
                                       : RecordType::kRight;
        // The right image decodes as the left one does.
        if (!s.load_image(e.idx, e.kind == kDepthK ? RecordType::kDepth : RecordType::kRgb, out.image,
                          report))
          continue;
        out.image.t_ns = e.t_ns;
        out.image.t_recv_ns = e.t_recv_ns;
        out.image.seq = e.seq;
        out.image.exposure_us = 0;
        return true;
      }
    }
  }
  return false;
}

ExportStats export_rosbag(LogSource& src, const std::string& path, const RosbagTopics& topics) {
  rosbag::Bag bag;
  try {
    bag.open(path, rosbag::bagmode::Write);
  } catch (const std::exception& e) {
    throw std::runtime_error(path + ": cannot create: " + e.what());
  }
  const Rig& rig = src.rig();
  const std::string info_topic = camera_info_topic(topics);
  ExportStats st;
  uint32_t seq_img = 0;
  src.rewind();
  LogRecord r;
  try {
    while (src.next(r)) {
      switch (r.type) {
        case RecordType::kImu: {
          sensor_msgs::Imu m;
          m.header.stamp = time_of(r.imu.t_ns);
          m.header.seq = r.imu.seq;
          m.header.frame_id = "imu";
          m.orientation_covariance[0] = -1;  // no orientation estimate
          m.angular_velocity.x = r.imu.gyro_rps[0], m.angular_velocity.y = r.imu.gyro_rps[1];
          m.angular_velocity.z = r.imu.gyro_rps[2];
          m.linear_acceleration.x = r.imu.acc_mps2[0], m.linear_acceleration.y = r.imu.acc_mps2[1];
          m.linear_acceleration.z = r.imu.acc_mps2[2];
          bag.write(topics.imu, m.header.stamp, m);
          ++st.imu;
          break;
        }
        case RecordType::kRgb:
        case RecordType::kDepth: {
          const LogImage& im = r.image;
          sensor_msgs::Image m;
          m.header.stamp = time_of(im.t_ns);
          m.header.seq = im.seq;
          m.header.frame_id = "camera_color_optical_frame";
          m.width = static_cast<uint32_t>(im.width);
          m.height = static_cast<uint32_t>(im.height);
          m.is_bigendian = 0;
          if (r.type == RecordType::kDepth) {
            m.encoding = "16UC1";
            m.step = m.width * 2;
            m.data.resize(static_cast<size_t>(m.step) * m.height);
            // Bags hold millimetres; other scales are converted.
            const double k = rig.depth.scale_m_per_unit * 1000.0;
            for (size_t i = 0; i < static_cast<size_t>(im.width) * im.height; ++i) {
              uint16_t v;
              std::memcpy(&v, im.pixels.data() + 2 * i, 2);
              if (k != 1.0) {
                const double mm = std::round(v * k);
                v = mm > 0 && mm <= 65535 ? static_cast<uint16_t>(mm) : 0;
              }
              std::memcpy(m.data.data() + 2 * i, &v, 2);
            }
            bag.write(topics.depth, m.header.stamp, m);
            ++st.depth;
            break;
          }
          cv::Mat rgb;
          switch (im.format) {
            case PixelFormat::kGray8:
              m.encoding = "mono8";
              break;
            case PixelFormat::kRgb8:
              m.encoding = "rgb8";
              break;
            case PixelFormat::kBgr8:
              m.encoding = "bgr8";
              break;
            case PixelFormat::kYuyv:
              cv::cvtColor(cv::Mat(im.height, im.width, CV_8UC2, const_cast<uint8_t*>(im.pixels.data())), rgb,
                           cv::COLOR_YUV2RGB_YUYV);
              m.encoding = "rgb8";
              break;
            case PixelFormat::kDepthU16:
              throw std::runtime_error("a colour record holds depth pixels");
          }
          const int bpp = m.encoding == "mono8" ? 1 : 3;
          m.step = m.width * static_cast<uint32_t>(bpp);
          if (rgb.empty()) {
            m.data = im.pixels;
          } else {
            m.data.assign(rgb.data, rgb.data + static_cast<size_t>(m.step) * m.height);
          }
          bag.write(topics.rgb, m.header.stamp, m);
          sensor_msgs::CameraInfo ci;
          ci.header = m.header;
          ci.width = static_cast<uint32_t>(rig.rgb.width > 0 ? rig.rgb.width : im.width);
          ci.height = static_cast<uint32_t>(rig.rgb.height > 0 ? rig.rgb.height : im.height);
          ci.K = {rig.rgb.fx, 0, rig.rgb.cx, 0, rig.rgb.fy, rig.rgb.cy, 0, 0, 1};
          ci.R = {1, 0, 0, 0, 1, 0, 0, 0, 1};
          ci.P = {rig.rgb.fx, 0, rig.rgb.cx, 0, 0, rig.rgb.fy, rig.rgb.cy, 0, 0, 0, 1, 0};
          if (rig.rgb.distortion == DistortionModel::kEquidistant) {
            ci.distortion_model = "equidistant";
            ci.D.assign(rig.rgb.dist.begin(), rig.rgb.dist.begin() + 4);
          } else {
            ci.distortion_model = "plumb_bob";
            ci.D.assign(rig.rgb.dist.begin(), rig.rgb.dist.end());
          }
          bag.write(info_topic, m.header.stamp, ci);
          ++st.rgb;
          ++seq_img;
          break;
        }
        case RecordType::kGroundTruth: {
          geometry_msgs::PoseStamped m;
          m.header.stamp = time_of(r.gt.t_ns);
          m.header.frame_id = "world";
          m.pose.position.x = r.gt.p_WB[0], m.pose.position.y = r.gt.p_WB[1],
          m.pose.position.z = r.gt.p_WB[2];
          m.pose.orientation.w = r.gt.q_WB[0], m.pose.orientation.x = r.gt.q_WB[1];
          m.pose.orientation.y = r.gt.q_WB[2], m.pose.orientation.z = r.gt.q_WB[3];
          bag.write(topics.ground_truth, m.header.stamp, m);
          ++st.ground_truth;
          break;
        }
        case RecordType::kEvent:
          break;  // no ROS message for it
        case RecordType::kRight: {
          // A stereo log's right image, with a CameraInfo whose P carries the baseline (ROS's convention).
          if (!rig.stereo.present) break;
          const LogImage& im = r.image;
          if (im.format != PixelFormat::kGray8 && im.format != PixelFormat::kRgb8 &&
              im.format != PixelFormat::kBgr8)
            break;
          const std::string right_topic = topics.right.empty() ? "/camera/right/image_raw" : topics.right;
          const size_t k = right_topic.find_last_of('/');
          const std::string rinfo_topic =
              (k == std::string::npos ? std::string() : right_topic.substr(0, k)) + "/camera_info";
          sensor_msgs::Image m;
          m.header.stamp = time_of(im.t_ns);
          m.header.seq = im.seq;
          m.header.frame_id = "camera_right";
          m.width = static_cast<uint32_t>(im.width);
          m.height = static_cast<uint32_t>(im.height);
          m.encoding = im.format == PixelFormat::kGray8  ? "mono8"
                       : im.format == PixelFormat::kRgb8 ? "rgb8"
                                                         : "bgr8";
          m.step = m.width * static_cast<uint32_t>(bytes_per_pixel(im.format));
          m.data = im.pixels;
          bag.write(right_topic, m.header.stamp, m);
          const CameraIntrinsics& ki = rig.stereo.intrinsics;
          const Mat4d T_C0C1 = ds::mat_mul(ds::mat_inv(rig.T_BC), rig.stereo.T_BC1);
          sensor_msgs::CameraInfo ci;
          ci.header = m.header;
          ci.width = static_cast<uint32_t>(ki.width), ci.height = static_cast<uint32_t>(ki.height);
          ci.K = {ki.fx, 0, ki.cx, 0, ki.fy, ki.cy, 0, 0, 1};
          ci.R = {1, 0, 0, 0, 1, 0, 0, 0, 1};
          ci.P = {ki.fx, 0, ki.cx, -ki.fx * T_C0C1[3], 0, ki.fy, ki.cy, 0, 0, 0, 1, 0};
          ci.distortion_model = ki.distortion == DistortionModel::kEquidistant ? "equidistant" : "plumb_bob";
          if (ki.distortion == DistortionModel::kEquidistant) {
            ci.D.assign(ki.dist.begin(), ki.dist.begin() + 4);
          } else {
            ci.D.assign(ki.dist.begin(), ki.dist.end());
          }
          bag.write(rinfo_topic, m.header.stamp, ci);
          break;
        }
      }
    }
    bag.close();
  } catch (const std::exception& e) {
    throw std::runtime_error(path + ": write failed: " + e.what());
  }
  return st;
}

#else  // !KESTREL_WITH_ROSBAG

struct RosbagReader::Impl {
  Rig rig;
  std::vector<LogProblem> problems;
};
RosbagReader::RosbagReader(const std::string& path, const RosbagTopics&, const Rig*) { not_built(path); }
RosbagReader::~RosbagReader() = default;
const Rig& RosbagReader::rig() const { return impl_->rig; }
const std::vector<LogProblem>& RosbagReader::problems() const { return impl_->problems; }
void RosbagReader::rewind() {}
bool RosbagReader::next(LogRecord&) { return false; }
ExportStats export_rosbag(LogSource&, const std::string& path, const RosbagTopics&) { not_built(path); }

#endif

}  // namespace kestrel::drivers

// rosbag2 folders (metadata.yaml + MCAP) written from and read into LogSource records.
#include "kestrel/drivers/rosbag2.hpp"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <climits>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <set>
#include <sstream>
#include <stdexcept>

#include "kestrel/drivers/camera_time_shift.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/drivers/ros2_msgs.hpp"
#include "kestrel/drivers/text.hpp"
#include "message_store.hpp"

namespace kestrel::drivers {
namespace fs = std::filesystem;
namespace {

constexpr const char* kImuType = "sensor_msgs/msg/Imu";
constexpr const char* kImageType = "sensor_msgs/msg/Image";
constexpr const char* kCompressedType = "sensor_msgs/msg/CompressedImage";
constexpr const char* kInfoType = "sensor_msgs/msg/CameraInfo";
constexpr const char* kTfType = "tf2_msgs/msg/TFMessage";
constexpr const char* kPoseType = "geometry_msgs/msg/PoseStamped";
constexpr const char* kBaseFrame = "base_link";
constexpr const char* kImuFrame = "camera_imu_optical_frame";
constexpr const char* kColorFrame = "camera_color_optical_frame";
constexpr const char* kRightFrame = "camera_right_optical_frame";

// rosbag2's offered_qos_profiles: reliable, keep last 10 (tf_static: transient local, keep last 1).
std::string qos(bool latched) {
  return std::string("- history: 3\n  depth: 0\n  reliability: 1\n  durability: ") + (latched ? "1" : "2") +
         "\n  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n  lifespan:\n    sec: 2147483647\n"
         "    nsec: 4294967295\n  liveliness: 1\n  liveliness_lease_duration:\n    sec: 2147483647\n"
         "    nsec: 4294967295\n  avoid_ros_namespace_conventions: false\n";
}

std::array<double, 4> quat_xyzw_of(const Mat4d& T) {
  const double r00 = T[0], r01 = T[1], r02 = T[2], r10 = T[4], r11 = T[5], r12 = T[6], r20 = T[8], r21 = T[9],
               r22 = T[10];
  double w, x, y, z;
  const double tr = r00 + r11 + r22;
  if (tr > 0) {
    const double s = std::sqrt(tr + 1.0) * 2;
    w = 0.25 * s, x = (r21 - r12) / s, y = (r02 - r20) / s, z = (r10 - r01) / s;
  } else if (r00 > r11 && r00 > r22) {
    const double s = std::sqrt(1.0 + r00 - r11 - r22) * 2;
    w = (r21 - r12) / s, x = 0.25 * s, y = (r01 + r10) / s, z = (r02 + r20) / s;
  } else if (r11 > r22) {
    const double s = std::sqrt(1.0 + r11 - r00 - r22) * 2;
    w = (r02 - r20) / s, x = (r01 + r10) / s, y = 0.25 * s, z = (r12 + r21) / s;
  } else {
    const double s = std::sqrt(1.0 + r22 - r00 - r11) * 2;
    w = (r10 - r01) / s, x = (r02 + r20) / s, y = (r12 + r21) / s, z = 0.25 * s;
  }
  return {x, y, z, w};
}

Mat4d transform_of(const std::array<double, 3>& t, const std::array<double, 4>& q_xyzw) {
  double x = q_xyzw[0], y = q_xyzw[1], z = q_xyzw[2], w = q_xyzw[3];
  const double n = std::sqrt(x * x + y * y + z * z + w * w);
  if (!(n > 0)) return kIdentity4;
  x /= n, y /= n, z /= n, w /= n;
  return Mat4d{1 - 2 * (y * y + z * z),
               2 * (x * y - z * w),
               2 * (x * z + y * w),
               t[0],
               2 * (x * y + z * w),
               1 - 2 * (x * x + z * z),
               2 * (y * z - x * w),
               t[1],
               2 * (x * z - y * w),
               2 * (y * z + x * w),
               1 - 2 * (x * x + y * y),
               t[2],
               0,
               0,
               0,
               1};
}

Mat4d mul(const Mat4d& a, const Mat4d& b) {
  Mat4d c{};
  for (int i = 0; i < 4; ++i) {
    for (int j = 0; j < 4; ++j)
      for (int k = 0; k < 4; ++k) c[i * 4 + j] += a[i * 4 + k] * b[k * 4 + j];
  }
  return c;
}

Mat4d inverse(const Mat4d& T) {
  Mat4d r = kIdentity4;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r[i * 4 + j] = T[j * 4 + i];
  for (int i = 0; i < 3; ++i)
    r[i * 4 + 3] = -(r[i * 4 + 0] * T[3] + r[i * 4 + 1] * T[7] + r[i * 4 + 2] * T[11]);
  return r;
}

uint64_t log_time(int64_t t_ns) { return t_ns < 0 ? 0 : static_cast<uint64_t>(t_ns); }

const char* encoding_of(PixelFormat f) {
  switch (f) {
    case PixelFormat::kRgb8:
      return "rgb8";
    case PixelFormat::kBgr8:
      return "bgr8";
    case PixelFormat::kGray8:
      return "mono8";
    case PixelFormat::kDepthU16:
      return "16UC1";
    case PixelFormat::kYuyv:
      return "yuv422_yuy2";
  }
  return "";
}

}  // namespace

// ---- writing ------------------------------------------------------------------

Rosbag2Stats export_rosbag2(LogSource& src, const std::string& out_dir, const Rosbag2WriteOptions& o) {
  std::error_code ec;
  fs::create_directories(out_dir, ec);
  if (ec) throw std::runtime_error(out_dir + ": cannot create the folder: " + ec.message());
  std::string base = fs::path(out_dir).lexically_normal().filename().string();
  if (base.empty() || base == "." || base == "..") base = "kestrel";
  const std::string file = base + "_0.mcap";
  const std::string path = (fs::path(out_dir) / file).string();
  const Rig rig = rig_for_shifted_records(src.rig());
  const Rosbag2Topics& t = o.topics;

  mcap::Writer w;
  w.open(path, o.mcap);
  std::map<std::string, uint16_t> schema;
  for (const char* type : {kImuType, kImageType, kInfoType, kTfType, kPoseType})
    schema[type] = w.add_schema(type, "ros2msg", ros2::schema_text(type));
  struct Topic {
    std::string name, type;
    uint16_t id;
    size_t count = 0;
  };
  std::vector<Topic> topics;
  auto channel = [&](const std::string& name, const char* type, bool latched) {
    topics.push_back(
        {name, type, w.add_channel(schema[type], name, "cdr", {{"offered_qos_profiles", qos(latched)}})});
    return topics.size() - 1;
  };
  const size_t c_imu = channel(t.imu, kImuType, false), c_rgb = channel(t.rgb, kImageType, false),
               c_depth = channel(t.depth, kImageType, false),
               c_info = channel(t.camera_info, kInfoType, false), c_tf = channel("/tf_static", kTfType, true),
               c_gt = channel(t.ground_truth, kPoseType, false);
  // A stereo rig's right camera: its images, its CameraInfo (P carries the baseline) and its frame in
  // tf_static.
  const bool stereo = rig.stereo.present;
  const size_t c_right = stereo ? channel(t.right, kImageType, false) : 0,
               c_rinfo = stereo ? channel(t.right_camera_info, kInfoType, false) : 0;
  // The exact rig (IMU noise, depth model, T_BC): CameraInfo and tf_static carry only part of it.
  w.add_metadata("kestrel", {{"rig_yaml", rig_to_yaml(rig)}});

  ros2::CameraInfo info;
  info.frame_id = kColorFrame;
  info.width = static_cast<uint32_t>(rig.rgb.width);
  info.height = static_cast<uint32_t>(rig.rgb.height);
  info.k = {rig.rgb.fx, 0, rig.rgb.cx, 0, rig.rgb.fy, rig.rgb.cy, 0, 0, 1};
  info.r = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  info.p = {rig.rgb.fx, 0, rig.rgb.cx, 0, 0, rig.rgb.fy, rig.rgb.cy, 0, 0, 0, 1, 0};
  if (rig.rgb.distortion == DistortionModel::kRadTan) {
    info.distortion_model = "plumb_bob", info.d.assign(rig.rgb.dist.begin(), rig.rgb.dist.end());
  } else if (rig.rgb.distortion == DistortionModel::kEquidistant) {
    info.distortion_model = "equidistant", info.d.assign(rig.rgb.dist.begin(), rig.rgb.dist.begin() + 4);
  } else {
    info.distortion_model = "plumb_bob", info.d.assign(5, 0.0);
  }

  ros2::CameraInfo rinfo;
  if (stereo) {
    const CameraIntrinsics& k = rig.stereo.intrinsics;
    rinfo.frame_id = kRightFrame;
    rinfo.width = static_cast<uint32_t>(k.width);
    rinfo.height = static_cast<uint32_t>(k.height);
    rinfo.k = {k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1};
    rinfo.r = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    // ROS's convention: P[3] = -fx * baseline in the left camera's frame (exact for a rectified pair).
    const Mat4d T_C0C1 = mul(inverse(rig.T_BC), rig.stereo.T_BC1);
    rinfo.p = {k.fx, 0, k.cx, -k.fx * T_C0C1[3], 0, k.fy, k.cy, 0, 0, 0, 1, 0};
    if (k.distortion == DistortionModel::kRadTan) {
      rinfo.distortion_model = "plumb_bob", rinfo.d.assign(k.dist.begin(), k.dist.end());
    } else if (k.distortion == DistortionModel::kEquidistant) {
      rinfo.distortion_model = "equidistant", rinfo.d.assign(k.dist.begin(), k.dist.begin() + 4);
    } else {
      rinfo.distortion_model = "plumb_bob", rinfo.d.assign(5, 0.0);
    }
  }

  Rosbag2Stats st;
  std::vector<uint8_t> buf, px;
  int64_t t_first = INT64_MAX, t_last = INT64_MIN;
  bool tf_written = false;
  auto put = [&](size_t c, int64_t t_ns) {
    if (t_ns < 0) {
      throw std::runtime_error(path + ": a stamp before 1970 (" + std::to_string(t_ns) +
                               " ns) cannot be a ROS 2 time");
    }
    w.write(topics[c].id, log_time(t_ns), log_time(t_ns), buf.data(), buf.size());
    ++topics[c].count;
    t_first = std::min(t_first, t_ns), t_last = std::max(t_last, t_ns);
  };
  LogRecord r;
  src.rewind();
  while (src.next(r)) {
    const int64_t t_rec = record_time_ns(r);
    if (!tf_written) {
      std::vector<ros2::TransformStamped> tf(stereo ? 3 : 2);
      tf[0].t_ns = tf[1].t_ns = std::max<int64_t>(0, t_rec);
      tf[0].frame_id = tf[1].frame_id = kBaseFrame;
      tf[0].child_frame_id = kImuFrame;
      tf[0].translation = {rig.T_BI[3], rig.T_BI[7], rig.T_BI[11]};
      tf[0].rotation_xyzw = quat_xyzw_of(rig.T_BI);
      tf[1].child_frame_id = kColorFrame;
      tf[1].translation = {rig.T_BC[3], rig.T_BC[7], rig.T_BC[11]};
      tf[1].rotation_xyzw = quat_xyzw_of(rig.T_BC);
      if (stereo) {
        tf[2].t_ns = tf[0].t_ns;
        tf[2].frame_id = kBaseFrame;
        tf[2].child_frame_id = kRightFrame;
        tf[2].translation = {rig.stereo.T_BC1[3], rig.stereo.T_BC1[7], rig.stereo.T_BC1[11]};
        tf[2].rotation_xyzw = quat_xyzw_of(rig.stereo.T_BC1);
      }
      ros2::encode(tf, buf);
      put(c_tf, tf[0].t_ns);
      tf_written = true;
    }
    switch (r.type) {
      case RecordType::kImu: {
        ros2::Imu m;
        m.t_ns = r.imu.t_ns;
        m.frame_id = kImuFrame;
        m.angular_velocity = r.imu.gyro_rps;
        m.linear_acceleration = r.imu.acc_mps2;
        ros2::encode(m, buf);
        put(c_imu, m.t_ns);
        ++st.imu;
        break;
      }
      case RecordType::kRgb:
      case RecordType::kDepth: {
        const LogImage& im = r.image;
        const bool depth = r.type == RecordType::kDepth;
        if (im.format == PixelFormat::kYuyv || (depth != (im.format == PixelFormat::kDepthU16))) {
          ++st.skipped;
          break;
        }
        ros2::Image m;
        m.t_ns = im.t_ns;
        m.frame_id = kColorFrame;  // depth is registered to the colour camera
        m.width = static_cast<uint32_t>(im.width);
        m.height = static_cast<uint32_t>(im.height);
        m.encoding = encoding_of(im.format);
        m.step = static_cast<uint32_t>(im.width * bytes_per_pixel(im.format));
        m.data = im.pixels.data();
        m.data_size = static_cast<uint32_t>(im.pixels.size());
        if (depth && rig.depth.scale_m_per_unit != 0.001) {
          // 16UC1 depth is millimetres (REP 118).
          px.resize(im.pixels.size());
          for (size_t i = 0; i + 1 < px.size(); i += 2) {
            uint16_t v;
            std::memcpy(&v, im.pixels.data() + i, 2);
            const double mm = std::round(v * rig.depth.scale_m_per_unit * 1000.0);
            v = mm > 0 && mm <= 65535 ? static_cast<uint16_t>(mm) : 0;
            std::memcpy(px.data() + i, &v, 2);
          }
          m.data = px.data();
        }
        ros2::encode(m, buf);
        put(depth ? c_depth : c_rgb, m.t_ns);
        if (depth) {
          ++st.depth;
        } else {
          ++st.rgb;
          info.t_ns = im.t_ns;
          ros2::encode(info, buf);
          put(c_info, info.t_ns);
        }
        break;
      }
      case RecordType::kGroundTruth: {
        ros2::PoseStamped m;
        m.t_ns = r.gt.t_ns;
        m.frame_id = "map";
        m.pose.position = r.gt.p_WB;
        m.pose.orientation_xyzw = {r.gt.q_WB[1], r.gt.q_WB[2], r.gt.q_WB[3], r.gt.q_WB[0]};
        ros2::encode(m, buf);
        put(c_gt, m.t_ns);
        ++st.ground_truth;
        break;
      }
      case RecordType::kRight: {
        const LogImage& im = r.image;
        if (!stereo || im.format == PixelFormat::kYuyv || im.format == PixelFormat::kDepthU16) {
          ++st.skipped;
          break;
        }
        ros2::Image m;
        m.t_ns = im.t_ns;
        m.frame_id = kRightFrame;
        m.width = static_cast<uint32_t>(im.width);
        m.height = static_cast<uint32_t>(im.height);
        m.encoding = encoding_of(im.format);
        m.step = static_cast<uint32_t>(im.width * bytes_per_pixel(im.format));
        m.data = im.pixels.data();
        m.data_size = static_cast<uint32_t>(im.pixels.size());
        ros2::encode(m, buf);
        put(c_right, m.t_ns);
        ++st.right;
        rinfo.t_ns = im.t_ns;
        ros2::encode(rinfo, buf);
        put(c_rinfo, rinfo.t_ns);
        break;
      }
      case RecordType::kEvent:
        ++st.skipped;
        break;
    }
  }
  w.close();
  st.bytes = w.stats().bytes;

  const int64_t start = t_first == INT64_MAX ? 0 : t_first;
  const int64_t duration = t_first == INT64_MAX ? 0 : t_last - t_first;
  std::ostringstream y;
  y << "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: mcap\n";
  y << "  duration:\n    nanoseconds: " << duration << "\n";
  y << "  starting_time:\n    nanoseconds_since_epoch: " << start << "\n";
  y << "  message_count: " << w.stats().messages << "\n  topics_with_message_count:\n";
  for (const auto& tp : topics) {
    if (tp.count == 0) continue;
    std::string q = qos(tp.name == "/tf_static");
    YAML::Emitter e;
    e << YAML::DoubleQuoted << q;
    y << "    - topic_metadata:\n        name: " << tp.name << "\n        type: " << tp.type
      << "\n        serialization_format: cdr\n        offered_qos_profiles: " << e.c_str()
      << "\n      message_count: " << tp.count << "\n";
  }
  y << "  compression_format: \"\"\n  compression_mode: \"\"\n";
  y << "  relative_file_paths:\n    - " << file << "\n";
  y << "  files:\n    - path: " << file
    << "\n      starting_time:\n        nanoseconds_since_epoch: " << start
    << "\n      duration:\n        nanoseconds: " << duration
    << "\n      message_count: " << w.stats().messages << "\n";
  const std::string meta = (fs::path(out_dir) / "metadata.yaml").string();
  std::ofstream f(meta);
  if (!(f << y.str()) || !(f.flush())) throw std::runtime_error(meta + ": cannot write");
  return st;
}

// ---- reading ------------------------------------------------------------------

bool is_rosbag2(const std::string& path) {
  if (text::is_dir(path)) return text::is_file((fs::path(path) / "metadata.yaml").string());
  std::ifstream f(path, std::ios::binary);
  char m[8] = {};
  if (f.read(m, 8) && std::memcmp(m, mcap::kMagic, 8) == 0) return true;
  // A lone .db3 (rosbag2's sqlite3 storage): SQLite's header and the extension.
  return fs::path(path).extension() == ".db3" && rosbag2_store::is_sqlite3_file(path);
}

namespace {
enum Kind : uint8_t { kImuK = 0, kRgbK = 1, kDepthK = 2, kGtK = 3, kRightK = 4 };
enum Role : uint8_t { kIgnore, kImuRole, kColorRole, kDepthRole, kInfoRole, kTfRole, kGtRole, kRightRole };
bool colour_encoding(const std::string& e) {
  return e == "rgb8" || e == "bgr8" || e == "mono8" || e == "8UC1";
}
bool depth_encoding(const std::string& e) { return e == "16UC1" || e == "mono16" || e == "32FC1"; }
// CompressedImage.format as image_transport writes it: "jpeg" / "png" (colour),
// "<encoding>; jpeg compressed <encoding>", "16UC1; compressedDepth png"
// (depth). The encoding before ';' decides, else the word compressedDepth.
bool compressed_is_depth(const std::string& f) {
  const std::string enc = f.substr(0, f.find(';'));
  return depth_encoding(enc) || f.find("compressedDepth") != std::string::npos;
}
bool compressed_known(const std::string& f) {
  return f.find("jpeg") != std::string::npos || f.find("jpg") != std::string::npos ||
         f.find("png") != std::string::npos;
}
}  // namespace

struct Rosbag2Reader::Impl {
  std::string path, file;
  Rosbag2ReadOptions opt;
  Rig rig;
  std::vector<LogProblem> problems;
  std::unique_ptr<rosbag2_store::MessageStore> mr;
  std::set<uint16_t> compressed;  // channels of sensor_msgs/msg/CompressedImage
  struct Entry {
    int64_t t_ns, t_recv_ns;
    Kind kind;
    uint32_t idx;
  };
  std::vector<Entry> entries;
  std::vector<ImuSample> imu;
  std::vector<GroundTruthPose> gt;
  std::vector<mcap::MessageRef> images;
  std::vector<uint8_t> scratch;
  size_t pos = 0;

  // What the one pass over the messages finds (the constructor's scan).
  struct Img {
    int64_t t_ns, t_recv;
    uint32_t idx;
  };
  struct Scan {
    std::map<uint16_t, Role> role;  // by channel, decided at its first message
    std::string rgb_topic, depth_topic, imu_topic, gt_topic, right_topic;
    std::string right_frame, imu_frame, cam_frame;
    std::map<std::string, ros2::CameraInfo> infos;  // first per topic
    std::vector<ros2::TransformStamped> tf_static;
    std::vector<Img> rgb, depth, right;
  };
  // The bag's storage (a folder's metadata.yaml, or the file itself): file, mr.
  void open_storage();
  // A channel's role from its type, the options and its first message.
  Role classify(Scan& sc, const mcap::MessageRef& m, const uint8_t* data, size_t n);
  // One message, by its channel's role.
  void take(Scan& sc, const mcap::MessageRef& m, const uint8_t* data, size_t n);
  // The rig from CameraInfo and /tf_static (no --rig, no Kestrel metadata).
  Rig rig_from_messages(Scan& sc);
  // Colour/depth and left/right pairs into entries.
  void pair_images(Scan& sc);
  // Entries in time order, IMU duplicates dropped.
  void order_entries(const std::string& imu_topic);

  void problem(std::string where, std::string kind, std::string detail) {
    problems.push_back(LogProblem{std::move(where), std::move(kind), std::move(detail)});
  }
  std::string where_of(const mcap::MessageRef& m) {
    const auto& ch = mr->channels().at(m.channel_id);
    return file + ":" + ch.topic + "#" + std::to_string(m.sequence);
  }

  bool load_image(const mcap::MessageRef& ref, bool depth, LogImage& img) {
    const uint8_t* data = nullptr;
    if (!mr->load(ref, scratch, data)) {
      problem(where_of(ref), "bad-image", "cannot read the message again");
      return false;
    }
    if (compressed.count(ref.channel_id)) return load_compressed(ref, data, depth, img);
    ros2::Image m;
    try {
      ros2::decode(data, ref.size, m);
    } catch (const std::exception& e) {
      problem(where_of(ref), "bad-payload", e.what());
      return false;
    }
    const std::string& enc = m.encoding;
    PixelFormat fmt;
    int in_bpp;
    if (depth) {
      fmt = PixelFormat::kDepthU16, in_bpp = enc == "32FC1" ? 4 : 2;
    } else if (enc == "rgb8") {
      fmt = PixelFormat::kRgb8, in_bpp = 3;
    } else if (enc == "bgr8") {
      fmt = PixelFormat::kBgr8, in_bpp = 3;
    } else {
      fmt = PixelFormat::kGray8, in_bpp = 1;
    }
    const uint64_t w = m.width, h = m.height;
    if (w == 0 || h == 0 || w > 32768 || h > 32768 || m.step < w * in_bpp ||
        m.data_size < static_cast<uint64_t>(m.step) * h) {
      problem(where_of(ref), "bad-image",
              "size " + std::to_string(w) + "x" + std::to_string(h) + ", step " + std::to_string(m.step) +
                  " and " + std::to_string(m.data_size) + " data bytes do not agree");
      return false;
    }
    img.t_ns = m.t_ns;
    img.width = static_cast<int>(w);
    img.height = static_cast<int>(h);
    img.format = fmt;
    const size_t out_bpp = static_cast<size_t>(bytes_per_pixel(fmt));
    img.pixels.resize(w * h * out_bpp);
    const bool swap = m.is_bigendian != 0;
    for (uint64_t y = 0; y < h; ++y) {
      const uint8_t* s = m.data + y * m.step;
      uint8_t* d = img.pixels.data() + y * w * out_bpp;
      ros2::image_row_to_log(s, d, w, static_cast<int>(in_bpp), static_cast<int>(out_bpp), swap);
    }
    return true;
  }

  // JPEG / PNG through OpenCV's decoders. compressedDepth (image_transport's
  // depth plugin) puts a 12-byte header before the PNG: int32 format, then
  // float depthQuantA, depthQuantB, used by 32FC1 (inverse depth, quantised:
  // z = A / (v - B)); 16UC1 PNGs hold the millimetres themselves.
  bool load_compressed(const mcap::MessageRef& ref, const uint8_t* data, bool depth, LogImage& img) {
    ros2::CompressedImage m;
    try {
      ros2::decode(data, ref.size, m);
    } catch (const std::exception& e) {
      problem(where_of(ref), "bad-payload", e.what());
      return false;
    }
    const bool cdepth = m.format.find("compressedDepth") != std::string::npos;
    const bool inverse = cdepth && m.format.rfind("32FC1", 0) == 0;
    const uint8_t* p = m.data;
    size_t n = m.data_size;
    float quant_a = 0, quant_b = 0;
    if (cdepth) {
      if (n < 12) {
        problem(where_of(ref), "bad-image", "compressedDepth shorter than its 12-byte header");
        return false;
      }
      std::memcpy(&quant_a, p + 4, 4);
      std::memcpy(&quant_b, p + 8, 4);
      p += 12, n -= 12;
    }
    cv::Mat im;
    try {
      im = cv::imdecode(cv::Mat(1, static_cast<int>(n), CV_8UC1, const_cast<uint8_t*>(p)),
                        cv::IMREAD_UNCHANGED);
    } catch (const cv::Exception& e) {
      im.release();
    }
    if (im.empty() || im.cols > 32768 || im.rows > 32768) {
      problem(where_of(ref), "bad-image", "format \"" + m.format + "\": the JPEG/PNG data does not decode");
      return false;
    }
    const int w = im.cols, h = im.rows;
    img.t_ns = m.t_ns;
    img.width = w;
    img.height = h;
    if (depth) {
      if (im.type() != CV_16UC1) {
        problem(where_of(ref), "bad-image",
                "depth \"" + m.format + "\" decodes to " + std::to_string(im.channels()) + " channel(s) of " +
                    std::to_string(im.elemSize1() * 8) + " bits (expected one of 16)");
        return false;
      }
      img.format = PixelFormat::kDepthU16;
      img.pixels.resize(static_cast<size_t>(w) * h * 2);
      for (int y = 0; y < h; ++y) {
        const uint16_t* s = im.ptr<uint16_t>(y);
        uint8_t* d = img.pixels.data() + static_cast<size_t>(y) * w * 2;
        if (!inverse) {
          std::memcpy(d, s, static_cast<size_t>(w) * 2);
          continue;
        }
        for (int x = 0; x < w; ++x) {
          const double z = s[x] != 0 ? quant_a / (static_cast<double>(s[x]) - quant_b) : 0.0;
          const double mm = std::isfinite(z) && z > 0 ? std::round(z * 1000.0) : 0.0;
          const uint16_t v = mm > 0 && mm <= 65535 ? static_cast<uint16_t>(mm) : 0;
          std::memcpy(d + 2 * x, &v, 2);
        }
      }
      return true;
    }
    if (im.depth() != CV_8U || (im.channels() != 1 && im.channels() != 3 && im.channels() != 4)) {
      problem(where_of(ref), "bad-image",
              "colour \"" + m.format + "\" decodes to " + std::to_string(im.channels()) + " channel(s) of " +
                  std::to_string(im.elemSize1() * 8) + " bits (expected 8-bit grey or colour)");
      return false;
    }
    // OpenCV decodes colour as BGR(A); alpha is dropped.
    img.format = im.channels() == 1 ? PixelFormat::kGray8 : PixelFormat::kBgr8;
    const int out_c = im.channels() == 1 ? 1 : 3;
    img.pixels.resize(static_cast<size_t>(w) * h * out_c);
    for (int y = 0; y < h; ++y) {
      const uint8_t* s = im.ptr<uint8_t>(y);
      uint8_t* d = img.pixels.data() + static_cast<size_t>(y) * w * out_c;
      if (im.channels() != 4) {
        std::memcpy(d, s, static_cast<size_t>(w) * out_c);
        continue;
      }
      for (int x = 0; x < w; ++x)
        d[3 * x] = s[4 * x], d[3 * x + 1] = s[4 * x + 1], d[3 * x + 2] = s[4 * x + 2];
    }
    return true;
  }
};

void Rosbag2Reader::Impl::open_storage() {
  Impl& s = *this;
  std::string mcap_path = s.path;
  std::string storage;
  if (text::is_dir(s.path)) {
    const std::string meta = (fs::path(s.path) / "metadata.yaml").string();
    YAML::Node y;
    try {
      y = YAML::LoadFile(meta)["rosbag2_bagfile_information"];
    } catch (const std::exception& e) {
      throw std::runtime_error(meta + ": cannot read: " + e.what());
    }
    if (!y) throw std::runtime_error(meta + ": no rosbag2_bagfile_information");
    storage = y["storage_identifier"] ? y["storage_identifier"].as<std::string>() : "";
    if (storage != "mcap" && storage != "sqlite3")
      throw std::runtime_error(meta + ": storage_identifier \"" + storage + "\" (mcap and sqlite3 are read)");
    const std::string comp = y["compression_format"] ? y["compression_format"].as<std::string>() : "";
    if (!comp.empty()) {
      throw std::runtime_error(meta + ": compression_format \"" + comp +
                               "\" (whole-file compression is not read; MCAP chunk compression is)");
    }
    const YAML::Node files = y["relative_file_paths"];
    if (!files || !files.IsSequence() || files.size() == 0)
      throw std::runtime_error(meta + ": relative_file_paths names no file");
    mcap_path = (fs::path(s.path) / files[0].as<std::string>()).string();
    if (files.size() > 1) {
      s.problem(meta + ":relative_file_paths", "unsupported",
                "only the first of " + std::to_string(files.size()) + " split files is read");
    }
  }
  s.file = mcap_path;
  if (storage.empty()) storage = rosbag2_store::is_sqlite3_file(mcap_path) ? "sqlite3" : "mcap";
  if (storage == "sqlite3") {
    s.mr = rosbag2_store::open_sqlite3(mcap_path);
  } else {
    s.mr = rosbag2_store::open_mcap(mcap_path, s.opt.mcap);
  }
}

Role Rosbag2Reader::Impl::classify(Scan& scan, const mcap::MessageRef& m, const uint8_t* data, size_t n) {
  Impl& s = *this;
  const Rosbag2ReadOptions& options = s.opt;
  std::string &rgb_topic = scan.rgb_topic, &depth_topic = scan.depth_topic, &imu_topic = scan.imu_topic,
              &gt_topic = scan.gt_topic, &right_topic = scan.right_topic;
  const auto& ch = s.mr->channels().at(m.channel_id);
  const auto sc = s.mr->schemas().find(ch.schema_id);
  const std::string type = sc == s.mr->schemas().end() ? "" : sc->second.name;
  const std::string where = s.file + ":" + ch.topic;
  auto known = [](const std::string& t) {
    return t == kImuType || t == kImageType || t == kCompressedType || t == kInfoType || t == kTfType ||
           t == kPoseType;
  };
  if (!options.topics.empty() &&
      std::find(options.topics.begin(), options.topics.end(), ch.topic) == options.topics.end() &&
      type != kTfType && type != kInfoType)
    return kIgnore;  // not chosen (--topics); tf_static and CameraInfo still give the rig
  if (!known(type)) {
    s.problem(where, "unsupported-type", "message type \"" + type + "\" is not read; topic ignored");
    return kIgnore;
  }
  if (ch.message_encoding != "cdr") {
    s.problem(
        where, "bad-encoding",
        "message encoding \"" + ch.message_encoding + "\" of " + type + " (only cdr is read); topic ignored");
    return kIgnore;
  }
  if (sc->second.encoding != "ros2msg" && sc->second.encoding != "ros2idl") {
    s.problem(where, "assumed",
              "schema encoding \"" + sc->second.encoding + "\"; decoded as the ROS 2 " + type);
  }
  if (type == kImuType) {
    if (imu_topic.empty()) imu_topic = ch.topic;
    return ch.topic == imu_topic ? kImuRole : kIgnore;
  }
  if (type == kInfoType) return kInfoRole;
  if (type == kTfType) return ch.topic == "/tf_static" ? kTfRole : kIgnore;
  if (type == kPoseType) {
    if (gt_topic.empty()) gt_topic = ch.topic;
    return ch.topic == gt_topic ? kGtRole : kIgnore;
  }
  // Image: the named topics, else by the first message's encoding.
  if (type == kCompressedType) s.compressed.insert(ch.id);
  if (ch.topic == rgb_topic) return kColorRole;
  if (ch.topic == depth_topic) return kDepthRole;
  if (right_topic.empty() && ch.topic == Rosbag2Topics{}.right) right_topic = ch.topic;  // our writer's
  if (ch.topic == right_topic) return kRightRole;
  if (type == kCompressedType) {
    ros2::CompressedImage ci;
    try {
      ros2::decode(data, n, ci);
    } catch (const std::exception&) {
      return kIgnore;
    }
    if (!compressed_known(ci.format)) {
      s.problem(where, "bad-encoding",
                "CompressedImage format \"" + ci.format + "\" (jpeg or png are read); topic ignored");
      return kIgnore;
    }
    const bool d = compressed_is_depth(ci.format);
    if (!d && rgb_topic.empty() && options.rgb_topic.empty()) {
      rgb_topic = ch.topic;
      return kColorRole;
    }
    if (d && depth_topic.empty() && options.depth_topic.empty()) {
      depth_topic = ch.topic;
      return kDepthRole;
    }
    return kIgnore;
  }
  ros2::Image im;
  try {
    ros2::decode(data, n, im);
  } catch (const std::exception&) {
    return kIgnore;  // undecided: the message itself is reported below
  }
  if (rgb_topic.empty() && options.rgb_topic.empty() && colour_encoding(im.encoding)) {
    rgb_topic = ch.topic;
    return kColorRole;
  }
  if (depth_topic.empty() && options.depth_topic.empty() && depth_encoding(im.encoding)) {
    depth_topic = ch.topic;
    return kDepthRole;
  }
  return kIgnore;
}

void Rosbag2Reader::Impl::take(Scan& sc, const mcap::MessageRef& m, const uint8_t* data, size_t n) {
  Impl& s = *this;
  auto& [role, rgb_topic, depth_topic, imu_topic, gt_topic, right_topic, right_frame, imu_frame, cam_frame,
         infos, tf_static, rgb, depth, right] = sc;
  auto it = role.find(m.channel_id);
  if (it == role.end()) it = role.emplace(m.channel_id, classify(sc, m, data, n)).first;
  const Role ro = it->second;
  if (ro == kIgnore) return;
  const std::string where =
      s.file + ":" + s.mr->channels().at(m.channel_id).topic + "#" + std::to_string(m.sequence);
  const int64_t t_recv = static_cast<int64_t>(std::min<uint64_t>(m.log_time_ns, INT64_MAX));
  try {
    switch (ro) {
      case kImuRole: {
        ros2::Imu x;
        ros2::decode(data, n, x);
        ImuSample sm;
        sm.t_ns = x.t_ns;
        sm.t_recv_ns = t_recv;
        sm.seq = static_cast<uint32_t>(s.imu.size());
        sm.gyro_rps = x.angular_velocity;
        sm.acc_mps2 = x.linear_acceleration;
        bool finite = true;
        for (int j = 0; j < 3; ++j)
          finite = finite && std::isfinite(sm.gyro_rps[j]) && std::isfinite(sm.acc_mps2[j]);
        if (!finite) {
          sm.flags |= kImuNonFinite;
          s.problem(where, "non-finite", "NaN or Inf in an IMU message; kept with kImuNonFinite");
        }
        if (imu_frame.empty()) imu_frame = x.frame_id;
        s.entries.push_back({sm.t_ns, t_recv, kImuK, static_cast<uint32_t>(s.imu.size())});
        s.imu.push_back(sm);
        break;
      }
      case kRightRole: {
        // The right image of a stereo pair: colour encodings as the left (loaded as the left is).
        if (s.compressed.count(m.channel_id)) {
          ros2::CompressedImage ci;
          ros2::decode(data, n, ci);
          if (!compressed_known(ci.format) || compressed_is_depth(ci.format)) {
            s.problem(where, "bad-image", "right CompressedImage format \"" + ci.format + "\"");
            return;
          }
          if (right_frame.empty()) right_frame = ci.frame_id;
          right.push_back({ci.t_ns, t_recv, static_cast<uint32_t>(s.images.size())});
          s.images.push_back(m);
          break;
        }
        ros2::Image im;
        ros2::decode(data, n, im);
        if (!colour_encoding(im.encoding)) {
          s.problem(where, "bad-image",
                    "right encoding \"" + im.encoding + "\" (expected rgb8, bgr8 or mono8)");
          return;
        }
        if (right_frame.empty()) right_frame = im.frame_id;
        right.push_back({im.t_ns, t_recv, static_cast<uint32_t>(s.images.size())});
        s.images.push_back(m);
        break;
      }
      case kColorRole:
      case kDepthRole: {
        const bool d = ro == kDepthRole;
        if (s.compressed.count(m.channel_id)) {
          ros2::CompressedImage ci;
          ros2::decode(data, n, ci);
          if (!compressed_known(ci.format) || compressed_is_depth(ci.format) != d) {
            s.problem(where, "bad-image",
                      std::string(d ? "depth" : "colour") + " CompressedImage format \"" + ci.format + "\"");
            return;
          }
          if (!d && cam_frame.empty()) cam_frame = ci.frame_id;
          (d ? depth : rgb).push_back({ci.t_ns, t_recv, static_cast<uint32_t>(s.images.size())});
          s.images.push_back(m);
          break;
        }
        ros2::Image im;
        ros2::decode(data, n, im);
        if (d ? !depth_encoding(im.encoding) : !colour_encoding(im.encoding)) {
          s.problem(where, "bad-image",
                    std::string(d ? "depth" : "colour") + " encoding \"" + im.encoding + "\" (expected " +
                        (d ? "16UC1 or 32FC1" : "rgb8, bgr8 or mono8") + ")");
          return;
        }
        if (!d && cam_frame.empty()) cam_frame = im.frame_id;
        (d ? depth : rgb).push_back({im.t_ns, t_recv, static_cast<uint32_t>(s.images.size())});
        s.images.push_back(m);
        break;
      }
      case kInfoRole: {
        const std::string topic = s.mr->channels().at(m.channel_id).topic;
        if (infos.count(topic)) return;
        ros2::CameraInfo ci;
        ros2::decode(data, n, ci);
        infos[topic] = ci;
        break;
      }
      case kTfRole: {
        std::vector<ros2::TransformStamped> tf;
        ros2::decode(data, n, tf);
        tf_static.insert(tf_static.end(), tf.begin(), tf.end());
        break;
      }
      case kGtRole: {
        ros2::PoseStamped p;
        ros2::decode(data, n, p);
        GroundTruthPose g;
        g.t_ns = p.t_ns;
        g.p_WB = p.pose.position;
        const auto& q = p.pose.orientation_xyzw;
        g.q_WB = {q[3], q[0], q[1], q[2]};
        const double qn = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        if (!(std::abs(qn - 1.0) <= 1e-2)) {
          s.problem(where, "bad-row", "quaternion norm " + text::fmt17(qn) + " is not 1");
          return;
        }
        s.entries.push_back({g.t_ns, t_recv, kGtK, static_cast<uint32_t>(s.gt.size())});
        s.gt.push_back(g);
        break;
      }
      case kIgnore:
        break;
    }
  } catch (const std::exception& e) {
    s.problem(where, "bad-payload", e.what());
  }
}

Rig Rosbag2Reader::Impl::rig_from_messages(Scan& sc) {
  Impl& s = *this;
  const Rosbag2ReadOptions& options = s.opt;
  const std::string& path = s.path;
  auto& [role, rgb_topic, depth_topic, imu_topic, gt_topic, right_topic, right_frame, imu_frame, cam_frame,
         infos, tf_static, rgb, depth, right] = sc;
  Rig r;
  r.name = text::file_name(path);
  std::string info_topic = options.camera_info_topic;
  if (info_topic.empty() && !rgb_topic.empty()) {
    const size_t k = rgb_topic.rfind('/');
    info_topic = (k == std::string::npos ? std::string() : rgb_topic.substr(0, k)) + "/camera_info";
    if (!infos.count(info_topic) && infos.size() == 1) info_topic = infos.begin()->first;
  }
  const auto it = infos.find(info_topic);
  if (it == infos.end()) {
    throw std::runtime_error(path + ": no sensor_msgs/msg/CameraInfo on " +
                             (info_topic.empty() ? std::string("any topic") : info_topic) +
                             ": camera intrinsics missing; give them with --rig FILE.yaml or name the topic "
                             "with --camera-info-topic");
  }
  const ros2::CameraInfo& ci = it->second;
  if (ci.k[0] <= 0 || ci.k[4] <= 0 || ci.width == 0 || ci.height == 0 || ci.width > 32768 ||
      ci.height > 32768)
    throw std::runtime_error(s.file + ":" + info_topic + ": CameraInfo without a usable k / size");
  r.rgb.width = static_cast<int>(ci.width), r.rgb.height = static_cast<int>(ci.height);
  r.rgb.fx = ci.k[0], r.rgb.cx = ci.k[2], r.rgb.fy = ci.k[4], r.rgb.cy = ci.k[5];
  const bool zero = std::all_of(ci.d.begin(), ci.d.end(), [](double d) { return d == 0; });
  if (zero) {
    r.rgb.distortion = DistortionModel::kNone;
  } else if (ci.distortion_model == "plumb_bob" || ci.distortion_model == "rational_polynomial") {
    r.rgb.distortion = DistortionModel::kRadTan;
  } else if (ci.distortion_model == "equidistant") {
    r.rgb.distortion = DistortionModel::kEquidistant;
  } else {
    s.problem(s.file + ":" + info_topic, "bad-row",
              "distortion model \"" + ci.distortion_model + "\" not supported; taken as undistorted");
  }
  if (r.rgb.distortion != DistortionModel::kNone)
    for (size_t j = 0; j < std::min<size_t>(5, ci.d.size()); ++j) r.rgb.dist[j] = ci.d[j];
  if (cam_frame.empty()) cam_frame = ci.frame_id;
  // T_BC from /tf_static: both frames up to a common root, body = the IMU frame.
  std::map<std::string, std::pair<std::string, Mat4d>> parent;
  for (const auto& t : tf_static)
    parent[t.child_frame_id] = {t.frame_id, transform_of(t.translation, t.rotation_xyzw)};
  auto to_root = [&](std::string f, std::string& root) {
    Mat4d T = kIdentity4;
    for (int k = 0; k < 64 && parent.count(f); ++k) {
      T = mul(parent[f].second, T);
      f = parent[f].first;
    }
    root = f;
    return T;
  };
  std::string ri, rc;
  const Mat4d T_Ri = to_root(imu_frame, ri), T_Rc = to_root(cam_frame, rc);
  if (!imu_frame.empty() && !cam_frame.empty() && ri == rc &&
      (parent.count(imu_frame) || parent.count(cam_frame))) {
    r.T_BC = mul(inverse(T_Ri), T_Rc);
  } else if (!s.imu.empty() && imu_frame != cam_frame) {
    s.problem(s.file + ":/tf_static", "assumed",
              "no transform between \"" + imu_frame + "\" and \"" + cam_frame +
                  "\": T_BC = identity assumed (give --rig)");
  }
  // A stereo pair: the right camera from its CameraInfo, placed by /tf_static or else by P's baseline.
  if (!right.empty()) {
    const size_t k = right_topic.rfind('/');
    const std::string rinfo_topic =
        (k == std::string::npos ? std::string() : right_topic.substr(0, k)) + "/camera_info";
    const auto ri_it = infos.find(rinfo_topic);
    if (ri_it == infos.end()) {
      s.problem(s.file + ":" + rinfo_topic, "missing-file",
                "no CameraInfo for the right images of " + right_topic +
                    ": replayed as a monocular log (give the stereo rig with --rig)");
      right.clear();
    } else {
      const ros2::CameraInfo& rci = ri_it->second;
      CameraIntrinsics& rk = r.stereo.intrinsics;
      rk.width = static_cast<int>(rci.width), rk.height = static_cast<int>(rci.height);
      rk.fx = rci.k[0], rk.cx = rci.k[2], rk.fy = rci.k[4], rk.cy = rci.k[5];
      const bool rzero = std::all_of(rci.d.begin(), rci.d.end(), [](double d) { return d == 0; });
      rk.distortion = rzero                                   ? DistortionModel::kNone
                      : rci.distortion_model == "equidistant" ? DistortionModel::kEquidistant
                                                              : DistortionModel::kRadTan;
      if (rk.distortion != DistortionModel::kNone)
        for (size_t j = 0; j < std::min<size_t>(5, rci.d.size()); ++j) rk.dist[j] = rci.d[j];
      if (right_frame.empty()) right_frame = rci.frame_id;
      std::string rr;
      const Mat4d T_Rr = to_root(right_frame, rr);
      if (!right_frame.empty() && parent.count(right_frame) && rr == rc) {
        r.stereo.T_BC1 = mul(r.T_BC, mul(inverse(T_Rc), T_Rr));
      } else if (rci.p[0] > 0 && rci.p[3] < 0) {
        Mat4d T_C0C1 = kIdentity4;
        T_C0C1[3] = -rci.p[3] / rci.p[0];
        r.stereo.T_BC1 = mul(r.T_BC, T_C0C1);
        s.problem(s.file + ":" + rinfo_topic, "assumed",
                  "no /tf_static to the right camera's frame \"" + right_frame +
                      "\": placed by its CameraInfo's baseline (-P[3]/P[0] = " + text::fmt17(T_C0C1[3]) +
                      " m), rotation identity");
      } else {
        throw std::runtime_error(s.file + ":" + rinfo_topic +
                                 ": the right camera has no transform in /tf_static and no baseline in P "
                                 "(P[3] = -fx * baseline); give the stereo rig with --rig");
      }
      r.stereo.present = true;
    }
  }
  // BMX055 / BMI055 datasheet densities, as the other dataset readers assume.
  r.imu.gyro_noise_density_rad_s_sqrthz = 2.4434609527920612e-04;
  r.imu.gyro_random_walk_rad_s2_sqrthz = 2.0e-05;
  r.imu.acc_noise_density_mps2_sqrthz = 1.4709975e-03;
  r.imu.acc_random_walk_mps3_sqrthz = 3.2028384781419539e-03;
  if (!s.imu.empty()) {
    s.problem(
        s.file + ":" + imu_topic, "assumed",
        "no IMU noise densities in the bag: BMI055/BMX055-class figures assumed; give yours with --rig");
  }
  auto rate = [](int64_t a, int64_t b, size_t n) {
    return n > 1 && b > a ? (n - 1) * 1e9 / double(b - a) : 0.0;
  };
  if (!s.imu.empty()) {
    int64_t lo = INT64_MAX, hi = INT64_MIN;
    for (const auto& m : s.imu) lo = std::min(lo, m.t_ns), hi = std::max(hi, m.t_ns);
    r.imu_rate_hz = rate(lo, hi, s.imu.size());
  }
  if (rgb.size() > 1) {
    int64_t lo = INT64_MAX, hi = INT64_MIN;
    for (const auto& m : rgb) lo = std::min(lo, m.t_ns), hi = std::max(hi, m.t_ns);
    r.camera_rate_hz = rate(lo, hi, rgb.size());
  }
  r.depth.scale_m_per_unit = 0.001;  // 16UC1 millimetres, 32FC1 converted to them
  return r;
}

void Rosbag2Reader::Impl::pair_images(Scan& sc) {
  Impl& s = *this;
  const Rig& r = s.rig;
  auto& [role, rgb_topic, depth_topic, imu_topic, gt_topic, right_topic, right_frame, imu_frame, cam_frame,
         infos, tf_static, rgb, depth, right] = sc;
  // Colour/depth pairs share the colour stamp (nearest depth within 20 ms).
  auto by_t = [](const Img& a, const Img& b) { return a.t_ns < b.t_ns; };
  std::stable_sort(rgb.begin(), rgb.end(), by_t);
  std::stable_sort(depth.begin(), depth.end(), by_t);
  std::vector<bool> used(depth.size(), false);
  size_t j = 0;
  for (size_t i = 0; i < rgb.size(); ++i) {
    if (i > 0 && rgb[i].t_ns == rgb[i - 1].t_ns) {
      s.problem(s.where_of(s.images[rgb[i].idx]), "duplicate",
                "colour stamp repeats the previous frame's; dropped");
      continue;
    }
    const int64_t tc = camera_stamp_on_imu_clock(r, rgb[i].t_ns);
    s.entries.push_back({tc, rgb[i].t_recv, kRgbK, rgb[i].idx});
    while (j + 1 < depth.size() &&
           std::llabs(depth[j + 1].t_ns - rgb[i].t_ns) <= std::llabs(depth[j].t_ns - rgb[i].t_ns))
      ++j;
    if (j < depth.size() && !used[j] && std::llabs(depth[j].t_ns - rgb[i].t_ns) <= 20'000'000) {
      used[j] = true;
      s.entries.push_back({tc, depth[j].t_recv, kDepthK, depth[j].idx});
    }
  }
  // Right images share the left stamp too (nearest within 20 ms), only with a stereo rig.
  if (!right.empty() && !r.stereo.present) {
    s.problem(s.file + ":" + right_topic, "unsupported",
              "right images but a rig without a stereo: section; replayed as a monocular log");
    right.clear();
  }
  std::stable_sort(right.begin(), right.end(), by_t);
  size_t right_unpaired = 0;
  {
    std::vector<bool> taken(right.size(), false);
    size_t q = 0;
    for (size_t i = 0; i < rgb.size() && !right.empty(); ++i) {
      if (i > 0 && rgb[i].t_ns == rgb[i - 1].t_ns) continue;
      while (q + 1 < right.size() &&
             std::llabs(right[q + 1].t_ns - rgb[i].t_ns) <= std::llabs(right[q].t_ns - rgb[i].t_ns))
        ++q;
      if (!taken[q] && std::llabs(right[q].t_ns - rgb[i].t_ns) <= 20'000'000) {
        taken[q] = true;
        s.entries.push_back(
            {camera_stamp_on_imu_clock(r, rgb[i].t_ns), right[q].t_recv, kRightK, right[q].idx});
      }
    }
    right_unpaired = static_cast<size_t>(std::count(taken.begin(), taken.end(), false));
  }
  if (right_unpaired > 0) {
    s.problem(s.file + ":" + right_topic, "unassociated",
              std::to_string(right_unpaired) + " right images without a left image within 20 ms; skipped");
  }
  const size_t unassoc = static_cast<size_t>(std::count(used.begin(), used.end(), false));
  if (unassoc > 0) {
    s.problem(s.file + ":" + depth_topic, "unassociated",
              std::to_string(unassoc) + " depth images without a colour image within 20 ms; skipped");
  }
  if (rgb.empty())
    s.problem(s.file, "missing-file", "no colour images (sensor_msgs/msg/Image rgb8/bgr8/mono8)");
  if (s.imu.empty()) s.problem(s.file, "missing-file", "no IMU messages (sensor_msgs/msg/Imu)");
}

void Rosbag2Reader::Impl::order_entries(const std::string& imu_topic) {
  Impl& s = *this;
  size_t late = 0;
  for (size_t i = 1; i < s.entries.size(); ++i) {
    if (s.entries[i].kind == kImuK && s.entries[i - 1].kind == kImuK &&
        s.entries[i].t_ns < s.entries[i - 1].t_ns)
      ++late;
  }
  if (late > 0) {
    s.problem(s.file + ":" + imu_topic, "time-order",
              std::to_string(late) + " IMU messages stamped before the previous one; replayed sorted");
  }
  std::stable_sort(s.entries.begin(), s.entries.end(), [](const Impl::Entry& a, const Impl::Entry& b) {
    return a.t_ns != b.t_ns ? a.t_ns < b.t_ns : a.kind < b.kind;
  });
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
    s.problem(s.file + ":" + imu_topic, "duplicate",
              std::to_string(dups) + " IMU messages repeat a stamp; dropped");
  }
  s.entries.swap(kept);
}

Rosbag2Reader::Rosbag2Reader(const std::string& path, const Rosbag2ReadOptions& options, const Rig* rig_in)
    : impl_(std::make_unique<Impl>()) {
  Impl& s = *impl_;
  s.path = path;
  s.opt = options;
  s.open_storage();
  Impl::Scan sc;
  sc.rgb_topic = options.rgb_topic;
  sc.depth_topic = options.depth_topic;
  sc.imu_topic = options.imu_topic;
  sc.gt_topic = options.ground_truth_topic;
  sc.right_topic = options.right_topic;
  s.mr->scan([&](const mcap::MessageRef& m, const uint8_t* data, size_t n) { s.take(sc, m, data, n); });
  for (auto& p : s.mr->problems()) s.problems.push_back(p);
  s.mr->problems().clear();
  for (const auto& t : options.topics) {
    bool found = false;
    std::string have;
    for (const auto& [id, ch] : s.mr->channels()) {
      found = found || ch.topic == t;
      have += (have.empty() ? "" : ", ") + ch.topic;
    }
    if (!found) {
      throw std::runtime_error(path + ": --topics names " + t +
                               ", which the bag does not have (it has: " + have + ")");
    }
  }

  // The rig: --rig, else Kestrel's own, else CameraInfo (+ tf_static).
  Rig r;
  const auto km = s.mr->metadata().find("kestrel");
  if (rig_in) {
    r = *rig_in;
  } else if (km != s.mr->metadata().end() && km->second.count("rig_yaml")) {
    r = rig_from_yaml(km->second.at("rig_yaml"), s.file + ": MCAP metadata kestrel.rig_yaml");
  } else {
    r = s.rig_from_messages(sc);
  }
  s.rig = r;
  s.pair_images(sc);
  s.order_entries(sc.imu_topic);
}

Rosbag2Reader::~Rosbag2Reader() = default;
const Rig& Rosbag2Reader::rig() const { return impl_->rig; }
const std::vector<LogProblem>& Rosbag2Reader::problems() const { return impl_->problems; }
void Rosbag2Reader::rewind() { impl_->pos = 0; }

bool Rosbag2Reader::next(LogRecord& out) {
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
        const bool depth = e.kind == kDepthK;
        if (!s.load_image(s.images[e.idx], depth, out.image)) continue;
        out.type = depth ? RecordType::kDepth : e.kind == kRightK ? RecordType::kRight : RecordType::kRgb;
        out.image.t_ns = e.t_ns;
        out.image.t_recv_ns = e.t_recv_ns;
        out.image.seq = s.images[e.idx].sequence;
        out.image.exposure_us = 0;
        return true;
      }
    }
  }
  return false;
}

}  // namespace kestrel::drivers

// CDR codecs and ros2msg schema texts for the handful of ROS 2 types Kestrel reads and writes.
#include "kestrel/drivers/ros2_msgs.hpp"

#include <cmath>
#include <cstring>
#include <map>
#include <stdexcept>

namespace kestrel::drivers::ros2 {

// ---- CDR --------------------------------------------------------------------

CdrWriter::CdrWriter(std::vector<uint8_t>& out) : b_(out) {
  b_.clear();
  b_.insert(b_.end(), {0x00, 0x01, 0x00, 0x00});  // CDR_LE, no options
}
void CdrWriter::align(size_t n) {
  while ((b_.size() - 4) % n != 0) b_.push_back(0);
}
void CdrWriter::u8(uint8_t v) { b_.push_back(v); }
void CdrWriter::u32(uint32_t v) {
  align(4);
  for (int k = 0; k < 4; ++k) b_.push_back(static_cast<uint8_t>(v >> (8 * k)));
}
void CdrWriter::i32(int32_t v) { u32(static_cast<uint32_t>(v)); }
void CdrWriter::f64(double v) {
  align(8);
  uint64_t u;
  std::memcpy(&u, &v, 8);
  for (int k = 0; k < 8; ++k) b_.push_back(static_cast<uint8_t>(u >> (8 * k)));
}
void CdrWriter::f32(float v) {
  uint32_t u;
  std::memcpy(&u, &v, 4);
  u32(u);
}
void CdrWriter::str(const std::string& s) {
  u32(static_cast<uint32_t>(s.size() + 1));  // the length counts the terminating NUL
  b_.insert(b_.end(), s.begin(), s.end());
  b_.push_back(0);
}
void CdrWriter::bytes(const uint8_t* p, size_t n) {
  u32(static_cast<uint32_t>(n));
  b_.insert(b_.end(), p, p + n);
}
void CdrWriter::f64s(const double* p, size_t n) {
  for (size_t k = 0; k < n; ++k) f64(p[k]);
}
void CdrWriter::stamp(int64_t t_ns) {
  // Floor division, so times before the epoch keep 0 <= nanosec < 1e9.
  int64_t sec = t_ns / 1000000000, ns = t_ns % 1000000000;
  if (ns < 0) ns += 1000000000, --sec;
  i32(static_cast<int32_t>(sec));
  u32(static_cast<uint32_t>(ns));
}
void CdrWriter::header(int64_t t_ns, const std::string& frame_id) {
  stamp(t_ns);
  str(frame_id);
}

CdrReader::CdrReader(const uint8_t* p, size_t n) : p_(p), n_(n) {
  if (n < 4) throw std::runtime_error("CDR message shorter than its 4-byte encapsulation header");
  if (p[0] != 0x00 || p[1] != 0x01) {
    throw std::runtime_error("CDR encapsulation " + std::to_string(p[0]) + " " + std::to_string(p[1]) +
                             " (only CDR_LE, 00 01, is read)");
  }
}
void CdrReader::need(size_t k, const char* field) {
  if (k > n_ - i_)
    throw std::runtime_error(std::string("CDR field ") + field + " runs past the end of the message");
}
void CdrReader::align(size_t k) {
  const size_t pad = (k - (i_ - 4) % k) % k;
  if (pad > n_ - i_) throw std::runtime_error("CDR message ends in alignment padding");
  i_ += pad;
}
uint8_t CdrReader::u8(const char* field) {
  need(1, field);
  return p_[i_++];
}
uint32_t CdrReader::u32(const char* field) {
  align(4);
  need(4, field);
  uint32_t v = 0;
  for (int k = 0; k < 4; ++k) v |= static_cast<uint32_t>(p_[i_ + k]) << (8 * k);
  i_ += 4;
  return v;
}
int32_t CdrReader::i32(const char* field) { return static_cast<int32_t>(u32(field)); }
double CdrReader::f64(const char* field) {
  align(8);
  need(8, field);
  uint64_t u = 0;
  for (int k = 0; k < 8; ++k) u |= static_cast<uint64_t>(p_[i_ + k]) << (8 * k);
  i_ += 8;
  double v;
  std::memcpy(&v, &u, 8);
  return v;
}
std::string CdrReader::str(const char* field) {
  const uint32_t n = u32(field);
  need(n, field);
  // Length includes the NUL; tolerate writers that leave it out (n == 0).
  size_t len = n;
  if (len > 0 && p_[i_ + len - 1] == 0) --len;
  std::string s(reinterpret_cast<const char*>(p_ + i_), len);
  i_ += n;
  return s;
}
const uint8_t* CdrReader::bytes(const char* field, uint32_t& n) {
  n = u32(field);
  need(n, field);
  const uint8_t* p = p_ + i_;
  i_ += n;
  return p;
}
void CdrReader::f64s(double* out, size_t n, const char* field) {
  for (size_t k = 0; k < n; ++k) out[k] = f64(field);
}
uint32_t CdrReader::seq_len(const char* field, size_t min_element_bytes) {
  const uint32_t n = u32(field);
  // Bounded by what is left, so a corrupt length cannot make the caller allocate.
  if (min_element_bytes > 0 && n > (n_ - i_) / min_element_bytes) {
    throw std::runtime_error(std::string("CDR sequence ") + field + " of " + std::to_string(n) +
                             " elements is longer than the message");
  }
  return n;
}
int64_t CdrReader::stamp(const char* field) {
  const int64_t sec = i32(field);
  const uint32_t ns = u32(field);
  if (ns >= 1000000000u)
    throw std::runtime_error(std::string(field) + ".nanosec " + std::to_string(ns) + " >= 1e9");
  return sec * 1000000000 + ns;
}
int64_t CdrReader::header(std::string* frame_id) {
  const int64_t t = stamp("header.stamp");
  std::string f = str("header.frame_id");
  if (frame_id) *frame_id = std::move(f);
  return t;
}

// ---- messages ---------------------------------------------------------------

namespace {
void vec3(CdrWriter& w, const std::array<double, 3>& v) { w.f64s(v.data(), 3); }
void pose(CdrWriter& w, const Pose& p) {
  w.f64s(p.position.data(), 3);
  w.f64s(p.orientation_xyzw.data(), 4);
}
void pose(CdrReader& r, Pose& p) {
  r.f64s(p.position.data(), 3, "pose.position");
  r.f64s(p.orientation_xyzw.data(), 4, "pose.orientation");
}
}  // namespace

void encode(const PointCloudXyz& m, std::vector<uint8_t>& out) {
  CdrWriter w(out);
  w.header(m.t_ns, m.frame_id);
  w.u32(1);  // height: an unordered cloud is one row
  w.u32(m.n);
  const uint32_t fields = m.rgb != nullptr ? 4 : 3;
  w.u32(fields);
  const char* names[4] = {"x", "y", "z", "rgb"};
  for (uint32_t k = 0; k < fields; ++k) {
    w.str(names[k]);
    w.u32(4 * k);  // offset
    w.u8(7);       // sensor_msgs/PointField FLOAT32
    w.u32(1);      // count
  }
  w.u8(0);  // is_bigendian
  const uint32_t step = 4 * fields;
  w.u32(step);
  w.u32(step * m.n);
  // The floats' bytes as they are in memory: CDR_LE, and every target is little-endian.
  static_assert(sizeof(float) == 4);
  if (m.rgb == nullptr) {
    w.bytes(reinterpret_cast<const uint8_t*>(m.xyz), 12u * m.n);
  } else {
    w.u32(step * m.n);  // the data's length, then the points interleaved straight into out
    const std::size_t at = out.size();
    out.resize(at + static_cast<std::size_t>(step) * m.n);
    for (uint32_t i = 0; i < m.n; ++i) {
      uint8_t* q = out.data() + at + static_cast<std::size_t>(step) * i;
      std::memcpy(q, m.xyz + 3 * static_cast<std::size_t>(i), 12);
      const uint8_t* c = m.rgb + 3 * static_cast<std::size_t>(i);
      const uint32_t packed = (uint32_t{c[0]} << 16) | (uint32_t{c[1]} << 8) | uint32_t{c[2]};
      std::memcpy(q + 12, &packed, 4);
    }
  }
  w.u8(1);  // is_dense: no NaN points
}
void encode(const std::vector<Marker>& markers, std::vector<uint8_t>& out) {
  CdrWriter w(out);
  w.u32(static_cast<uint32_t>(markers.size()));
  for (const Marker& m : markers) {
    w.header(m.t_ns, m.frame_id);
    w.str(m.ns);
    w.i32(m.id);
    w.i32(m.type);
    w.i32(m.action);
    pose(w, m.pose);
    w.f64s(m.scale.data(), 3);
    for (float c : m.color_rgba) w.f32(c);
    w.i32(0);  // lifetime.sec: 0, forever
    w.u32(0);  // lifetime.nanosec
    w.u8(0);   // frame_locked
    w.u32(static_cast<uint32_t>(m.points.size()));
    for (const auto& p : m.points) w.f64s(p.data(), 3);
    w.u32(0);         // colors: none (color holds for every point)
    w.str("");        // texture_resource
    w.header(0, "");  // texture: an empty CompressedImage
    w.str("");
    w.u32(0);
    w.u32(0);   // uv_coordinates
    w.str("");  // text
    w.str("");  // mesh_resource
    w.str("");  // mesh_file.filename
    w.u32(0);   // mesh_file.data
    w.u8(0);    // mesh_use_embedded_materials
  }
}

void encode(const Imu& m, std::vector<uint8_t>& out) {
  CdrWriter w(out);
  w.header(m.t_ns, m.frame_id);
  w.f64s(m.orientation_xyzw.data(), 4);
  w.f64s(m.orientation_covariance.data(), 9);
  vec3(w, m.angular_velocity);
  w.f64s(m.angular_velocity_covariance.data(), 9);
  vec3(w, m.linear_acceleration);
  w.f64s(m.linear_acceleration_covariance.data(), 9);
}
void decode(const uint8_t* p, size_t n, Imu& m) {
  CdrReader r(p, n);
  m.t_ns = r.header(&m.frame_id);
  r.f64s(m.orientation_xyzw.data(), 4, "orientation");
  r.f64s(m.orientation_covariance.data(), 9, "orientation_covariance");
  r.f64s(m.angular_velocity.data(), 3, "angular_velocity");
  r.f64s(m.angular_velocity_covariance.data(), 9, "angular_velocity_covariance");
  r.f64s(m.linear_acceleration.data(), 3, "linear_acceleration");
  r.f64s(m.linear_acceleration_covariance.data(), 9, "linear_acceleration_covariance");
}

void encode(const Image& m, std::vector<uint8_t>& out) {
  CdrWriter w(out);
  w.header(m.t_ns, m.frame_id);
  w.u32(m.height);
  w.u32(m.width);
  w.str(m.encoding);
  w.u8(m.is_bigendian);
  w.u32(m.step);
  w.bytes(m.data, m.data_size);
}
void encode(const DiagnosticArray& m, std::vector<uint8_t>& out) {
  CdrWriter w(out);
  w.header(m.t_ns, m.frame_id);
  w.u32(static_cast<uint32_t>(m.status.size()));
  for (const auto& s : m.status) {
    w.u8(s.level);
    w.str(s.name);
    w.str(s.message);
    w.str(s.hardware_id);
    w.u32(static_cast<uint32_t>(s.values.size()));
    for (const auto& [k, v] : s.values) {
      w.str(k);
      w.str(v);
    }
  }
}
void encode(const CompressedImage& m, std::vector<uint8_t>& out) {
  CdrWriter w(out);
  w.header(m.t_ns, m.frame_id);
  w.str(m.format);
  w.bytes(m.data, m.data_size);
}
void decode(const uint8_t* p, size_t n, CompressedImage& m) {
  CdrReader r(p, n);
  m.t_ns = r.header(&m.frame_id);
  m.format = r.str("format");
  m.data = r.bytes("data", m.data_size);
}
void decode(const uint8_t* p, size_t n, Image& m) {
  CdrReader r(p, n);
  m.t_ns = r.header(&m.frame_id);
  m.height = r.u32("height");
  m.width = r.u32("width");
  m.encoding = r.str("encoding");
  m.is_bigendian = r.u8("is_bigendian");
  m.step = r.u32("step");
  m.data = r.bytes("data", m.data_size);
}

void encode(const CameraInfo& m, std::vector<uint8_t>& out) {
  CdrWriter w(out);
  w.header(m.t_ns, m.frame_id);
  w.u32(m.height);
  w.u32(m.width);
  w.str(m.distortion_model);
  w.u32(static_cast<uint32_t>(m.d.size()));
  w.f64s(m.d.data(), m.d.size());
  w.f64s(m.k.data(), 9);
  w.f64s(m.r.data(), 9);
  w.f64s(m.p.data(), 12);
  w.u32(0);                              // binning_x
  w.u32(0);                              // binning_y
  for (int k = 0; k < 4; ++k) w.u32(0);  // roi x_offset y_offset height width
  w.u8(0);                               // roi.do_rectify
}
void decode(const uint8_t* p, size_t n, CameraInfo& m) {
  CdrReader r(p, n);
  m.t_ns = r.header(&m.frame_id);
  m.height = r.u32("height");
  m.width = r.u32("width");
  m.distortion_model = r.str("distortion_model");
  m.d.resize(r.seq_len("d", 8));
  r.f64s(m.d.data(), m.d.size(), "d");
  r.f64s(m.k.data(), 9, "k");
  r.f64s(m.r.data(), 9, "r");
  r.f64s(m.p.data(), 12, "p");
  // binning and roi are not used
}

void encode(const Odometry& m, std::vector<uint8_t>& out) {
  CdrWriter w(out);
  w.header(m.t_ns, m.frame_id);
  w.str(m.child_frame_id);
  pose(w, m.pose);
  w.f64s(m.pose_covariance.data(), 36);
  vec3(w, m.linear);
  vec3(w, m.angular);
  w.f64s(m.twist_covariance.data(), 36);
}
void decode(const uint8_t* p, size_t n, Odometry& m) {
  CdrReader r(p, n);
  m.t_ns = r.header(&m.frame_id);
  m.child_frame_id = r.str("child_frame_id");
  pose(r, m.pose);
  r.f64s(m.pose_covariance.data(), 36, "pose.covariance");
  r.f64s(m.linear.data(), 3, "twist.twist.linear");
  r.f64s(m.angular.data(), 3, "twist.twist.angular");
  r.f64s(m.twist_covariance.data(), 36, "twist.covariance");
}

void encode(const PoseStamped& m, std::vector<uint8_t>& out) {
  CdrWriter w(out);
  w.header(m.t_ns, m.frame_id);
  pose(w, m.pose);
}
void decode(const uint8_t* p, size_t n, PoseStamped& m) {
  CdrReader r(p, n);
  m.t_ns = r.header(&m.frame_id);
  pose(r, m.pose);
}

void encode(const std::vector<TransformStamped>& tf, std::vector<uint8_t>& out) {
  CdrWriter w(out);
  w.u32(static_cast<uint32_t>(tf.size()));
  for (const auto& t : tf) {
    w.header(t.t_ns, t.frame_id);
    w.str(t.child_frame_id);
    w.f64s(t.translation.data(), 3);
    w.f64s(t.rotation_xyzw.data(), 4);
  }
}
void decode(const uint8_t* p, size_t n, std::vector<TransformStamped>& tf) {
  CdrReader r(p, n);
  // A transform is at least 8 + 4 + 4 + 7 * 8 bytes.
  tf.resize(r.seq_len("transforms", 72));
  for (auto& t : tf) {
    t.t_ns = r.header(&t.frame_id);
    t.child_frame_id = r.str("child_frame_id");
    r.f64s(t.translation.data(), 3, "transform.translation");
    r.f64s(t.rotation_xyzw.data(), 4, "transform.rotation");
  }
}

// ---- schemas ----------------------------------------------------------------

namespace {
// Field lists of the ROS 2 .msg files (comments and constants left out).
const std::map<std::string, std::string>& definitions() {
  static const std::map<std::string, std::string> d = {
      {"builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n"},
      {"std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id\n"},
      {"geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z\n"},
      {"geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n"},
      {"geometry_msgs/Quaternion", "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n"},
      {"geometry_msgs/Pose", "Point position\nQuaternion orientation\n"},
      {"geometry_msgs/PoseWithCovariance", "Pose pose\nfloat64[36] covariance\n"},
      {"geometry_msgs/Twist", "Vector3 linear\nVector3 angular\n"},
      {"geometry_msgs/TwistWithCovariance", "Twist twist\nfloat64[36] covariance\n"},
      {"geometry_msgs/Transform", "Vector3 translation\nQuaternion rotation\n"},
      {"geometry_msgs/TransformStamped",
       "std_msgs/Header header\nstring child_frame_id\nTransform transform\n"},
      {"geometry_msgs/PoseStamped", "std_msgs/Header header\nPose pose\n"},
      {"sensor_msgs/RegionOfInterest",
       "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"},
      {"sensor_msgs/Imu",
       "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
       "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
       "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n"},
      {"sensor_msgs/Image",
       "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 "
       "step\n"
       "uint8[] data\n"},
      {"sensor_msgs/CompressedImage", "std_msgs/Header header\nstring format\nuint8[] data\n"},
      {"sensor_msgs/CameraInfo",
       "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] "
       "d\nfloat64[9] k\n"
       "float64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nRegionOfInterest roi\n"},
      {"nav_msgs/Odometry",
       "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
       "geometry_msgs/TwistWithCovariance twist\n"},
      {"tf2_msgs/TFMessage", "geometry_msgs/TransformStamped[] transforms\n"},
      {"diagnostic_msgs/KeyValue", "string key\nstring value\n"},
      {"diagnostic_msgs/DiagnosticStatus",
       "byte level\nstring name\nstring message\nstring hardware_id\nKeyValue[] values\n"},
      {"diagnostic_msgs/DiagnosticArray", "std_msgs/Header header\nDiagnosticStatus[] status\n"},
      {"sensor_msgs/PointField", "string name\nuint32 offset\nuint8 datatype\nuint32 count\n"},
      {"sensor_msgs/PointCloud2",
       "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\nbool is_bigendian\n"
       "uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"},
      {"builtin_interfaces/Duration", "int32 sec\nuint32 nanosec\n"},
      {"std_msgs/ColorRGBA", "float32 r\nfloat32 g\nfloat32 b\nfloat32 a\n"},
      {"visualization_msgs/UVCoordinate", "float32 u\nfloat32 v\n"},
      {"visualization_msgs/MeshFile", "string filename\nuint8[] data\n"},
      {"visualization_msgs/Marker",
       "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\ngeometry_msgs/Pose pose\n"
       "geometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\nbuiltin_interfaces/Duration lifetime\n"
       "bool frame_locked\ngeometry_msgs/Point[] points\nstd_msgs/ColorRGBA[] colors\n"
       "string texture_resource\nsensor_msgs/CompressedImage texture\nUVCoordinate[] uv_coordinates\n"
       "string text\nstring mesh_resource\nMeshFile mesh_file\nbool mesh_use_embedded_materials\n"},
      {"visualization_msgs/MarkerArray", "Marker[] markers\n"},
  };
  return d;
}
const std::map<std::string, std::vector<std::string>>& dependencies() {
  static const std::map<std::string, std::vector<std::string>> d = {
      {"sensor_msgs/Imu",
       {"std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Quaternion", "geometry_msgs/Vector3"}},
      {"sensor_msgs/Image", {"std_msgs/Header", "builtin_interfaces/Time"}},
      {"sensor_msgs/CompressedImage", {"std_msgs/Header", "builtin_interfaces/Time"}},
      {"sensor_msgs/CameraInfo",
       {"std_msgs/Header", "builtin_interfaces/Time", "sensor_msgs/RegionOfInterest"}},
      {"nav_msgs/Odometry",
       {"std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/PoseWithCovariance",
        "geometry_msgs/Pose", "geometry_msgs/Point", "geometry_msgs/Quaternion",
        "geometry_msgs/TwistWithCovariance", "geometry_msgs/Twist", "geometry_msgs/Vector3"}},
      {"geometry_msgs/PoseStamped",
       {"std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Pose", "geometry_msgs/Point",
        "geometry_msgs/Quaternion"}},
      {"tf2_msgs/TFMessage",
       {"geometry_msgs/TransformStamped", "std_msgs/Header", "builtin_interfaces/Time",
        "geometry_msgs/Transform", "geometry_msgs/Vector3", "geometry_msgs/Quaternion"}},
      {"diagnostic_msgs/DiagnosticArray",
       {"std_msgs/Header", "builtin_interfaces/Time", "diagnostic_msgs/DiagnosticStatus",
        "diagnostic_msgs/KeyValue"}},
      {"sensor_msgs/PointCloud2", {"std_msgs/Header", "builtin_interfaces/Time", "sensor_msgs/PointField"}},
      {"visualization_msgs/MarkerArray",
       {"visualization_msgs/Marker", "std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Pose",
        "geometry_msgs/Point", "geometry_msgs/Quaternion", "geometry_msgs/Vector3", "std_msgs/ColorRGBA",
        "builtin_interfaces/Duration", "sensor_msgs/CompressedImage", "visualization_msgs/UVCoordinate",
        "visualization_msgs/MeshFile"}},
  };
  return d;
}
}  // namespace

std::string schema_text(const std::string& type) {
  // "pkg/msg/Name" -> "pkg/Name", the form the .msg files and "MSG:" lines use.
  std::string t = type;
  const size_t k = t.find("/msg/");
  if (k != std::string::npos) t.erase(k, 4);
  const auto def = definitions().find(t);
  const auto dep = dependencies().find(t);
  if (def == definitions().end() || dep == dependencies().end()) return "";
  std::string s = def->second;
  for (const auto& d : dep->second)
    s += "\n" + std::string(80, '=') + "\nMSG: " + d + "\n" + definitions().at(d);
  return s;
}

void image_row_to_log(const uint8_t* src, uint8_t* dst, uint64_t width, int in_bpp, int out_bpp,
                      bool big_endian) {
  if (in_bpp == 4) {
    for (uint64_t x = 0; x < width; ++x) {
      uint8_t b[4];
      std::memcpy(b, src + 4 * x, 4);
      if (big_endian) std::swap(b[0], b[3]), std::swap(b[1], b[2]);
      float f;
      std::memcpy(&f, b, 4);
      const double mm = std::isfinite(f) && f > 0 ? std::round(static_cast<double>(f) * 1000.0) : 0.0;
      const uint16_t v = mm > 0 && mm <= 65535 ? static_cast<uint16_t>(mm) : 0;
      std::memcpy(dst + 2 * x, &v, 2);
    }
  } else if (in_bpp == 2 && big_endian) {
    for (uint64_t x = 0; x < width; ++x) dst[2 * x] = src[2 * x + 1], dst[2 * x + 1] = src[2 * x];
  } else {
    std::memcpy(dst, src, width * static_cast<uint64_t>(out_bpp));
  }
}

}  // namespace kestrel::drivers::ros2

// ROS 2 messages in CDR (XCDR1, little-endian: encapsulation header 00 01 00 00,
// each primitive aligned to its size counted from the byte after the header),
// written from the OMG CDR rules and the ROS 2 .msg definitions, and the
// ros2msg schema texts rosbag2 stores beside them (the type's definition, then
// each dependency after a line of 80 '=' and "MSG: pkg/Type").
// Decoders check every length against the buffer and throw
// std::runtime_error naming the field; they never allocate more than the
// buffer holds.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

namespace kestrel::drivers::ros2 {

class CdrWriter {
 public:
  explicit CdrWriter(std::vector<uint8_t>& out);  // clears out and writes the encapsulation header
  void u8(uint8_t v);
  void u32(uint32_t v);
  void i32(int32_t v);
  void f64(double v);
  void f32(float v);
  void str(const std::string& s);
  void bytes(const uint8_t* p, size_t n);  // uint8[] with its length
  void f64s(const double* p, size_t n);    // fixed array: no length
  void stamp(int64_t t_ns);                // builtin_interfaces/Time
  void header(int64_t t_ns, const std::string& frame_id);

 private:
  void align(size_t n);
  std::vector<uint8_t>& b_;
};

class CdrReader {
 public:
  CdrReader(const uint8_t* p, size_t n);  // checks the encapsulation header (CDR_LE only)
  uint8_t u8(const char* field);
  uint32_t u32(const char* field);
  int32_t i32(const char* field);
  double f64(const char* field);
  std::string str(const char* field);
  // uint8[]: a view into the buffer.
  const uint8_t* bytes(const char* field, uint32_t& n);
  void f64s(double* out, size_t n, const char* field);
  uint32_t seq_len(const char* field, size_t min_element_bytes);
  int64_t stamp(const char* field);
  int64_t header(std::string* frame_id);

 private:
  void align(size_t n);
  void need(size_t n, const char* field);
  const uint8_t* p_;
  size_t n_, i_ = 4;
};

struct Imu {
  int64_t t_ns = 0;
  std::string frame_id;
  std::array<double, 4> orientation_xyzw{0, 0, 0, 1};
  std::array<double, 9> orientation_covariance{-1, 0, 0, 0, 0, 0, 0, 0, 0};  // -1: no orientation
  std::array<double, 3> angular_velocity{};
  std::array<double, 9> angular_velocity_covariance{};
  std::array<double, 3> linear_acceleration{};
  std::array<double, 9> linear_acceleration_covariance{};
};

// Image: the pixels are a view (into the caller's buffer when encoding, into
// the message when decoding).
struct Image {
  int64_t t_ns = 0;
  std::string frame_id;
  uint32_t height = 0, width = 0;
  std::string encoding;
  uint8_t is_bigendian = 0;
  uint32_t step = 0;
  const uint8_t* data = nullptr;
  uint32_t data_size = 0;
};

// sensor_msgs/msg/CompressedImage: `format` as image_transport writes it
// ("jpeg", "png", "rgb8; jpeg compressed bgr8", "16UC1; compressedDepth png");
// data is a view, as for Image.
struct CompressedImage {
  int64_t t_ns = 0;
  std::string frame_id;
  std::string format;
  const uint8_t* data = nullptr;
  uint32_t data_size = 0;
};

struct CameraInfo {
  int64_t t_ns = 0;
  std::string frame_id;
  uint32_t height = 0, width = 0;
  std::string distortion_model;
  std::vector<double> d;
  std::array<double, 9> k{}, r{};
  std::array<double, 12> p{};
};

struct Pose {
  std::array<double, 3> position{};
  std::array<double, 4> orientation_xyzw{0, 0, 0, 1};
};

struct Odometry {
  int64_t t_ns = 0;
  std::string frame_id, child_frame_id;
  Pose pose;
  std::array<double, 36> pose_covariance{};
  std::array<double, 3> linear{}, angular{};
  std::array<double, 36> twist_covariance{};
};

struct PoseStamped {
  int64_t t_ns = 0;
  std::string frame_id;
  Pose pose;
};

struct TransformStamped {
  int64_t t_ns = 0;
  std::string frame_id, child_frame_id;
  std::array<double, 3> translation{};
  std::array<double, 4> rotation_xyzw{0, 0, 0, 1};
};

// diagnostic_msgs/msg/DiagnosticArray (written only: --mcap-out's /diagnostics).
struct DiagnosticStatus {
  uint8_t level = 0;  // OK 0, WARN 1, ERROR 2, STALE 3
  std::string name, message, hardware_id;
  std::vector<std::pair<std::string, std::string>> values;  // diagnostic_msgs/KeyValue
};
struct DiagnosticArray {
  int64_t t_ns = 0;
  std::string frame_id;
  std::vector<DiagnosticStatus> status;
};

// sensor_msgs/msg/PointCloud2 of x y z float32 points (written only:
// --mcap-out's and --foxglove's map points and dense surface). One row, dense,
// little-endian, 12 bytes per point; with colour 16, the fourth field `rgb` a
// FLOAT32 holding the bits of 0x00RRGGBB (the layout PCL, RViz and Foxglove read).
struct PointCloudXyz {
  int64_t t_ns = 0;
  std::string frame_id;
  const float* xyz = nullptr;    // 3 * n floats, a view into the caller's buffer
  const uint8_t* rgb = nullptr;  // 3 * n bytes r g b, or none
  uint32_t n = 0;
};

// visualization_msgs/msg/Marker (the Humble definition) with what Kestrel
// draws: a pose, a scale, one colour and a list of points.
struct Marker {
  enum Type : int32_t { kArrow = 0, kSphere = 2, kLineStrip = 4, kLineList = 5 };
  enum Action : int32_t { kAdd = 0, kDeleteAll = 3 };
  int64_t t_ns = 0;
  std::string frame_id, ns;
  int32_t id = 0, type = kArrow, action = kAdd;
  Pose pose;
  std::array<double, 3> scale{1, 1, 1};
  std::array<float, 4> color_rgba{1, 1, 1, 1};
  std::vector<std::array<double, 3>> points;
};

void encode(const PointCloudXyz& m, std::vector<uint8_t>& out);
void encode(const std::vector<Marker>& markers,
            std::vector<uint8_t>& out);  // visualization_msgs/msg/MarkerArray
void encode(const Imu& m, std::vector<uint8_t>& out);
void encode(const DiagnosticArray& m, std::vector<uint8_t>& out);
void encode(const Image& m, std::vector<uint8_t>& out);
void encode(const CameraInfo& m, std::vector<uint8_t>& out);
void encode(const CompressedImage& m, std::vector<uint8_t>& out);
void encode(const Odometry& m, std::vector<uint8_t>& out);
void encode(const PoseStamped& m, std::vector<uint8_t>& out);
void encode(const std::vector<TransformStamped>& tf, std::vector<uint8_t>& out);  // tf2_msgs/msg/TFMessage

void decode(const uint8_t* p, size_t n, Imu& m);
void decode(const uint8_t* p, size_t n, Image& m);
void decode(const uint8_t* p, size_t n, CompressedImage& m);
void decode(const uint8_t* p, size_t n, CameraInfo& m);
void decode(const uint8_t* p, size_t n, Odometry& m);
void decode(const uint8_t* p, size_t n, PoseStamped& m);
void decode(const uint8_t* p, size_t n, std::vector<TransformStamped>& tf);

// The ros2msg schema text of a type ("sensor_msgs/msg/Imu", ...), with its
// dependencies; "" for a type this file does not know.
std::string schema_text(const std::string& type);

// One row of a sensor_msgs Image into a log image's row, shared by the ROS 1
// and ROS 2 readers: 32FC1 metres (REP 118) become millimetres (0: invalid,
// non-finite or beyond 65.535 m), 16-bit big-endian rows are swapped, other
// rows copied (in_bpp == out_bpp).
void image_row_to_log(const uint8_t* src, uint8_t* dst, uint64_t width, int in_bpp, int out_bpp,
                      bool big_endian);

}  // namespace kestrel::drivers::ros2

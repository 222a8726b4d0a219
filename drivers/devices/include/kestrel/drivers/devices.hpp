// Live rig configuration and the sensors it names.
//
//  - The config file's sections drivers own: `drivers:` (camera, IMU, strobe
//    settings; units in key names, unknown keys are errors naming file and
//    key), `threads:`, `mavlink:`, `record:` and `ros2:`, each parsed from its
//    node into its struct; `rig:` is drivers/rig's. tools/config reads the file.
//  - probe_devices(): what is connected, for `kestrel devices`.
//  - LiveSensors: opens every configured device (or explains each one that is
//    missing) and runs one thread per sensor delivering into an ImuSink and a
//    FrameSink. Used by `kestrel record` and `kestrel run`.
#pragma once

#include <yaml-cpp/yaml.h>

#include <array>
#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "kestrel/drivers/bmx055.hpp"
#include "kestrel/drivers/clock_sync.hpp"
#include "kestrel/drivers/iio_imu.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/mavlink_imu.hpp"
#include "kestrel/drivers/replay_source.hpp"
#include "kestrel/drivers/sensor_rings.hpp"
#include "kestrel/drivers/usb_bridge.hpp"
#include "kestrel/msgs.hpp"
#include "kestrel/rt/thread_setup.hpp"

namespace kestrel::drivers {

// kLog: both sensors played from a recorded .klog at its own pace, through the
// same sinks and threads as the hardware (a bench without sensors, and the
// tests of `kestrel run`). Camera stamps are handed out as the camera's clock
// gave them (the log's offset taken back out), like a camera driver's.
enum class CameraType { kNone, kOpenNi2, kV4l2, kLog, kD4xx };
enum class ImuType { kNone, kBmx055I2c, kBmx055Usb, kLog, kMavlink, kIio };

struct CameraSettings {
  CameraType type = CameraType::kNone;
  int width_px = 640;
  int height_px = 480;
  double rate_hz = 30;
  // openni2
  std::string openni2_uri;
  bool openni2_registration = true;
  bool openni2_frame_sync = true;
  bool openni2_mirror = false;
  // v4l2
  std::string v4l2_color_device;
  std::string v4l2_color_format = "yuyv";
  std::string v4l2_depth_device;  // "" = colour only
  // A stereo rig's right image (the rig's `stereo:` section; docs/stereo.md):
  // a second node (right_device, its frame nearest in time within half a
  // period), or one node whose frames carry left | right side by side
  // (stereo_layout side_by_side: the node is opened at twice the width).
  std::string v4l2_right_device;           // "" = none
  std::string v4l2_stereo_layout = "off";  // off | side_by_side
  std::string v4l2_depth_format = "z16";
  double v4l2_depth_unit_m = 0.001;
  int v4l2_buffers = 4;
  int64_t v4l2_readout_ns = 0;
  // d4xx: a RealSense D4xx over V4L2 with its UVC metadata nodes (docs/realsense.md).
  // Empty device paths are found by card name; a metadata path of "none" turns
  // that stream's hardware stamps off (kernel stamps).
  struct D4xx {
    std::string card_match = "RealSense";
    std::string color_device, color_meta_device;
    std::string depth_device, depth_meta_device;
    std::string infrared_device, infrared_meta_device;
    std::string image = "color";  // color | infrared1: the stream that is the rig's camera
    bool depth = true;
    std::string infrared = "off";  // off | y8 (Infrared 1) | y8i (Infrared 1 + 2)
    int depth_width_px = 0;        // 0: the rig's depth_camera size, else the camera's
    int depth_height_px = 0;
    double depth_unit_m = 0.001;
    int buffers = 4;
    int metadata_wait_ms = 2;
    int64_t pair_tolerance_ns = 0;  // 0: half a frame period
    int64_t readout_ns = 0;         // for kernel-stamped (fallback) frames
  } d4xx;
};

struct ImuSettings {
  ImuType type = ImuType::kNone;
  bmx055::Config bmx055;  // ranges, ODR, FIFO, data-ready, self-test, axis remap
  std::string i2c_bus_device;
  std::string gpio_chip;  // data_ready: gpio
  int gpio_line = -1;
  UsbBridgeConfig usb;
  MavlinkImuConfig mavlink;  // type: mavlink, the flight controller's IMU (docs/px4.md)
  iio::ImuConfig iio;        // type iio: Linux IIO devices (docs/drivers/iio.md)
};

struct StrobeSettings {
  bool enabled = false;
  int64_t initial_offset_ns = 0;
  int64_t tolerance_ns = 8'000'000;
};

struct DriverSettings {
  CameraSettings camera;
  ImuSettings imu;
  StrobeSettings strobe;
  std::string log_path;  // drivers.log.path: the .klog both `log` sensors play (relative to the config)
  // drivers.log.pace: realtime plays the log through the live sensor threads
  // at its own rate (as a flight); fast and lockstep run it through the replay
  // pipeline (`kestrel run` then writes what `kestrel replay --pace P` writes).
  ReplayPace log_pace = ReplayPace::kRealtime;
};

// `mavlink:` section (optional): the flight-controller link (tools/mavlink,
// docs/px4.md). The command line's --mavlink-udp / --mavlink-serial choose
// the transport over these; the rest holds for either.
struct MavlinkSettings {
  bool present = false;       // the section was read
  std::string udp;            // HOST:PORT, "" = none
  std::string serial_device;  // e.g. /dev/ttyTHS1, "" = none
  int serial_baud = 921600;
  int sysid = 1;     // the vehicle's system id (a companion shares it)
  int compid = 197;  // MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
  // The vehicle's FRD body axes in B, row-major 3x3 (p_F = R_FB p_B): a
  // rotation. Default: B is forward-left-up, so FRD is a half turn about x.
  std::array<double, 9> R_FB{1, 0, 0, 0, -1, 0, 0, 0, -1};
  double odometry_rate_hz = 0;  // at most this often; 0 = every pose
  double heartbeat_rate_hz = 1;
  bool timesync = true;
  double timesync_max_rtt_ms = 10;
  // signing: {key_file, link_id}: sign what we send, accept only what verifies.
  bool signing = false;
  std::string signing_key_file;  // resolved against the config's folder
  mavlink::SigningKey signing_key;
  int signing_link_id = 0;
};

// `record:` section (optional): how `kestrel record` and `kestrel run
// --record` write their .klog. Keys `image_codec` (zstd | lz4 | none) and
// `zstd_level`; defaults and what they were chosen on: docs/log-format.md.
struct RecordSettings {
  klog::ImageCompression compression = default_image_compression();
};
// Throws std::runtime_error "where: record.image_codec: expected one of zstd, lz4, none".
RecordSettings record_settings_from_yaml_node(const YAML::Node& node, const std::string& where);

// `ros2:` section (optional): what `--mcap-out` and `--foxglove` publish
// beside the poses (docs/ros2.md).
struct Ros2Settings {
  double map_points_rate_hz =
      1.0;  // PointCloud2 of the local map at most this often [Hz of log time]; 0: none
};
// Throws std::runtime_error "where: ros2.map_points_rate_hz: expected a number in [0, 30]".
Ros2Settings ros2_settings_from_yaml_node(const YAML::Node& node, const std::string& where);

// `threads:` section (optional): scheduling and CPU of every pipeline thread.
// One rt::ThreadSpec per known thread (priority 0 = SCHED_OTHER, cpu -1 =
// any). Threads the section does not name keep default_thread_table()'s value.
enum class PipelineThread : int {
  kImu,
  kCamera,
  kReplay,
  kPropagate,
  kEstimator,
  kOptimizer,
  kLog,
  kViewer,
  kMapping,
  kLoop,
  kCount
};
constexpr int kPipelineThreads = static_cast<int>(PipelineThread::kCount);

struct ThreadTable {
  rt::ThreadSpec spec[kPipelineThreads]{};
  bool from_config = false;  // a `threads:` section was read
  const rt::ThreadSpec& operator[](PipelineThread t) const { return spec[static_cast<int>(t)]; }
  rt::ThreadSpec& operator[](PipelineThread t) { return spec[static_cast<int>(t)]; }
};

// The built-in table, used when a config has no `threads:` section (the one
// place the defaults live; docs/threads.md explains each value).
ThreadTable default_thread_table();
// "kst-imu, kst-cam, ..." (the names a `threads:` section may use).
std::string thread_names();
// Throws std::runtime_error "where: threads.kst-optimizer.priority: expected 1..99".
ThreadTable thread_table_from_yaml_node(const YAML::Node& node, const std::string& where);

// What the live sensors run from: the sections of a config file that
// drivers own, already parsed. The file itself is read by tools/config's one
// reader (tools::load_config), which hands each section to its parser below.
struct LiveConfig {
  std::string path;  // the config file, for messages and relative paths
  Rig rig;           // `rig:` inline, or `rig: FILE.yaml` (relative to the config), or the log's own
  DriverSettings drivers;
  ThreadTable threads = default_thread_table();
  MavlinkSettings mavlink;
  RecordSettings record;
  Ros2Settings ros2;
};

// The section parsers. Each throws std::runtime_error naming `where` and the
// key: "path: drivers.imu.acc_range_g: expected one of 2, 4, 8, 16".
DriverSettings driver_settings_from_yaml_node(const YAML::Node& node, const std::string& where);
// Throws std::runtime_error "where: mavlink.sysid: must be in 1..255".
MavlinkSettings mavlink_settings_from_yaml_node(const YAML::Node& node, const std::string& where);

// "v4l2 built, openni2 built, libusb built, i2c-dev built, gpio-cdev built"
std::string built_drivers_summary();

struct FoundDevice {
  std::string kind;    // "camera" | "imu"
  std::string driver;  // "v4l2" | "openni2" | "bmx055-i2c" | "usb-bridge"
  std::string where;   // path / URI / bus:address
  std::string detail;
};
struct DeviceReport {
  std::vector<FoundDevice> found;
  std::vector<std::string> notes;  // why a driver could not look (permissions, not built)
};
DeviceReport probe_devices();

// ---- live sensors ---------------------------------------------------------------------

struct CameraFrame {
  int64_t t_ns = 0;  // mid-exposure, host clock
  int64_t t_recv_ns = 0;
  uint32_t seq = 0;
  int32_t exposure_us = 0;
  bool strobe_matched = false;
  const ImageBuffer* rgb = nullptr;
  const ImageBuffer* depth = nullptr;  // nullptr when the rig has no depth
  const ImageBuffer* right = nullptr;  // a stereo rig's right image, nullptr when none came
};

// One side-by-side stereo frame (left | right, each half the width) into two
// images of the half width, without allocating when their capacity suffices.
// False when the width is odd, the format unknown or a capacity too small.
bool split_side_by_side(const ImageBuffer& in, ImageBuffer& left, ImageBuffer& right);

// Whether the camera settings can deliver a stereo rig's right image
// (`kestrel run` refuses a stereo rig before start when they cannot, and says why).
std::string stereo_capability(const CameraSettings& c);  // "" when they can

class FrameSink {
 public:
  virtual ~FrameSink() = default;
  virtual bool push_frame(const CameraFrame& f) noexcept = 0;
};

class LiveSensors {
 public:
  // Opens every configured device. Throws std::runtime_error listing each
  // device that is missing and why, and which drivers are built.
  explicit LiveSensors(const LiveConfig& cfg);
  ~LiveSensors();
  LiveSensors(const LiveSensors&) = delete;
  LiveSensors& operator=(const LiveSensors&) = delete;

  // Starts the sensor threads (kst-imu, kst-cam) with the config's thread
  // table; the sinks must outlive stop(). Scheduling that is refused falls
  // back (the thread runs anyway): thread_reports() says what each got.
  void start(ImuSink& imu, FrameSink& frames);
  // One per started sensor thread, filled when start() returns.
  std::vector<std::pair<rt::ThreadSpec, rt::ThreadSetupReport>> thread_reports() const;
  void stop();
  // Counters of every driver, one line each (for the end-of-run report).
  std::string report() const;
  std::string description() const;  // what runs, in one line

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace kestrel::drivers

#include "kestrel/drivers/devices.hpp"

#include <dirent.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <initializer_list>
#include <sstream>
#include <stdexcept>

#include "kestrel/drivers/bmx055_drdy.hpp"
#include "kestrel/drivers/d4xx_camera.hpp"
#include "kestrel/drivers/i2c_bus.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/openni2_camera.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/drivers/v4l2_camera.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::drivers {
namespace {

// ---- YAML helpers: every error names the file and the key ----------------------------
class P {
 public:
  explicit P(std::string where) : where_(std::move(where)) {}
  [[noreturn]] void fail(const std::string& key, const std::string& msg) const {
    throw std::runtime_error(where_ + ": " + key + ": " + msg);
  }
  void only(const YAML::Node& m, const std::string& path, std::initializer_list<const char*> keys) const {
    if (!m.IsMap()) fail(path, "expected a mapping");
    for (const auto& kv : m) {
      const std::string k = kv.first.Scalar();
      if (std::none_of(keys.begin(), keys.end(), [&](const char* a) { return k == a; })) {
        std::string list;
        for (const char* a : keys) list += std::string(list.empty() ? "" : ", ") + a;
        fail(path + "." + k, "unknown key (expected one of: " + list + ")");
      }
    }
  }
  double num(const YAML::Node& m, const char* k, const std::string& path, double def) const {
    if (!m[k]) return def;
    const YAML::Node n = m[k];
    const std::string key = path + "." + k;
    if (!n.IsScalar()) fail(key, "expected a number");
    char* end = nullptr;
    errno = 0;
    const double v = std::strtod(n.Scalar().c_str(), &end);
    if (n.Scalar().empty() || *end != '\0' || errno == ERANGE || !std::isfinite(v))
      fail(key, "expected a number, got \"" + n.Scalar() + "\"");
    return v;
  }
  long integer(const YAML::Node& m, const char* k, const std::string& path, long def, long lo,
               long hi) const {
    if (!m[k]) return def;
    const YAML::Node n = m[k];
    const std::string key = path + "." + k;
    if (!n.IsScalar()) fail(key, "expected an integer");
    char* end = nullptr;
    errno = 0;
    const long v = std::strtol(n.Scalar().c_str(), &end, 0);  // 0x18 allowed for addresses
    if (n.Scalar().empty() || *end != '\0' || errno == ERANGE)
      fail(key, "expected an integer, got \"" + n.Scalar() + "\"");
    if (v < lo || v > hi) fail(key, "must be in " + std::to_string(lo) + ".." + std::to_string(hi));
    return v;
  }
  std::string str(const YAML::Node& m, const char* k, const std::string& path, const std::string& def) const {
    if (!m[k]) return def;
    if (!m[k].IsScalar()) fail(path + "." + k, "expected a string");
    return m[k].Scalar();
  }
  bool boolean(const YAML::Node& m, const char* k, const std::string& path, bool def) const {
    if (!m[k]) return def;
    const std::string s = m[k].IsScalar() ? m[k].Scalar() : "";
    if (s == "true") return true;
    if (s == "false") return false;
    fail(path + "." + k, "expected true or false, got \"" + s + "\"");
  }
  template <class T>
  T choice(const YAML::Node& m, const char* k, const std::string& path, T def,
           std::initializer_list<std::pair<const char*, T>> options) const {
    if (!m[k]) return def;
    const std::string s = m[k].IsScalar() ? m[k].Scalar() : "";
    for (const auto& [name, v] : options)
      if (s == name) return v;
    std::string list;
    for (const auto& o : options) list += std::string(list.empty() ? "" : ", ") + o.first;
    fail(path + "." + k, "expected one of " + list + ", got \"" + s + "\"");
  }

 private:
  std::string where_;
};

template <class E>
E pick_code(const P& p, const std::string& key, double v, std::initializer_list<std::pair<double, E>> table) {
  std::string list;
  for (const auto& [value, code] : table) {
    if (std::abs(v - value) < 1e-6 * std::max(1.0, value)) return code;
    char b[32];
    std::snprintf(b, sizeof b, "%s%g", list.empty() ? "" : ", ", value);
    list += b;
  }
  p.fail(key, "expected one of " + list);
}

// A path in a config, relative to the config file's folder.
std::string relative_to_config(const std::string& path, const std::string& where) {
  const auto slash = where.rfind('/');
  if (path.empty() || path[0] == '/' || slash == std::string::npos) return path;
  return where.substr(0, slash + 1) + path;
}

// `signing: {key_file: PATH, link_id: N}` of a MAVLink link; the key is read
// here, so a missing or short key file stops the start naming it.
void parse_signing(const P& p, const YAML::Node& n, const std::string& path, const std::string& where,
                   std::string& key_file, mavlink::SigningKey& key, int& link_id) {
  p.only(n, path, {"key_file", "link_id"});
  key_file = relative_to_config(p.str(n, "key_file", path, ""), where);
  if (key_file.empty()) p.fail(path + ".key_file", "missing (a file with the 32-byte key)");
  link_id = static_cast<int>(p.integer(n, "link_id", path, 0, 0, 255));
  try {
    key = mavlink::load_signing_key(key_file);
  } catch (const std::exception& e) {
    p.fail(path + ".key_file", e.what());
  }
}

void parse_mavlink_imu(const P& p, const YAML::Node& n, const std::string& path, const std::string& where,
                       MavlinkImuConfig& c) {
  p.only(n, path,
         {"udp", "serial_device", "serial_baud", "message", "rate_hz", "sysid", "compid", "target_sysid",
          "target_compid", "raw_acc_mps2_per_lsb", "raw_gyro_rad_s_per_lsb", "timesync_rate_hz",
          "timesync_max_rtt_ms", "max_latency_ms", "gap_periods", "signing"});
  c.udp = p.str(n, "udp", path, "");
  c.serial_device = p.str(n, "serial_device", path, "");
  c.serial_baud = static_cast<int>(p.integer(n, "serial_baud", path, c.serial_baud, 1200, 4000000));
  if (c.udp.empty() == c.serial_device.empty())
    p.fail(path, "expected one of udp (HOST:PORT) or serial_device");
  c.message = p.choice<MavlinkImuMessage>(n, "message", path, MavlinkImuMessage::kHighres,
                                          {{"highres_imu", MavlinkImuMessage::kHighres},
                                           {"scaled_imu", MavlinkImuMessage::kScaled},
                                           {"raw_imu", MavlinkImuMessage::kRaw}});
  c.rate_hz = p.num(n, "rate_hz", path, c.rate_hz);
  if (!(c.rate_hz > 0 && c.rate_hz <= 2000)) p.fail(path + ".rate_hz", "must be in (0, 2000]");
  c.sysid = static_cast<uint8_t>(p.integer(n, "sysid", path, c.sysid, 1, 255));
  c.compid = static_cast<uint8_t>(p.integer(n, "compid", path, c.compid, 1, 255));
  c.target_sysid = static_cast<uint8_t>(p.integer(n, "target_sysid", path, c.target_sysid, 0, 255));
  c.target_compid = static_cast<uint8_t>(p.integer(n, "target_compid", path, c.target_compid, 0, 255));
  c.raw_acc_mps2_per_lsb = p.num(n, "raw_acc_mps2_per_lsb", path, 0);
  c.raw_gyro_rad_s_per_lsb = p.num(n, "raw_gyro_rad_s_per_lsb", path, 0);
  if (c.message == MavlinkImuMessage::kRaw && !(c.raw_acc_mps2_per_lsb > 0 && c.raw_gyro_rad_s_per_lsb > 0)) {
    p.fail(path + ".raw_acc_mps2_per_lsb",
           "message raw_imu needs raw_acc_mps2_per_lsb and raw_gyro_rad_s_per_lsb > 0 "
           "(the board's sensor scale)");
  }
  c.timesync_rate_hz = p.num(n, "timesync_rate_hz", path, c.timesync_rate_hz);
  if (!(c.timesync_rate_hz > 0))
    p.fail(path + ".timesync_rate_hz", "must be > 0 (the samples need the clock)");
  const double rtt_ms =
      p.num(n, "timesync_max_rtt_ms", path, 1e-6 * static_cast<double>(c.timesync.max_rtt_ns));
  if (!(rtt_ms > 0)) p.fail(path + ".timesync_max_rtt_ms", "must be > 0");
  c.timesync.max_rtt_ns = static_cast<int64_t>(rtt_ms * 1e6);
  const double lat_ms = p.num(n, "max_latency_ms", path, 1e-6 * static_cast<double>(c.max_latency_ns));
  if (!(lat_ms > 0)) p.fail(path + ".max_latency_ms", "must be > 0");
  c.max_latency_ns = static_cast<int64_t>(lat_ms * 1e6);
  c.gap_periods = p.num(n, "gap_periods", path, c.gap_periods);
  if (!(c.gap_periods > 1)) p.fail(path + ".gap_periods", "must be > 1");
  if (const YAML::Node sg = n["signing"]) {
    std::string file;
    int link = 0;
    parse_signing(p, sg, path + ".signing", where, file, c.key, link);
    c.signing = true;
    c.link_id = static_cast<uint8_t>(link);
  }
}

}  // namespace

DriverSettings driver_settings_from_yaml_node(const YAML::Node& root, const std::string& where) {
  P p(where);
  DriverSettings d;
  if (!root || root.IsNull()) p.fail("drivers", "missing (required)");
  p.only(root, "drivers", {"camera", "imu", "strobe", "log"});

  if (const YAML::Node c = root["camera"]) {
    const std::string path = "drivers.camera";
    p.only(c, path, {"type", "width_px", "height_px", "rate_hz", "openni2", "v4l2", "d4xx"});
    CameraSettings& cs = d.camera;
    cs.type = p.choice<CameraType>(c, "type", path, CameraType::kNone,
                                   {{"none", CameraType::kNone},
                                    {"openni2", CameraType::kOpenNi2},
                                    {"v4l2", CameraType::kV4l2},
                                    {"d4xx", CameraType::kD4xx},
                                    {"log", CameraType::kLog}});
    cs.width_px = static_cast<int>(p.integer(c, "width_px", path, 640, 1, 8192));
    cs.height_px = static_cast<int>(p.integer(c, "height_px", path, 480, 1, 8192));
    cs.rate_hz = p.num(c, "rate_hz", path, 30);
    if (cs.rate_hz <= 0 || cs.rate_hz > 1000) p.fail(path + ".rate_hz", "must be in (0, 1000]");
    if (const YAML::Node o = c["openni2"]) {
      const std::string op = path + ".openni2";
      p.only(o, op, {"uri", "registration", "frame_sync", "mirror"});
      cs.openni2_uri = p.str(o, "uri", op, "");
      cs.openni2_registration =
          p.choice<bool>(o, "registration", op, true, {{"depth_to_color", true}, {"off", false}});
      cs.openni2_frame_sync = p.boolean(o, "frame_sync", op, true);
      cs.openni2_mirror = p.boolean(o, "mirror", op, false);
    }
    if (const YAML::Node v = c["v4l2"]) {
      const std::string vp = path + ".v4l2";
      p.only(v, vp,
             {"color_device", "color_format", "depth_device", "depth_format", "depth_unit_m", "buffers",
              "readout_us", "right_device", "stereo_layout"});
      cs.v4l2_color_device = p.str(v, "color_device", vp, "");
      cs.v4l2_color_format = p.choice<std::string>(v, "color_format", vp, "yuyv",
                                                   {{"yuyv", "yuyv"}, {"mjpeg", "mjpeg"}, {"grey", "grey"}});
      cs.v4l2_depth_device = p.str(v, "depth_device", vp, "");
      cs.v4l2_depth_format = p.choice<std::string>(v, "depth_format", vp, "z16", {{"z16", "z16"}});
      cs.v4l2_depth_unit_m = p.num(v, "depth_unit_m", vp, 0.001);
      if (cs.v4l2_depth_unit_m <= 0) p.fail(vp + ".depth_unit_m", "must be > 0");
      cs.v4l2_buffers = static_cast<int>(p.integer(v, "buffers", vp, 4, 2, 32));
      cs.v4l2_readout_ns = 1000 * p.integer(v, "readout_us", vp, 0, 0, 1'000'000);
      cs.v4l2_right_device = p.str(v, "right_device", vp, "");
      cs.v4l2_stereo_layout = p.choice<std::string>(v, "stereo_layout", vp, "off",
                                                    {{"off", "off"}, {"side_by_side", "side_by_side"}});
      if (!cs.v4l2_right_device.empty() && cs.v4l2_stereo_layout != "off")
        p.fail(vp + ".stereo_layout", "side_by_side and right_device exclude each other (one right image)");
    }
    if (const YAML::Node v = c["d4xx"]) {
      // RealSense D4xx over V4L2 + UVC metadata (docs/realsense.md lists every key and its default).
      const std::string vp = path + ".d4xx";
      p.only(v, vp,
             {"card_match", "color_device", "color_meta_device", "depth_device", "depth_meta_device",
              "infrared_device", "infrared_meta_device", "image", "depth", "infrared", "depth_width_px",
              "depth_height_px", "depth_unit_m", "buffers", "metadata_wait_ms", "pair_tolerance_us",
              "readout_us"});
      CameraSettings::D4xx& x = cs.d4xx;
      x.card_match = p.str(v, "card_match", vp, "RealSense");
      x.color_device = p.str(v, "color_device", vp, "");
      x.color_meta_device = p.str(v, "color_meta_device", vp, "");
      x.depth_device = p.str(v, "depth_device", vp, "");
      x.depth_meta_device = p.str(v, "depth_meta_device", vp, "");
      x.infrared_device = p.str(v, "infrared_device", vp, "");
      x.infrared_meta_device = p.str(v, "infrared_meta_device", vp, "");
      x.image =
          p.choice<std::string>(v, "image", vp, "color", {{"color", "color"}, {"infrared1", "infrared1"}});
      x.depth = p.boolean(v, "depth", vp, true);
      x.infrared =
          p.choice<std::string>(v, "infrared", vp, "off", {{"off", "off"}, {"y8", "y8"}, {"y8i", "y8i"}});
      x.depth_width_px = static_cast<int>(p.integer(v, "depth_width_px", vp, 0, 0, 8192));
      x.depth_height_px = static_cast<int>(p.integer(v, "depth_height_px", vp, 0, 0, 8192));
      x.depth_unit_m = p.num(v, "depth_unit_m", vp, 0.001);
      if (x.depth_unit_m <= 0) p.fail(vp + ".depth_unit_m", "must be > 0");
      x.buffers = static_cast<int>(p.integer(v, "buffers", vp, 4, 2, 32));
      x.metadata_wait_ms = static_cast<int>(p.integer(v, "metadata_wait_ms", vp, 2, 0, 100));
      x.pair_tolerance_ns = 1000 * p.integer(v, "pair_tolerance_us", vp, 0, 0, 1'000'000);
      x.readout_ns = 1000 * p.integer(v, "readout_us", vp, 0, 0, 1'000'000);
      if (x.image == "infrared1" && x.infrared == "off")
        p.fail(vp + ".infrared", "must be y8 or y8i when image is infrared1");
    }
    if (cs.type == CameraType::kV4l2 && cs.v4l2_color_device.empty())
      p.fail(path + ".v4l2.color_device", "missing (required for type v4l2)");
  }

  if (const YAML::Node m = root["imu"]) {
    const std::string path = "drivers.imu";
    p.only(m, path,
           {"type", "acc_range_g", "acc_bandwidth_hz", "gyro_range_dps", "gyro_odr_hz", "gyro_bandwidth_hz",
            "axis_remap", "i2c", "usb", "mavlink", "iio"});
    ImuSettings& is = d.imu;
    is.type = p.choice<ImuType>(m, "type", path, ImuType::kNone,
                                {{"none", ImuType::kNone},
                                 {"bmx055_i2c", ImuType::kBmx055I2c},
                                 {"bmx055_usb", ImuType::kBmx055Usb},
                                 {"log", ImuType::kLog},
                                 {"mavlink", ImuType::kMavlink},
                                 {"iio", ImuType::kIio}});
    bmx055::Config& b = is.bmx055;
    using namespace bmx055;
    b.acc_range = pick_code<acc::Range>(
        p, path + ".acc_range_g", p.num(m, "acc_range_g", path, 16),
        {{2, acc::Range::k2g}, {4, acc::Range::k4g}, {8, acc::Range::k8g}, {16, acc::Range::k16g}});
    b.acc_bw =
        pick_code<acc::Bandwidth>(p, path + ".acc_bandwidth_hz", p.num(m, "acc_bandwidth_hz", path, 250),
                                  {{7.81, acc::Bandwidth::k7_81Hz},
                                   {15.63, acc::Bandwidth::k15_63Hz},
                                   {31.25, acc::Bandwidth::k31_25Hz},
                                   {62.5, acc::Bandwidth::k62_5Hz},
                                   {125, acc::Bandwidth::k125Hz},
                                   {250, acc::Bandwidth::k250Hz},
                                   {500, acc::Bandwidth::k500Hz},
                                   {1000, acc::Bandwidth::k1000Hz}});
    b.gyro_range = pick_code<gyro::Range>(p, path + ".gyro_range_dps", p.num(m, "gyro_range_dps", path, 2000),
                                          {{2000, gyro::Range::k2000dps},
                                           {1000, gyro::Range::k1000dps},
                                           {500, gyro::Range::k500dps},
                                           {250, gyro::Range::k250dps},
                                           {125, gyro::Range::k125dps}});
    const double odr = p.num(m, "gyro_odr_hz", path, 400);
    const double bw = p.num(m, "gyro_bandwidth_hz", path, 47);
    const std::pair<double, double> odr_bw[] = {{2000, 523}, {2000, 230}, {1000, 116}, {400, 47},
                                                {200, 23},   {100, 12},   {200, 64},   {100, 32}};
    bool found = false;
    for (unsigned i = 0; i < 8; ++i) {
      if (odr_bw[i].first == odr && odr_bw[i].second == bw) {
        b.gyro_bw = static_cast<gyro::Bandwidth>(i);
        found = true;
      }
    }
    if (!found) {
      p.fail(path + ".gyro_odr_hz",
             "gyro_odr_hz/gyro_bandwidth_hz must be a BMG160 pair: 2000/523, 2000/230, "
             "1000/116, 400/47, 200/23, 100/12, 200/64, 100/32");
    }
    if (const YAML::Node r = m["axis_remap"]) {
      if (!r.IsSequence() || r.size() != 3)
        p.fail(path + ".axis_remap", "expected three of +x -x +y -y +z -z");
      for (size_t i = 0; i < 3; ++i) {
        const std::string s = r[i].IsScalar() ? r[i].Scalar() : "";
        if (s.size() != 2 || (s[0] != '+' && s[0] != '-') || s[1] < 'x' || s[1] > 'z') {
          p.fail(path + ".axis_remap[" + std::to_string(i) + "]",
                 "expected +x, -x, +y, -y, +z or -z, got \"" + s + "\"");
        }
        b.axis_remap[i] = static_cast<int8_t>((s[0] == '-' ? -1 : 1) * (s[1] - 'x' + 1));
      }
    }
    is.usb.acc_range = b.acc_range;
    is.usb.gyro_range = b.gyro_range;
    is.usb.axis_remap = b.axis_remap;
    is.iio.axis_remap = b.axis_remap;
    if (const YAML::Node i2c = m["i2c"]) {
      const std::string ip = path + ".i2c";
      p.only(i2c, ip,
             {"bus_device", "acc_i2c_addr", "gyro_i2c_addr", "mag_enabled", "mag_i2c_addr", "data_ready",
              "gpio_chip", "gpio_line", "poll_period_us", "gyro_fifo_watermark_frames",
              "acc_fifo_watermark_frames", "self_test"});
      is.i2c_bus_device = p.str(i2c, "bus_device", ip, "");
      b.acc_addr = static_cast<uint8_t>(p.integer(i2c, "acc_i2c_addr", ip, 0x18, 0x18, 0x19));
      b.gyro_addr = static_cast<uint8_t>(p.integer(i2c, "gyro_i2c_addr", ip, 0x68, 0x68, 0x69));
      b.mag_enabled = p.boolean(i2c, "mag_enabled", ip, false);
      b.mag_addr = static_cast<uint8_t>(p.integer(i2c, "mag_i2c_addr", ip, 0x10, 0x10, 0x13));
      b.drdy = p.choice<DataReadyMode>(i2c, "data_ready", ip, DataReadyMode::kPoll,
                                       {{"gpio", DataReadyMode::kGpio}, {"poll", DataReadyMode::kPoll}});
      is.gpio_chip = p.str(i2c, "gpio_chip", ip, "");
      is.gpio_line = static_cast<int>(p.integer(i2c, "gpio_line", ip, -1, -1, 1023));
      b.poll_period_ns = 1000 * p.integer(i2c, "poll_period_us", ip, 5000, 100, 1'000'000);
      b.gyro_watermark_frames = static_cast<int>(p.integer(i2c, "gyro_fifo_watermark_frames", ip, 4, 1, 99));
      b.acc_watermark_frames = static_cast<int>(p.integer(i2c, "acc_fifo_watermark_frames", ip, 5, 1, 31));
      b.self_test = p.boolean(i2c, "self_test", ip, true);
      if (b.drdy == DataReadyMode::kGpio && (is.gpio_chip.empty() || is.gpio_line < 0))
        p.fail(ip + ".gpio_line", "data_ready: gpio needs gpio_chip and gpio_line");
    }
    if (const YAML::Node u = m["usb"]) {
      const std::string up = path + ".usb";
      p.only(u, up,
             {"vid", "pid", "endpoint_in", "latency_floor_us", "read_timeout_ms", "no_data_timeout_ms"});
      is.usb.vid = static_cast<uint16_t>(p.integer(u, "vid", up, usb_bridge::kDefaultVid, 0, 0xFFFF));
      is.usb.pid = static_cast<uint16_t>(p.integer(u, "pid", up, usb_bridge::kDefaultPid, 0, 0xFFFF));
      is.usb.endpoint_in = static_cast<uint8_t>(p.integer(u, "endpoint_in", up, 0x81, 0x81, 0x8F));
      is.usb.clock.latency_floor_ns = 1000 * p.integer(u, "latency_floor_us", up, 0, 0, 100'000);
      is.usb.read_timeout_ms = static_cast<int>(p.integer(u, "read_timeout_ms", up, 20, 1, 10'000));
      is.usb.no_data_timeout_ns = 1'000'000 * p.integer(u, "no_data_timeout_ms", up, 200, 1, 60'000);
    }
    // ---- Linux IIO (docs/drivers/iio.md) ----
    if (const YAML::Node x = m["iio"]) {
      const std::string xp = path + ".iio";
      p.only(x, xp,
             {"device", "accel_device", "gyro_device", "sysfs_root", "dev_root", "rate_hz", "accel_rate_hz",
              "gyro_rate_hz", "timestamp_clock", "buffer_length_samples", "watermark_samples",
              "read_timeout_ms", "stall_timeout_ms", "max_stamp_gap_ms", "latency_floor_us"});
      iio::ImuConfig& c = is.iio;
      c.device = p.str(x, "device", xp, c.device);
      c.accel_device = p.str(x, "accel_device", xp, c.accel_device);
      c.gyro_device = p.str(x, "gyro_device", xp, c.gyro_device);
      c.sysfs_root = p.str(x, "sysfs_root", xp, c.sysfs_root);
      c.dev_root = p.str(x, "dev_root", xp, c.dev_root);
      const auto rel = [&](std::string& dir) {
        const auto slash = where.rfind('/');
        if (!dir.empty() && dir[0] != '/' && slash != std::string::npos)
          dir = where.substr(0, slash + 1) + dir;
      };
      rel(c.sysfs_root);
      rel(c.dev_root);
      c.rate_hz = p.num(x, "rate_hz", xp, c.rate_hz);
      c.accel_rate_hz = p.num(x, "accel_rate_hz", xp, c.accel_rate_hz);
      c.gyro_rate_hz = p.num(x, "gyro_rate_hz", xp, c.gyro_rate_hz);
      c.timestamp_clock = p.choice<std::string>(x, "timestamp_clock", xp, c.timestamp_clock,
                                                {{"monotonic", "monotonic"},
                                                 {"boottime", "boottime"},
                                                 {"realtime", "realtime"},
                                                 {"monotonic_raw", "monotonic_raw"},
                                                 {"tai", "tai"}});
      c.buffer_length_samples =
          static_cast<int>(p.integer(x, "buffer_length_samples", xp, 512, 2, 1'000'000));
      c.watermark_samples = static_cast<int>(p.integer(x, "watermark_samples", xp, 1, 1, 1'000'000));
      c.read_timeout_ms = static_cast<int>(p.integer(x, "read_timeout_ms", xp, 20, 1, 10'000));
      c.stall_timeout_ns = 1'000'000 * p.integer(x, "stall_timeout_ms", xp, 200, 1, 60'000);
      c.max_stamp_gap_ns = 1'000'000 * p.integer(x, "max_stamp_gap_ms", xp, 1000, 1, 3'600'000);
      c.clock.latency_floor_ns = 1000 * p.integer(x, "latency_floor_us", xp, 0, 0, 100'000);
    }
    if (is.type == ImuType::kIio) {
      try {
        is.iio.validate();
      } catch (const std::invalid_argument& e) {
        const std::string w = e.what();
        const auto colon = w.find(": ");
        p.fail(path + ".iio." + w.substr(0, colon),
               colon == std::string::npos ? "invalid" : w.substr(colon + 2));
      }
    }
    try {
      b.validate();
    } catch (const std::invalid_argument& e) {
      p.fail(path, e.what());
    }
    if (is.type == ImuType::kBmx055I2c && is.i2c_bus_device.empty())
      p.fail(path + ".i2c.bus_device", "missing (required for type bmx055_i2c)");
    if (const YAML::Node ml = m["mavlink"]) parse_mavlink_imu(p, ml, path + ".mavlink", where, is.mavlink);
    if (is.type == ImuType::kMavlink && !m["mavlink"])
      p.fail(path + ".mavlink", "missing (required for type mavlink: udp or serial_device)");
  }

  if (const YAML::Node s = root["strobe"]) {
    const std::string sp = "drivers.strobe";
    p.only(s, sp, {"enabled", "initial_offset_us", "tolerance_us"});
    d.strobe.enabled = p.boolean(s, "enabled", sp, false);
    d.strobe.initial_offset_ns = 1000 * p.integer(s, "initial_offset_us", sp, 0, -1'000'000, 1'000'000);
    d.strobe.tolerance_ns = 1000 * p.integer(s, "tolerance_us", sp, 8000, 1, 1'000'000);
  }
  if (const YAML::Node l = root["log"]) {
    p.only(l, "drivers.log", {"path", "pace"});
    d.log_path = p.str(l, "path", "drivers.log", "");
    d.log_pace = p.choice<ReplayPace>(l, "pace", "drivers.log", ReplayPace::kRealtime,
                                      {{"realtime", ReplayPace::kRealtime},
                                       {"fast", ReplayPace::kFast},
                                       {"lockstep", ReplayPace::kLockstep}});
    const auto slash = where.rfind('/');
    if (!d.log_path.empty() && d.log_path[0] != '/' && slash != std::string::npos)
      d.log_path = where.substr(0, slash + 1) + d.log_path;
  }
  const bool cam_log = d.camera.type == CameraType::kLog, imu_log = d.imu.type == ImuType::kLog;
  if (cam_log != imu_log) p.fail("drivers", "camera.type and imu.type must both be log, or neither");
  if (cam_log && d.log_path.empty()) p.fail("drivers.log.path", "missing (required for the log sensors)");
  return d;
}

MavlinkSettings mavlink_settings_from_yaml_node(const YAML::Node& node, const std::string& where) {
  MavlinkSettings m;
  if (!node) return m;
  P p(where);
  const std::string path = "mavlink";
  p.only(node, path,
         {"udp", "serial_device", "serial_baud", "sysid", "compid", "R_FB", "odometry_rate_hz",
          "heartbeat_rate_hz", "timesync", "timesync_max_rtt_ms", "signing"});
  m.present = true;
  m.udp = p.str(node, "udp", path, m.udp);
  m.serial_device = p.str(node, "serial_device", path, m.serial_device);
  m.serial_baud = static_cast<int>(p.integer(node, "serial_baud", path, m.serial_baud, 1200, 4000000));
  m.sysid = static_cast<int>(p.integer(node, "sysid", path, m.sysid, 1, 255));
  m.compid = static_cast<int>(p.integer(node, "compid", path, m.compid, 1, 255));
  if (const YAML::Node r = node["R_FB"]) {
    if (!r.IsSequence() || r.size() != 9) p.fail(path + ".R_FB", "expected 9 numbers (3x3, row-major)");
    for (int i = 0; i < 9; ++i) {
      YAML::Node holder;
      holder["v"] = r[i];
      m.R_FB[i] = p.num(holder, "v", path + ".R_FB[" + std::to_string(i) + "]", 0.0);
    }
    // A rotation: orthonormal rows and determinant +1 (a mirror is a mistake).
    const auto& R = m.R_FB;
    double worst = 0;
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        worst = std::max(worst, std::abs(R[3 * i] * R[3 * j] + R[3 * i + 1] * R[3 * j + 1] +
                                         R[3 * i + 2] * R[3 * j + 2] - (i == j ? 1.0 : 0.0)));
      }
    }
    const double det = R[0] * (R[4] * R[8] - R[5] * R[7]) - R[1] * (R[3] * R[8] - R[5] * R[6]) +
                       R[2] * (R[3] * R[7] - R[4] * R[6]);
    if (worst > 1e-6 || det < 0)
      p.fail(path + ".R_FB", "not a rotation (rows must be orthonormal, determinant +1)");
  }
  m.odometry_rate_hz = p.num(node, "odometry_rate_hz", path, m.odometry_rate_hz);
  m.heartbeat_rate_hz = p.num(node, "heartbeat_rate_hz", path, m.heartbeat_rate_hz);
  m.timesync = p.boolean(node, "timesync", path, m.timesync);
  m.timesync_max_rtt_ms = p.num(node, "timesync_max_rtt_ms", path, m.timesync_max_rtt_ms);
  if (m.odometry_rate_hz < 0) p.fail(path + ".odometry_rate_hz", "must be >= 0 (0 = every pose)");
  if (m.heartbeat_rate_hz < 0) p.fail(path + ".heartbeat_rate_hz", "must be >= 0");
  if (!(m.timesync_max_rtt_ms > 0)) p.fail(path + ".timesync_max_rtt_ms", "must be > 0");
  if (!m.udp.empty() && !m.serial_device.empty())
    p.fail(path, "udp and serial_device both set: one link at a time");
  if (const YAML::Node sg = node["signing"]) {
    parse_signing(p, sg, path + ".signing", where, m.signing_key_file, m.signing_key, m.signing_link_id);
    m.signing = true;
  }
  return m;
}

RecordSettings record_settings_from_yaml_node(const YAML::Node& node, const std::string& where) {
  RecordSettings r;
  if (!node) return r;
  P p(where);
  const std::string path = "record";
  p.only(node, path, {"image_codec", "zstd_level"});
  const std::string codec = p.str(node, "image_codec", path, klog::codec_name(r.compression.codec));
  if (!klog::parse_codec(codec, r.compression.codec))
    p.fail(path + ".image_codec", "expected one of zstd, lz4, none, got \"" + codec + "\"");
  r.compression.zstd_level = static_cast<int>(p.integer(node, "zstd_level", path, r.compression.zstd_level,
                                                        klog::zstd_min_level(), klog::zstd_max_level()));
  return r;
}

Ros2Settings ros2_settings_from_yaml_node(const YAML::Node& node, const std::string& where) {
  Ros2Settings r;
  if (!node) return r;
  P p(where);
  const std::string path = "ros2";
  p.only(node, path, {"map_points_rate_hz"});
  r.map_points_rate_hz = p.num(node, "map_points_rate_hz", path, r.map_points_rate_hz);
  // Above the camera rate every frame would copy the map for nothing.
  if (!(r.map_points_rate_hz >= 0 && r.map_points_rate_hz <= 30))
    p.fail(path + ".map_points_rate_hz", "expected a number in [0, 30]");
  return r;
}

namespace {
constexpr const char* kThreadNames[kPipelineThreads] = {
    "kst-imu",       "kst-cam", "kst-replay", "kst-propagate", "kst-estimator",
    "kst-optimizer", "kst-log", "kst-viewer", "kst-mapping",   "kst-loop"};
}  // namespace

ThreadTable default_thread_table() {
  ThreadTable t;
  // What the pipeline ran with before the table became configurable: only the
  // IMU-rate pose asks for SCHED_FIFO (it sleeps between samples, so it cannot
  // starve anything), the rest is SCHED_OTHER on any CPU. A live rig's config
  // names its own table (configs/*.yaml, docs/threads.md).
  for (int i = 0; i < kPipelineThreads; ++i) t.spec[i] = rt::ThreadSpec{kThreadNames[i], 0, -1, 0};
  t[PipelineThread::kImu].period_ns = 2'500'000;
  t[PipelineThread::kCamera].period_ns = 33'333'333;
  t[PipelineThread::kPropagate].priority = 60;
  return t;
}

std::string thread_names() {
  std::string s;
  for (const char* n : kThreadNames) s += std::string(s.empty() ? "" : ", ") + n;
  return s;
}

ThreadTable thread_table_from_yaml_node(const YAML::Node& node, const std::string& where) {
  ThreadTable t = default_thread_table();
  if (!node) return t;
  P p(where);
  if (!node.IsMap()) p.fail("threads", "expected a mapping of thread name -> {cpu, policy, priority}");
  t.from_config = true;
  for (const auto& kv : node) {
    const std::string name = kv.first.Scalar();
    int idx = -1;
    for (int i = 0; i < kPipelineThreads; ++i)
      if (name == kThreadNames[i]) idx = i;
    const std::string path = "threads." + name;
    if (idx < 0) p.fail(path, "unknown thread (expected one of: " + thread_names() + ")");
    const YAML::Node m = kv.second;
    p.only(m, path, {"cpu", "policy", "priority"});
    rt::ThreadSpec& s = t.spec[idx];
    s.cpu = static_cast<int>(p.integer(m, "cpu", path, -1, -1, 1023));
    const bool fifo = p.choice<bool>(m, "policy", path, s.priority > 0, {{"fifo", true}, {"other", false}});
    if (fifo && !m["priority"]) {
      if (s.priority <= 0) p.fail(path + ".priority", "missing (required for policy fifo, 1..99)");
    } else if (fifo) {
      const YAML::Node pr = m["priority"];
      char* end = nullptr;
      const std::string txt = pr.IsScalar() ? pr.Scalar() : "";
      const long v = std::strtol(txt.c_str(), &end, 10);
      if (txt.empty() || *end != '\0' || v < 1 || v > 99)
        p.fail(path + ".priority", "expected 1..99 for policy fifo, got \"" + txt + "\"");
      s.priority = static_cast<int>(v);
    } else {
      if (m["priority"] && !(m["priority"].IsScalar() && m["priority"].Scalar() == "0"))
        p.fail(path + ".priority", "policy other takes no priority (0 or absent)");
      s.priority = 0;
    }
  }
  return t;
}

std::string built_drivers_summary() {
  auto b = [](bool x) { return x ? "built" : "NOT built"; };
  return std::string("v4l2 ") + b(v4l2::v4l2_built()) + ", openni2 " + b(openni2::openni2_built()) +
         ", libusb (IMU bridge) " + b(libusb_built()) + ", i2c-dev (BMX055) " + b(i2c_dev_built()) +
         ", gpio-cdev (data-ready) " + b(bmx055::gpio_cdev_built()) + ", iio (sysfs) built";
}

DeviceReport probe_devices() {
  DeviceReport r;
  std::string err;
  for (const auto& d : v4l2::list_devices(&err)) {
    std::string fmts;
    for (uint32_t f : d.formats) fmts += (fmts.empty() ? "" : " ") + v4l2::fourcc_name(f);
    r.found.push_back(
        {"camera", "v4l2", d.path, d.card + " [" + d.driver + ", " + d.bus_info + "] formats: " + fmts});
  }
  if (!err.empty()) r.notes.push_back("v4l2: " + err);
  err.clear();
  // RealSense D4xx: its nodes grouped as camera.type d4xx would find them.
  for (const d4xx::NodeSet& n :
       d4xx::group_d4xx_nodes(d4xx::probe_v4l2_nodes(&err), d4xx::kDefaultCardMatch)) {
    auto node = [](const std::string& v, const std::string& m) {
      return v.empty() ? std::string("-") : v + (m.empty() ? std::string(" (no metadata node)") : " + " + m);
    };
    r.found.push_back({"camera", "d4xx", n.bus_info,
                       n.card + ": colour " + node(n.color, n.color_meta) + ", depth " +
                           node(n.depth, n.depth_meta) + ", infrared " + node(n.infrared, n.infrared_meta)});
  }
  err.clear();
  for (const auto& d : openni2::list_devices(&err)) r.found.push_back({"camera", "openni2", d, ""});
  if (!err.empty()) r.notes.push_back("openni2: " + err);
  // I2C: probe the BMX055 chip ids on every adapter (reads only).
  if (i2c_dev_built()) {
    std::vector<std::string> buses;
    if (DIR* dir = opendir("/dev")) {
      while (dirent* e = readdir(dir))
        if (std::string(e->d_name).rfind("i2c-", 0) == 0) buses.push_back(std::string("/dev/") + e->d_name);
      closedir(dir);
    }
    std::sort(buses.begin(), buses.end());
    if (buses.empty()) r.notes.push_back("i2c: no /dev/i2c-* adapters (i2c-dev module loaded?)");
    for (const auto& bus : buses) {
      LinuxI2cBus b;
      const std::string e = b.open(bus);
      if (!e.empty()) {
        r.notes.push_back("i2c: " + e);
        continue;
      }
      for (uint8_t acc : {bmx055::kAccAddrDefault, bmx055::kAccAddrAlt}) {
        uint8_t id = 0;
        if (b.read_regs(acc, bmx055::acc::kChipIdReg, &id, 1) != I2cStatus::kOk || id != bmx055::acc::kChipId)
          continue;
        std::string gyro = "gyro not found";
        for (uint8_t g : {bmx055::kGyroAddrDefault, bmx055::kGyroAddrAlt}) {
          if (b.read_regs(g, bmx055::gyro::kChipIdReg, &id, 1) == I2cStatus::kOk &&
              id == bmx055::gyro::kChipId) {
            char s[32];
            std::snprintf(s, sizeof s, "gyro at 0x%02x", g);
            gyro = s;
          }
        }
        char s[64];
        std::snprintf(s, sizeof s, "%s accelerometer at 0x%02x, ", bus.c_str(), acc);
        r.found.push_back({"imu", "bmx055-i2c", bus, std::string(s) + gyro});
      }
    }
  } else {
    r.notes.push_back("i2c: not built");
  }
  err.clear();
  for (const auto& u : list_usb_devices(usb_bridge::kDefaultVid, usb_bridge::kDefaultPid, &err)) {
    char s[64];
    std::snprintf(s, sizeof s, "bus %d address %d", u.bus, u.address);
    r.found.push_back({"imu", "usb-bridge", s, "serial " + (u.serial.empty() ? std::string("?") : u.serial)});
  }
  if (!err.empty()) r.notes.push_back("usb: " + err);
  // IIO: every device whose scan has accel or anglvel channels (sysfs reads only).
  err.clear();
  for (const auto& d : iio::list_devices(iio::kDefaultSysfsRoot, &err)) {
    if (!d.has_accel && !d.has_gyro) continue;
    std::string what = d.has_accel && d.has_gyro ? "accel + gyro" : d.has_accel ? "accel" : "gyro";
    what +=
        d.has_buffer && d.has_timestamp ? ", buffered with timestamps" : ", no buffer/timestamp (not usable)";
    r.found.push_back({"imu", "iio", d.dir, "name \"" + d.name + "\" (" + what + ")"});
  }
  if (!err.empty()) r.notes.push_back("iio: " + err);
  return r;
}

// ---- LiveSensors --------------------------------------------------------------------------

namespace {
class StrobeRingSink final : public StrobeSink {
 public:
  bool push(const StrobeStamp& s) noexcept override { return ring.try_push(s); }
  rt::SpscRing<StrobeStamp, 128> ring;
};
}  // namespace

struct LiveSensors::Impl {
  LiveConfig cfg;
  MonotonicHostClock clock;
  // IMU
  LinuxI2cBus i2c;
  bmx055::GpioDataReadyLine drdy;
  std::unique_ptr<bmx055::Driver> bmx;
  LibusbEndpoint usb;
  std::unique_ptr<UsbBridgeDriver> bridge;
  std::unique_ptr<MavlinkImuDriver> mav;  // the flight controller's IMU
  std::unique_ptr<iio::ImuDriver> iio_imu;
  StrobeRingSink strobes;
  // Cameras
  openni2::Camera oni;
  v4l2::Camera color, depth, right;  // right: a stereo rig's second node
  ImageBuffer rgb_buf, depth_buf, right_buf;
  ImageBuffer sbs_buf;  // side_by_side: the whole frame before it is split
  // RealSense D4xx (camera.type d4xx): its device clock's line is published
  // in d4xx_clock for an IMU driver on the same camera (docs/realsense.md).
  std::unique_ptr<d4xx::Camera> d4xx_cam;
  SharedDeviceClock d4xx_clock;
  std::string d4xx_nodes;  // which nodes were used (auto-found or configured)
  StrobeMatcher matcher;
  std::unique_ptr<KlogReader> log;  // the `log` sensors
  uint64_t log_imu = 0;
  uint64_t frames = 0, frame_errors = 0, frame_timeouts = 0, unpaired = 0;
  std::atomic<bool> stop{false};
  std::thread imu_thread, cam_thread;
  std::vector<std::pair<rt::ThreadSpec, rt::ThreadSetupReport>> thread_reports;

  void imu_loop(ImuSink& sink);
  void cam_loop(FrameSink& sink);
  std::string open_d4xx();
  void log_loop(ImuSink& imu, FrameSink& frames);
};

LiveSensors::LiveSensors(const LiveConfig& cfg) : impl_(std::make_unique<Impl>()) {
  Impl& m = *impl_;
  m.cfg = cfg;
  const DriverSettings& d = cfg.drivers;
  std::vector<std::string> missing;
  const size_t px = static_cast<size_t>(d.camera.width_px) * static_cast<size_t>(d.camera.height_px);
  m.rgb_buf.pixels.reserve(px * 3);
  m.depth_buf.pixels.reserve(px * 2);
  m.right_buf.pixels.reserve(px * 3);
  if (d.camera.v4l2_stereo_layout == "side_by_side") m.sbs_buf.pixels.reserve(2 * px * 3);
  StrobeMatchOptions so;
  so.initial_offset_ns = d.strobe.initial_offset_ns;
  so.tolerance_ns = d.strobe.tolerance_ns;
  m.matcher = StrobeMatcher(so);

  if (d.imu.type == ImuType::kLog) {
    try {
      m.log = std::make_unique<KlogReader>(d.log_path);
    } catch (const std::exception& e) {
      missing.push_back(std::string("log sensors: ") + e.what());
    }
  }
  switch (d.imu.type) {
    case ImuType::kNone:
    case ImuType::kLog:
      break;
    case ImuType::kBmx055I2c: {
      std::string e = m.i2c.open(d.imu.i2c_bus_device);
      if (!e.empty()) {
        missing.push_back("IMU (BMX055 over I2C): " + e);
        break;
      }
      uint8_t id = 0;
      if (m.i2c.read_regs(d.imu.bmx055.acc_addr, bmx055::acc::kChipIdReg, &id, 1) != I2cStatus::kOk) {
        char s[96];
        std::snprintf(s, sizeof s, ": no BMX055 accelerometer answers at 0x%02x", d.imu.bmx055.acc_addr);
        missing.push_back("IMU (BMX055 over I2C): " + d.imu.i2c_bus_device + s);
        break;
      }
      if (d.imu.bmx055.drdy == bmx055::DataReadyMode::kGpio) {
        e = m.drdy.open(d.imu.gpio_chip, static_cast<unsigned>(d.imu.gpio_line));
        if (!e.empty()) {
          missing.push_back("IMU data-ready line: " + e);
          break;
        }
      }
      m.bmx = std::make_unique<bmx055::Driver>(m.i2c, m.clock, d.imu.bmx055);
      break;
    }
    case ImuType::kBmx055Usb: {
      const std::string e = m.usb.open(d.imu.usb.vid, d.imu.usb.pid, d.imu.usb.endpoint_in);
      if (!e.empty()) {
        missing.push_back("IMU (BMX055 via USB bridge): " + e);
        break;
      }
      m.bridge = std::make_unique<UsbBridgeDriver>(m.usb, m.clock, d.imu.usb);
      break;
    }
    case ImuType::kMavlink: {
      try {
        m.mav = std::make_unique<MavlinkImuDriver>(d.imu.mavlink, m.clock);
      } catch (const std::exception& e) {
        missing.push_back(std::string("IMU (flight controller over MAVLink): ") + e.what());
      }
      break;
    }
    case ImuType::kIio: {
      m.iio_imu = std::make_unique<iio::ImuDriver>(m.clock, d.imu.iio);
      const std::string e = m.iio_imu->open();
      if (!e.empty()) {
        missing.push_back("IMU (Linux IIO): " + e);
        m.iio_imu.reset();
      }
      break;
    }
  }
  switch (d.camera.type) {
    case CameraType::kNone:
    case CameraType::kLog:
    case CameraType::kD4xx:
      break;  // opened below (open_d4xx)
    case CameraType::kOpenNi2: {
      openni2::Options o;
      o.uri = d.camera.openni2_uri;
      o.width = d.camera.width_px;
      o.height = d.camera.height_px;
      o.fps = static_cast<int>(std::lround(d.camera.rate_hz));
      o.registration = d.camera.openni2_registration;
      o.frame_sync = d.camera.openni2_frame_sync;
      o.mirror = d.camera.openni2_mirror;
      o.rig_depth_scale_m = cfg.rig.depth.scale_m_per_unit;
      const std::string e = m.oni.open(o);
      if (!e.empty()) missing.push_back("camera (OpenNI2): " + e);
      break;
    }
    case CameraType::kV4l2: {
      v4l2::Options o;
      o.device = d.camera.v4l2_color_device;
      o.request.width = d.camera.width_px;
      o.request.height = d.camera.height_px;
      o.request.fps = d.camera.rate_hz;
      o.request.preferred = {v4l2::fourcc_from_name(d.camera.v4l2_color_format)};
      o.buffers = d.camera.v4l2_buffers;
      o.readout_ns = d.camera.v4l2_readout_ns;
      const bool side_by_side = d.camera.v4l2_stereo_layout == "side_by_side";
      if (side_by_side) o.request.width = 2 * d.camera.width_px;
      std::string e = m.color.open(o);
      if (!e.empty()) {
        missing.push_back(
            std::string(side_by_side ? "stereo camera (V4L2, side by side): " : "colour camera (V4L2): ") +
            e);
      }
      if (!d.camera.v4l2_right_device.empty()) {
        v4l2::Options r = o;
        r.device = d.camera.v4l2_right_device;
        e = m.right.open(r);
        if (!e.empty()) missing.push_back("right camera (V4L2): " + e);
      }
      if (!d.camera.v4l2_depth_device.empty()) {
        o.device = d.camera.v4l2_depth_device;
        o.request.preferred = {v4l2::fourcc_from_name(d.camera.v4l2_depth_format)};
        o.depth_scale_m = d.camera.v4l2_depth_unit_m;
        o.rig_depth_scale_m = cfg.rig.depth.scale_m_per_unit;
        // A depth camera in the rig: its own size, and its frames registered to colour in the driver.
        o.depth_camera = cfg.rig.depth_camera;
        o.colour = cfg.rig.rgb;
        if (o.depth_camera.present) {
          o.request.width = o.depth_camera.intrinsics.width;
          o.request.height = o.depth_camera.intrinsics.height;
        }
        e = m.depth.open(o);
        if (!e.empty()) missing.push_back("depth camera (V4L2): " + e);
      }
      break;
    }
  }
  if (d.camera.type == CameraType::kD4xx) {
    const std::string e = m.open_d4xx();
    if (!e.empty()) missing.push_back("camera (RealSense D4xx): " + e);
  }
  if (d.imu.type == ImuType::kNone && d.camera.type == CameraType::kNone)
    missing.push_back("the config names no sensor (drivers.camera.type and drivers.imu.type are none)");
  if (!missing.empty()) {
    std::string msg = "cannot start the live sensors of " + cfg.path + ":";
    for (const auto& s : missing) msg += "\n  - " + s;
    msg += "\n  drivers in this build: " + built_drivers_summary();
    msg += "\n  (`kestrel devices` lists what is connected)";
    throw std::runtime_error(msg);
  }
}

// The D4xx's nodes: as configured, else found by card name (the first camera
// whose V4L2 card matches), each video node's metadata node beside it.
std::string LiveSensors::Impl::open_d4xx() {
  const CameraSettings& cs = cfg.drivers.camera;
  const CameraSettings::D4xx& x = cs.d4xx;
  d4xx::NodeSet nodes;
  nodes.color = x.color_device;
  nodes.color_meta = x.color_meta_device;
  nodes.depth = x.depth_device;
  nodes.depth_meta = x.depth_meta_device;
  nodes.infrared = x.infrared_device;
  nodes.infrared_meta = x.infrared_meta_device;
  const bool want_color = x.image == "color", want_ir = x.infrared != "off";
  const bool need_find = (want_color && nodes.color.empty()) || (x.depth && nodes.depth.empty()) ||
                         (want_ir && nodes.infrared.empty());
  if (need_find) {
    std::string err;
    const std::vector<d4xx::NodeSet> sets =
        d4xx::group_d4xx_nodes(d4xx::probe_v4l2_nodes(&err), x.card_match);
    if (sets.empty()) {
      return "no V4L2 camera whose card name contains \"" + x.card_match + "\"" +
             (err.empty() ? "" : " (" + err + ")") +
             "; set drivers.camera.d4xx.*_device or check `kestrel devices`";
    }
    const d4xx::NodeSet& f = sets.front();
    auto fill = [](std::string& dev, std::string& meta, const std::string& fdev, const std::string& fmeta) {
      if (dev.empty()) {
        dev = fdev;
        if (meta.empty()) meta = fmeta;
      }
    };
    fill(nodes.color, nodes.color_meta, f.color, f.color_meta);
    fill(nodes.depth, nodes.depth_meta, f.depth, f.depth_meta);
    fill(nodes.infrared, nodes.infrared_meta, f.infrared, f.infrared_meta);
  }
  auto meta = [](const std::string& m) { return m == "none" ? std::string() : m; };
  d4xx::Options o;
  o.color.enabled = want_color;
  o.color.video_device = nodes.color;
  o.color.meta_device = meta(nodes.color_meta);
  o.color.request.width = cs.width_px;
  o.color.request.height = cs.height_px;
  o.color.request.fps = cs.rate_hz;
  o.color.request.preferred = {v4l2::kYuyv, d4xx::kRgb24};
  o.depth.enabled = x.depth;
  o.depth.video_device = nodes.depth;
  o.depth.meta_device = meta(nodes.depth_meta);
  o.depth.request.width = x.depth_width_px > 0                         ? x.depth_width_px
                          : cfg.rig.depth_camera.present && want_color ? cfg.rig.depth_camera.intrinsics.width
                                                                       : cs.width_px;
  o.depth.request.height = x.depth_height_px > 0 ? x.depth_height_px
                           : cfg.rig.depth_camera.present && want_color
                               ? cfg.rig.depth_camera.intrinsics.height
                               : cs.height_px;
  o.depth.request.fps = cs.rate_hz;
  o.depth.request.preferred = {v4l2::kZ16};
  o.infrared.enabled = want_ir;
  o.infrared.video_device = nodes.infrared;
  o.infrared.meta_device = meta(nodes.infrared_meta);
  o.infrared.request.width = cs.width_px;
  o.infrared.request.height = cs.height_px;
  o.infrared.request.fps = cs.rate_hz;
  o.infrared.request.preferred = {x.infrared == "y8i" ? d4xx::kY8i : v4l2::kGrey};
  o.infrared_is_image = x.image == "infrared1";
  o.buffers = x.buffers;
  o.metadata_wait_ms = x.metadata_wait_ms;
  o.readout_ns = x.readout_ns;
  o.depth_unit_m = x.depth_unit_m;
  o.rig_depth_scale_m = cfg.rig.depth.scale_m_per_unit;
  o.depth_camera = want_color ? cfg.rig.depth_camera : DepthCamera{};
  o.image_camera = cfg.rig.rgb;
  o.pair_tolerance_ns = x.pair_tolerance_ns;
  o.shared_clock = &d4xx_clock;
  auto describe = [](const d4xx::StreamOptions& so) {
    if (!so.enabled) return std::string("off");
    return so.video_device + " + " + (so.meta_device.empty() ? std::string("no metadata") : so.meta_device);
  };
  d4xx_nodes =
      "colour " + describe(o.color) + ", depth " + describe(o.depth) + ", infrared " + describe(o.infrared);
  d4xx_cam = std::make_unique<d4xx::Camera>();
  std::string e = d4xx_cam->open(o);
  if (!e.empty()) d4xx_cam.reset();
  return e;
}

LiveSensors::~LiveSensors() { stop(); }

void LiveSensors::Impl::imu_loop(ImuSink& sink) {
  while (!stop.load(std::memory_order_relaxed)) {
    if (bmx) {
      const int64_t wake = bmx->step(sink);
      if (drdy.is_open() && bmx->state() == bmx055::State::kStream) {
        int64_t edge = 0;
        if (drdy.wait(std::min(wake, rt::now_ns() + 100'000'000), edge) == 1) bmx->notify_data_ready(edge);
      } else {
        rt::sleep_until_ns(std::min(wake, rt::now_ns() + 100'000'000));
      }
    } else if (iio_imu) {
      // Blocks in poll() on the device nodes (read_timeout_ms at most).
      const iio::ImuState st = iio_imu->step(sink);
      if (st == iio::ImuState::kDisconnected || st == iio::ImuState::kClosed) {
        rt::sleep_for_ns(1'000'000'000);
        (void)iio_imu->open();  // retried every second until the device is back
      }
    } else if (bridge) {
      if (bridge->step(sink, &strobes) == UsbBridgeState::kDisconnected) {
        rt::sleep_for_ns(1'000'000'000);
        const auto& u = cfg.drivers.imu.usb;
        if (usb.open(u.vid, u.pid, u.endpoint_in).empty())
          bridge = std::make_unique<UsbBridgeDriver>(usb, clock, u);
      }
    } else if (mav) {
      // Blocks on the link until bytes arrive or a request is due; the cap keeps stop() prompt.
      mav->step(sink, 100'000'000);
    } else {
      return;
    }
  }
}

void LiveSensors::Impl::cam_loop(FrameSink& sink) {
  const DriverSettings& d = cfg.drivers;
  const int timeout_ms = static_cast<int>(std::lround(3000.0 / d.camera.rate_hz));
  while (!stop.load(std::memory_order_relaxed)) {
    CameraFrame f;
    bool ok = false;
    if (d.camera.type == CameraType::kOpenNi2) {
      openni2::FrameMeta meta;
      const auto r = oni.grab(timeout_ms, rgb_buf, depth_buf, meta);
      ok = r == openni2::GrabResult::kFrame;
      if (r == openni2::GrabResult::kTimeout) ++frame_timeouts;
      if (r == openni2::GrabResult::kError) ++frame_errors;
      f.t_ns = meta.t_ns;
      f.t_recv_ns = meta.t_recv_ns;
      f.seq = meta.seq;
      f.exposure_us = meta.exposure_us;
      f.rgb = &rgb_buf;
      f.depth = &depth_buf;
    } else if (d.camera.type == CameraType::kV4l2) {
      v4l2::FrameMeta meta;
      const bool side_by_side = d.camera.v4l2_stereo_layout == "side_by_side";
      const auto r = color.grab(timeout_ms, side_by_side ? sbs_buf : rgb_buf, meta);
      ok = r == v4l2::GrabResult::kFrame;
      if (ok && side_by_side) {
        if (split_side_by_side(sbs_buf, rgb_buf, right_buf)) {
          f.right = &right_buf;
        } else {
          ++frame_errors;
          ok = false;
        }
      }
      if (ok && right.is_open()) {
        // The right node's frame nearest in time (within half a period), as depth below.
        v4l2::FrameMeta rm;
        if (right.grab(timeout_ms, right_buf, rm) == v4l2::GrabResult::kFrame &&
            std::llabs(rm.t_ns - meta.t_ns) < static_cast<int64_t>(0.5e9 / d.camera.rate_hz)) {
          f.right = &right_buf;
        } else {
          ++unpaired;
        }
      }
      if (r == v4l2::GrabResult::kTimeout) ++frame_timeouts;
      if (r == v4l2::GrabResult::kError) ++frame_errors;
      f.t_ns = meta.t_ns;
      f.t_recv_ns = meta.t_recv_ns;
      f.seq = meta.seq;
      f.exposure_us = meta.exposure_us;
      f.rgb = &rgb_buf;
      if (ok && depth.is_open()) {
        // Separate UVC nodes: the depth frame nearest in time (within half a period).
        v4l2::FrameMeta dm;
        if (depth.grab(timeout_ms, depth_buf, dm) == v4l2::GrabResult::kFrame &&
            std::llabs(dm.t_ns - meta.t_ns) < static_cast<int64_t>(0.5e9 / d.camera.rate_hz)) {
          f.depth = &depth_buf;
        } else {
          ++unpaired;
        }
      }
    } else if (d.camera.type == CameraType::kD4xx && d4xx_cam) {
      d4xx::Frame df;
      const auto r = d4xx_cam->grab(timeout_ms, df);
      ok = r == d4xx::Camera::Result::kFrame;
      if (r == d4xx::Camera::Result::kTimeout) ++frame_timeouts;
      if (r == d4xx::Camera::Result::kError) ++frame_errors;
      f.t_ns = df.image_meta.t_ns;
      f.t_recv_ns = df.image_meta.t_recv_ns;
      f.seq = df.image_meta.seq;
      f.exposure_us = df.image_meta.exposure_us;
      f.rgb = df.image;
      f.depth = df.depth;
      // Infrared 1 as the image with Y8I: Infrared 2 is a stereo rig's right image (same exposure).
      if (cfg.rig.stereo.present && cfg.drivers.camera.d4xx.image == "infrared1") f.right = df.ir2;
      if (ok && cfg.drivers.camera.d4xx.depth && df.depth == nullptr) ++unpaired;
    } else {
      return;
    }
    if (!ok) continue;
    if (d.strobe.enabled) {
      StrobeStamp s;
      while (strobes.ring.try_pop(s)) matcher.add_strobe(s);
      // Strobe = start of exposure (bridge clock): publish mid-exposure.
      const StrobeMatch sm = matcher.match(f.t_ns);
      f.strobe_matched = sm.matched;
      f.t_ns = sm.t_exposure_start_ns + static_cast<int64_t>(f.exposure_us) * 500;
    }
    ++frames;
    (void)sink.push_frame(f);
  }
}

// Both sensors from one file, released at the log's pace on the wall clock.
void LiveSensors::Impl::log_loop(ImuSink& imu, FrameSink& sink) {
  const int64_t offset_ns = log->rig().time_offset_cam_imu_ns;
  LogRecord r;
  int64_t wall0 = -1, log0 = 0;
  bool have_rgb = false;
  CameraFrame f;
  auto copy = [](const LogImage& in, ImageBuffer& out) {
    if (in.pixels.size() > out.pixels.capacity()) return false;  // larger than the config's camera
    out.t_ns = in.t_ns;
    out.t_recv_ns = rt::now_ns();
    out.seq = in.seq;
    out.width = in.width;
    out.height = in.height;
    out.format = in.format;
    out.pixels.assign(in.pixels.begin(), in.pixels.end());
    return true;
  };
  auto flush = [&] {
    if (!have_rgb) return;
    have_rgb = false;
    ++frames;
    (void)sink.push_frame(f);
  };
  while (!stop.load(std::memory_order_relaxed) && log->next(r)) {
    const bool image =
        r.type == RecordType::kRgb || r.type == RecordType::kDepth || r.type == RecordType::kRight;
    const int64_t t = r.type == RecordType::kImu ? r.imu.t_ns : image ? r.image.t_ns : -1;
    if (t < 0) continue;  // ground truth and events are not sensors
    if (wall0 < 0) wall0 = rt::now_ns(), log0 = t;
    const bool image_part = r.type == RecordType::kDepth || r.type == RecordType::kRight;
    if (!(image_part && have_rgb)) flush();
    const int64_t due = wall0 + (t - log0);
    if (due > rt::now_ns()) rt::sleep_until_ns(due);
    if (r.type == RecordType::kImu) {
      r.imu.t_recv_ns = rt::now_ns();
      ++log_imu;
      (void)imu.push(r.imu);
    } else if (r.type == RecordType::kRgb) {
      if (!copy(r.image, rgb_buf)) {
        ++frame_errors;
        continue;
      }
      f = CameraFrame{};
      f.t_ns = r.image.t_ns - offset_ns;  // the camera's own clock, as a driver stamps it
      f.t_recv_ns = rt::now_ns();
      f.seq = r.image.seq;
      f.exposure_us = r.image.exposure_us;
      f.rgb = &rgb_buf;
      have_rgb = true;
    } else if (r.type == RecordType::kRight && have_rgb) {
      // A stereo log: the right image of the pair; the frame goes with the next record.
      if (copy(r.image, right_buf)) f.right = &right_buf;
    } else if (have_rgb) {
      if (copy(r.image, depth_buf)) f.depth = &depth_buf;
      flush();
    } else {
      ++unpaired;
    }
  }
  flush();
}

bool split_side_by_side(const ImageBuffer& in, ImageBuffer& left, ImageBuffer& right) {
  const int bpp = bytes_per_pixel(in.format);
  if (bpp <= 0 || in.width <= 0 || in.width % 2 != 0 || in.height <= 0) return false;
  if (in.format == PixelFormat::kYuyv && in.width % 4 != 0) return false;  // a macropixel holds two pixels
  const size_t row = static_cast<size_t>(in.width) * static_cast<size_t>(bpp);
  const size_t half = row / 2;
  const size_t bytes = half * static_cast<size_t>(in.height);
  if (in.pixels.size() < row * static_cast<size_t>(in.height) || left.pixels.capacity() < bytes ||
      right.pixels.capacity() < bytes)
    return false;
  for (ImageBuffer* o : {&left, &right}) {
    o->t_ns = in.t_ns;
    o->t_recv_ns = in.t_recv_ns;
    o->seq = in.seq;
    o->width = in.width / 2;
    o->height = in.height;
    o->format = in.format;
    o->pixels.resize(bytes);
  }
  for (int y = 0; y < in.height; ++y) {
    const uint8_t* src = in.pixels.data() + static_cast<size_t>(y) * row;
    std::memcpy(left.pixels.data() + static_cast<size_t>(y) * half, src, half);
    std::memcpy(right.pixels.data() + static_cast<size_t>(y) * half, src + half, half);
  }
  return true;
}

std::string stereo_capability(const CameraSettings& c) {
  switch (c.type) {
    case CameraType::kLog:
      return "";  // a stereo log's right records
    case CameraType::kV4l2:
      if (!c.v4l2_right_device.empty() || c.v4l2_stereo_layout == "side_by_side") return "";
      return "drivers.camera.v4l2: a stereo rig needs right_device or stereo_layout: side_by_side";
    case CameraType::kD4xx:
      if (c.d4xx.image == "infrared1" && c.d4xx.infrared == "y8i") return "";
      return "drivers.camera.d4xx: a stereo rig needs image: infrared1 and infrared: y8i (Infrared 1 + 2)";
    case CameraType::kOpenNi2:
      return "drivers.camera: OpenNI2 cameras deliver no right image";
    case CameraType::kNone:
      return "drivers.camera: none";
  }
  return "drivers.camera: unknown type";
}

void LiveSensors::start(ImuSink& imu, FrameSink& frames) {
  Impl& m = *impl_;
  m.stop.store(false);
  m.thread_reports.clear();
  rt::ThreadSetupReport r;
  if (m.log) {
    const rt::ThreadSpec& spec = m.cfg.threads[PipelineThread::kCamera];
    m.cam_thread = rt::start_thread(
        spec, [&m, &imu, &frames] { m.log_loop(imu, frames); }, &r);
    m.thread_reports.emplace_back(spec, r);
    return;
  }
  if (m.bmx || m.bridge || m.mav || m.iio_imu) {
    const rt::ThreadSpec& spec = m.cfg.threads[PipelineThread::kImu];
    m.imu_thread = rt::start_thread(
        spec, [&m, &imu] { m.imu_loop(imu); }, &r);
    m.thread_reports.emplace_back(spec, r);
  }
  if (m.cfg.drivers.camera.type != CameraType::kNone) {
    const rt::ThreadSpec& spec = m.cfg.threads[PipelineThread::kCamera];
    m.cam_thread = rt::start_thread(
        spec, [&m, &frames] { m.cam_loop(frames); }, &r);
    m.thread_reports.emplace_back(spec, r);
  }
}

std::vector<std::pair<rt::ThreadSpec, rt::ThreadSetupReport>> LiveSensors::thread_reports() const {
  return impl_->thread_reports;
}

void LiveSensors::stop() {
  Impl& m = *impl_;
  m.stop.store(true);
  if (m.imu_thread.joinable()) m.imu_thread.join();
  if (m.cam_thread.joinable()) m.cam_thread.join();
}

std::string LiveSensors::description() const {
  const DriverSettings& d = impl_->cfg.drivers;
  std::string s = "camera: ";
  if (d.camera.type == CameraType::kLog) return "camera and IMU: log " + d.log_path;
  s += d.camera.type == CameraType::kOpenNi2 ? "OpenNI2"
       : d.camera.type == CameraType::kV4l2  ? "V4L2"
       : d.camera.type == CameraType::kD4xx  ? "RealSense D4xx (" + impl_->d4xx_nodes + ")"
                                             : "none";
  s += ", IMU: ";
  s += d.imu.type == ImuType::kBmx055I2c   ? "BMX055 over I2C (" + d.imu.i2c_bus_device + ")"
       : d.imu.type == ImuType::kBmx055Usb ? std::string("BMX055 via USB bridge")
       : d.imu.type == ImuType::kMavlink
           ? "flight controller over MAVLink (" + std::string(to_string(d.imu.mavlink.message)) + ", " +
                 (d.imu.mavlink.udp.empty() ? d.imu.mavlink.serial_device : d.imu.mavlink.udp) + ")"
       : d.imu.type == ImuType::kIio && impl_->iio_imu ? "Linux IIO (" + impl_->iio_imu->description() + ")"
                                                       : std::string("none");
  return s;
}

std::string LiveSensors::report() const {
  const Impl& m = *impl_;
  char b[512];
  std::string s;
  std::snprintf(b, sizeof b, "camera: %llu frames, %llu timeouts, %llu errors, %llu depth unpaired\n",
                (unsigned long long)m.frames, (unsigned long long)m.frame_timeouts,
                (unsigned long long)m.frame_errors, (unsigned long long)m.unpaired);
  s += b;
  if (m.d4xx_cam) s += m.d4xx_cam->report() + "\n";
  if (m.log) {
    std::snprintf(b, sizeof b, "log sensors: %llu IMU samples played\n", (unsigned long long)m.log_imu);
    s += b;
  }
  if (m.bmx) {
    const auto& c = m.bmx->counters();
    std::snprintf(
        b, sizeof b,
        "bmx055: state %s, %llu samples, %llu resets, %llu i2c errors, %llu overruns, %llu timeouts, "
        "%llu sink drops, gyro ODR %.3f Hz\n",
        bmx055::to_string(m.bmx->state()), (unsigned long long)c.samples, (unsigned long long)c.resets,
        (unsigned long long)c.i2c_errors, (unsigned long long)c.fifo_overruns, (unsigned long long)c.timeouts,
        (unsigned long long)c.sink_drops, m.bmx->gyro_odr_estimate_hz());
    s += b;
  }
  if (m.bridge) {
    const auto& c = m.bridge->counters();
    std::snprintf(
        b, sizeof b,
        "usb bridge: state %s, %llu samples, %llu packets lost, %llu crc errors, %llu samples lost, "
        "clock skew %.1f ppm, %llu strobes\n",
        to_string(m.bridge->state()), (unsigned long long)c.samples, (unsigned long long)c.packets_lost,
        (unsigned long long)c.crc_errors, (unsigned long long)c.samples_lost,
        m.bridge->clock_sync().skew() * 1e6, (unsigned long long)c.strobes);
    s += b;
  }
  if (m.mav) s += m.mav->report();
  if (m.iio_imu) s += m.iio_imu->report() + "\n";
  if (m.cfg.drivers.strobe.enabled) {
    std::snprintf(b, sizeof b,
                  "strobes: %llu matched, %llu frames unmatched, residual camera offset %.3f ms\n",
                  (unsigned long long)m.matcher.matched(), (unsigned long long)m.matcher.unmatched_frames(),
                  m.matcher.residual_offset_ns() * 1e-6);
    s += b;
  }
  return s;
}

}  // namespace kestrel::drivers

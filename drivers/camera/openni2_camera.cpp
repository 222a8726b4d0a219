#include "kestrel/drivers/openni2_camera.hpp"

#include <cmath>
#include <cstring>

#include "kestrel/rt/clock.hpp"

#if KESTREL_WITH_OPENNI2
#include <OpenNI.h>
#endif

namespace kestrel::drivers::openni2 {

namespace {
ClockSyncOptions device_clock_options() {
  ClockSyncOptions o;
  o.bucket_ns = 500'000'000;  // ~15 frames per bucket
  o.max_buckets = 40;         // 20 s window
  o.max_abs_skew = 0.002;
  return o;
}
}  // namespace

#if KESTREL_WITH_OPENNI2

bool openni2_built() { return true; }

namespace {
// The SDK's messages come with tabs and newlines: one line for ours.
std::string sdk_error() {
  std::string s = openni::OpenNI::getExtendedError();
  for (char& c : s)
    if (c == '\n' || c == '\t' || c == '\r') c = ' ';
  const size_t a = s.find_first_not_of(' '), b = s.find_last_not_of(' ');
  return a == std::string::npos ? "" : s.substr(a, b - a + 1);
}
// OpenNI::initialize is process-wide and reference counted by the SDK.
std::string init_openni() {
  if (openni::OpenNI::initialize() != openni::STATUS_OK) return "OpenNI2 initialise failed: " + sdk_error();
  return "";
}
}  // namespace

std::vector<std::string> list_devices(std::string* error) {
  std::vector<std::string> out;
  const std::string e = init_openni();
  if (!e.empty()) {
    if (error) *error = e;
    return out;
  }
  openni::Array<openni::DeviceInfo> list;
  openni::OpenNI::enumerateDevices(&list);
  for (int i = 0; i < list.getSize(); ++i)
    out.push_back(std::string(list[i].getVendor()) + " " + list[i].getName() + " (" + list[i].getUri() + ")");
  return out;
}

struct Camera::Impl {
  openni::Device device;
  openni::VideoStream color, depth;
  openni::VideoFrameRef cf, df;
  bool open = false;
};

Camera::Camera() : impl_(std::make_unique<Impl>()), sync_(device_clock_options()) {}
Camera::~Camera() { close(); }
bool Camera::is_open() const { return impl_->open; }

std::string Camera::open(const Options& o) {
  close();
  opt_ = o;
  std::string e = init_openni();
  if (!e.empty()) return e;
  Impl& m = *impl_;
  const char* uri = o.uri.empty() ? openni::ANY_DEVICE : o.uri.c_str();
  if (m.device.open(uri) != openni::STATUS_OK)
    return std::string("OpenNI2: no device") + (o.uri.empty() ? "" : " at " + o.uri) + ": " + sdk_error();
  auto fail = [&](const std::string& what) {
    close();
    return "OpenNI2: " + what;
  };
  if (m.color.create(m.device, openni::SENSOR_COLOR) != openni::STATUS_OK) return fail("no colour stream");
  if (m.depth.create(m.device, openni::SENSOR_DEPTH) != openni::STATUS_OK) return fail("no depth stream");
  openni::VideoMode cm = m.color.getVideoMode();
  cm.setResolution(o.width, o.height);
  cm.setFps(o.fps);
  cm.setPixelFormat(openni::PIXEL_FORMAT_RGB888);
  if (m.color.setVideoMode(cm) != openni::STATUS_OK) {
    return fail("colour mode " + std::to_string(o.width) + "x" + std::to_string(o.height) + "@" +
                std::to_string(o.fps) + " RGB888 not supported");
  }
  openni::VideoMode dm = m.depth.getVideoMode();
  dm.setResolution(o.width, o.height);
  dm.setFps(o.fps);
  dm.setPixelFormat(openni::PIXEL_FORMAT_DEPTH_1_MM);
  if (m.depth.setVideoMode(dm) != openni::STATUS_OK)
    return fail("depth mode DEPTH_1_MM at the colour size not supported");
  (void)m.color.setMirroringEnabled(o.mirror);
  (void)m.depth.setMirroringEnabled(o.mirror);
  if (o.registration) {
    if (!m.device.isImageRegistrationModeSupported(openni::IMAGE_REGISTRATION_DEPTH_TO_COLOR) ||
        m.device.setImageRegistrationMode(openni::IMAGE_REGISTRATION_DEPTH_TO_COLOR) != openni::STATUS_OK)
      return fail("depth-to-colour registration not supported by this device");
  }
  if (o.frame_sync && m.device.setDepthColorSyncEnabled(true) != openni::STATUS_OK)
    return fail("depth/colour frame sync could not be enabled");
  if (m.depth.start() != openni::STATUS_OK || m.color.start() != openni::STATUS_OK)
    return fail("streams did not start");
  m.open = true;
  sync_.reset();
  have_index_ = false;
  return "";
}

void Camera::close() {
  Impl& m = *impl_;
  m.color.stop();
  m.depth.stop();
  m.color.destroy();
  m.depth.destroy();
  if (m.device.isValid()) m.device.close();
  m.open = false;
}

GrabResult Camera::grab(int timeout_ms, ImageBuffer& rgb, ImageBuffer& depth, FrameMeta& meta) {
  Impl& m = *impl_;
  if (!m.open) return GrabResult::kError;
  openni::VideoStream* streams[1] = {&m.color};
  int ready = -1;
  if (openni::OpenNI::waitForAnyStream(streams, 1, &ready, timeout_ms) != openni::STATUS_OK) {
    ++counters_.timeouts;
    return GrabResult::kTimeout;
  }
  if (m.color.readFrame(&m.cf) != openni::STATUS_OK || m.depth.readFrame(&m.df) != openni::STATUS_OK) {
    ++counters_.errors;
    return GrabResult::kError;
  }
  const int64_t t_recv = rt::now_ns();
  const auto tc = static_cast<int64_t>(m.cf.getTimestamp());
  const auto td = static_cast<int64_t>(m.df.getTimestamp());
  if (!stamps_pair(tc, td, opt_.fps)) ++counters_.unpaired;
  if (!sync_.add(tc * 1000, t_recv)) ++counters_.clock_jumps;
  const auto index = static_cast<uint32_t>(m.cf.getFrameIndex());
  meta.dropped_before = 0;
  if (have_index_ && index != next_index_) {
    const auto gap = static_cast<int32_t>(index - next_index_);
    if (gap > 0) {
      meta.dropped_before = static_cast<uint32_t>(gap);
      counters_.dropped += static_cast<uint64_t>(gap);
    }
  }
  have_index_ = true;
  next_index_ = index + 1;
  meta.t_device_us = tc;
  meta.t_ns = sync_.to_host_ns(tc * 1000) + opt_.exposure_mid_offset_ns;
  meta.t_recv_ns = t_recv;
  meta.seq = index;
  openni::CameraSettings* cs = m.color.getCameraSettings();
  meta.exposure_us =
      cs != nullptr ? cs->getExposure() : 0;  // SDK reports milliseconds or ticks; 0 if unknown

  const int w = m.cf.getWidth(), h = m.cf.getHeight();
  const size_t rgb_bytes = static_cast<size_t>(w) * h * 3, depth_bytes = static_cast<size_t>(w) * h * 2;
  if (rgb_bytes > rgb.pixels.capacity() || depth_bytes > depth.pixels.capacity() || m.df.getWidth() != w ||
      m.df.getHeight() != h) {
    ++counters_.errors;
    return GrabResult::kError;
  }
  rgb.pixels.resize(rgb_bytes);
  depth.pixels.resize(depth_bytes);
  for (int y = 0; y < h; ++y) {
    std::memcpy(
        rgb.pixels.data() + static_cast<size_t>(y) * w * 3,
        static_cast<const uint8_t*>(m.cf.getData()) + static_cast<size_t>(y) * m.cf.getStrideInBytes(),
        static_cast<size_t>(w) * 3);
  }
  const double k = 0.001 / opt_.rig_depth_scale_m;
  for (int y = 0; y < h; ++y) {
    const auto* s = reinterpret_cast<const uint16_t*>(static_cast<const uint8_t*>(m.df.getData()) +
                                                      static_cast<size_t>(y) * m.df.getStrideInBytes());
    auto* d = reinterpret_cast<uint16_t*>(depth.pixels.data()) + static_cast<size_t>(y) * w;
    if (k == 1.0) {
      std::memcpy(d, s, static_cast<size_t>(w) * 2);
    } else {
      for (int x = 0; x < w; ++x) {
        const double v = std::round(s[x] * k);
        d[x] = v > 65535.0 ? 0 : static_cast<uint16_t>(v);
      }
    }
  }
  rgb.t_ns = depth.t_ns = meta.t_ns;
  rgb.width = depth.width = w;
  rgb.height = depth.height = h;
  rgb.format = PixelFormat::kRgb8;
  depth.format = PixelFormat::kDepthU16;
  ++counters_.frames;
  return GrabResult::kFrame;
}

#else

bool openni2_built() { return false; }
std::vector<std::string> list_devices(std::string* error) {
  if (error) *error = "OpenNI2 support not built (libopenni2 not found at build time)";
  return {};
}
struct Camera::Impl {};
Camera::Camera() : impl_(std::make_unique<Impl>()), sync_(device_clock_options()) {}
Camera::~Camera() = default;
bool Camera::is_open() const { return false; }
std::string Camera::open(const Options&) {
  return "OpenNI2 support not built (libopenni2 not found at build time)";
}
void Camera::close() {}
GrabResult Camera::grab(int, ImageBuffer&, ImageBuffer&, FrameMeta&) { return GrabResult::kError; }

#endif

}  // namespace kestrel::drivers::openni2

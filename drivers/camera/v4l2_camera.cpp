#include "kestrel/drivers/v4l2_camera.hpp"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "kestrel/rt/clock.hpp"

#if KESTREL_WITH_V4L2
#include <fcntl.h>
#include <linux/videodev2.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>
#endif

namespace kestrel::drivers::v4l2 {

std::string fourcc_name(uint32_t f) {
  std::string s(4, ' ');
  for (int i = 0; i < 4; ++i) {
    const char c = static_cast<char>((f >> (8 * i)) & 0xFF);
    s[static_cast<size_t>(i)] = (c >= 32 && c < 127) ? c : '?';
  }
  return s;
}

uint32_t fourcc_from_name(const std::string& n) {
  if (n == "yuyv") return kYuyv;
  if (n == "mjpeg") return kMjpeg;
  if (n == "grey") return kGrey;
  if (n == "z16") return kZ16;
  return 0;
}

FormatChoice choose_format(const std::vector<FormatOption>& available, const FormatRequest& req) {
  FormatChoice c;
  for (uint32_t want : req.preferred) {
    const FormatOption* best = nullptr;
    for (const FormatOption& o : available) {
      if (o.fourcc != want || o.width != req.width || o.height != req.height) continue;
      if (best == nullptr) {
        best = &o;
        continue;
      }
      const bool o_ok = o.fps + 1e-6 >= req.fps;
      const bool b_ok = best->fps + 1e-6 >= req.fps;
      // Prefer the slowest rate that still meets the request; else the fastest.
      if ((o_ok && (!b_ok || o.fps < best->fps)) || (!o_ok && !b_ok && o.fps > best->fps)) best = &o;
    }
    if (best != nullptr) {
      c.ok = true;
      c.option = *best;
      return c;
    }
  }
  c.why =
      "no offered format matches " + std::to_string(req.width) + "x" + std::to_string(req.height) + " in {";
  for (size_t i = 0; i < req.preferred.size(); ++i) c.why += (i ? ", " : "") + fourcc_name(req.preferred[i]);
  c.why += "}; the device offers:";
  size_t shown = 0;
  for (const FormatOption& o : available) {
    if (++shown > 12) {
      c.why += " ...";
      break;
    }
    char b[64];
    std::snprintf(b, sizeof b, " %s %dx%d@%.0f", fourcc_name(o.fourcc).c_str(), o.width, o.height, o.fps);
    c.why += b;
  }
  if (available.empty()) c.why += " nothing";
  return c;
}

BufferTime buffer_time(int64_t tv_sec, int64_t tv_usec, uint32_t flags, int64_t t_dequeue_ns) {
  BufferTime t;
  t.monotonic = (flags & kBufFlagTimestampMask) == kBufFlagTimestampMonotonic;
  t.start_of_exposure = (flags & kBufFlagTstampSrcMask) == kBufFlagTstampSrcSoe;
  t.t_ns = t.monotonic ? tv_sec * 1'000'000'000 + tv_usec * 1'000 : t_dequeue_ns;
  if (!t.monotonic) t.start_of_exposure = false;  // a dequeue time is an end-of-frame time at best
  return t;
}

int64_t mid_exposure_ns(const BufferTime& t, int32_t exposure_us, int64_t readout_ns) {
  const int64_t half = static_cast<int64_t>(exposure_us) * 500;
  return t.start_of_exposure ? t.t_ns + half : t.t_ns - readout_ns - half;
}

uint32_t SequenceTracker::update(uint32_t seq) {
  uint32_t gap = 0;
  if (have_) {
    const auto d = static_cast<int32_t>(seq - expected_);
    if (d > 0) {
      gap = static_cast<uint32_t>(d);
      dropped_ += gap;
    } else if (d < 0) {
      ++restarts_;
    }
  }
  have_ = true;
  expected_ = seq + 1;
  return gap;
}

void BufferBook::reset(int n) {
  count_ = std::clamp(n, 0, kMaxBuffers);
  queued_ = 0;
  queued_flags_.fill(false);
}

bool BufferBook::on_queued(int i) {
  if (i < 0 || i >= count_ || queued_flags_[static_cast<size_t>(i)]) {
    ++errors_;
    return false;
  }
  queued_flags_[static_cast<size_t>(i)] = true;
  ++queued_;
  return true;
}

bool BufferBook::on_dequeued(int i) {
  if (i < 0 || i >= count_ || !queued_flags_[static_cast<size_t>(i)]) {
    ++errors_;
    return false;
  }
  queued_flags_[static_cast<size_t>(i)] = false;
  --queued_;
  return true;
}

namespace {
inline uint8_t clamp8(int v) { return static_cast<uint8_t>(v < 0 ? 0 : (v > 255 ? 255 : v)); }
}  // namespace

void yuyv_to_rgb(const uint8_t* src, int width, int height, int src_stride, uint8_t* dst, int dst_stride) {
  for (int y = 0; y < height; ++y) {
    const uint8_t* s = src + static_cast<size_t>(y) * static_cast<size_t>(src_stride);
    uint8_t* d = dst + static_cast<size_t>(y) * static_cast<size_t>(dst_stride);
    for (int x = 0; x + 1 < width; x += 2, s += 4, d += 6) {
      const int u = s[1] - 128, v = s[3] - 128;
      const int ruv = 409 * v, guv = -100 * u - 208 * v, buv = 516 * u;
      for (int k = 0; k < 2; ++k) {
        const int c = 298 * (s[2 * k] - 16) + 128;
        d[3 * k + 0] = clamp8((c + ruv) >> 8);
        d[3 * k + 1] = clamp8((c + guv) >> 8);
        d[3 * k + 2] = clamp8((c + buv) >> 8);
      }
    }
  }
}

void z16_to_depth(const uint8_t* src, int width, int height, int src_stride, double src_scale_m,
                  double dst_scale_m, uint16_t* dst) {
  const double k = src_scale_m / dst_scale_m;
  const bool same = std::abs(k - 1.0) < 1e-12;
  for (int y = 0; y < height; ++y) {
    const uint8_t* s = src + static_cast<size_t>(y) * static_cast<size_t>(src_stride);
    uint16_t* d = dst + static_cast<size_t>(y) * static_cast<size_t>(width);
    if (same) {
      std::memcpy(d, s, static_cast<size_t>(width) * 2);
      continue;
    }
    for (int x = 0; x < width; ++x) {
      const auto v = static_cast<uint16_t>(s[2 * x] | (s[2 * x + 1] << 8));
      const double r = std::round(v * k);
      d[x] = (v == 0 || r > 65535.0) ? 0 : static_cast<uint16_t>(r);
    }
  }
}

void copy_rows(const uint8_t* src, int row_bytes, int height, int src_stride, uint8_t* dst) {
  for (int y = 0; y < height; ++y) {
    std::memcpy(dst + static_cast<size_t>(y) * static_cast<size_t>(row_bytes),
                src + static_cast<size_t>(y) * static_cast<size_t>(src_stride),
                static_cast<size_t>(row_bytes));
  }
}

bool z16_to_registered_depth(const uint8_t* src, int width, int height, int src_stride, double src_scale_m,
                             double dst_scale_m, const DepthRegistration& reg, uint16_t* scratch,
                             uint16_t* dst, int dst_stride, RegistrationStats* stats) {
  if (width != reg.depth_width() || height != reg.depth_height()) return false;
  z16_to_depth(src, width, height, src_stride, src_scale_m, dst_scale_m, scratch);
  const ImageView v{width, height, width * 2, PixelFormat::kDepthU16,
                    reinterpret_cast<const uint8_t*>(scratch)};
  return reg.register_into(v, dst, dst_stride, stats);
}

PixelFormat Camera::output_format() const {
  switch (active_.fourcc) {
    case kZ16:
      return PixelFormat::kDepthU16;
    case kGrey:
      return PixelFormat::kGray8;
    default:
      return PixelFormat::kRgb8;
  }
}

#if KESTREL_WITH_V4L2

bool v4l2_built() { return true; }

namespace {
int xioctl(int fd, unsigned long req, void* arg) {
  int r;
  do r = ioctl(fd, req, arg);
  while (r < 0 && errno == EINTR);
  return r;
}

std::vector<FormatOption> enumerate(int fd) {
  std::vector<FormatOption> out;
  v4l2_fmtdesc fd_desc{};
  std::memset(&fd_desc, 0, sizeof fd_desc);
  fd_desc.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  for (fd_desc.index = 0; xioctl(fd, VIDIOC_ENUM_FMT, &fd_desc) == 0; ++fd_desc.index) {
    v4l2_frmsizeenum fs{};
    std::memset(&fs, 0, sizeof fs);
    fs.pixel_format = fd_desc.pixelformat;
    for (fs.index = 0; xioctl(fd, VIDIOC_ENUM_FRAMESIZES, &fs) == 0; ++fs.index) {
      if (fs.type != V4L2_FRMSIZE_TYPE_DISCRETE) break;  // stepwise sizes: not offered by UVC cameras we use
      v4l2_frmivalenum fi{};
      std::memset(&fi, 0, sizeof fi);
      fi.pixel_format = fs.pixel_format;
      fi.width = fs.discrete.width;
      fi.height = fs.discrete.height;
      bool any = false;
      for (fi.index = 0; xioctl(fd, VIDIOC_ENUM_FRAMEINTERVALS, &fi) == 0; ++fi.index) {
        if (fi.type != V4L2_FRMIVAL_TYPE_DISCRETE || fi.discrete.numerator == 0) break;
        out.push_back(FormatOption{fs.pixel_format, static_cast<int>(fs.discrete.width),
                                   static_cast<int>(fs.discrete.height),
                                   static_cast<double>(fi.discrete.denominator) / fi.discrete.numerator});
        any = true;
      }
      if (!any) {
        out.push_back(FormatOption{fs.pixel_format, static_cast<int>(fs.discrete.width),
                                   static_cast<int>(fs.discrete.height), 0.0});
      }
    }
  }
  return out;
}
}  // namespace

std::vector<DeviceInfo> list_devices(std::string* error) {
  std::vector<DeviceInfo> out;
  int found_nodes = 0;
  for (int i = 0; i < 64; ++i) {
    const std::string path = "/dev/video" + std::to_string(i);
    const int fd = ::open(path.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0) continue;
    ++found_nodes;
    v4l2_capability cap{};
    std::memset(&cap, 0, sizeof cap);
    if (xioctl(fd, VIDIOC_QUERYCAP, &cap) == 0) {
      const uint32_t caps = (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
      if ((caps & V4L2_CAP_VIDEO_CAPTURE) && (caps & V4L2_CAP_STREAMING)) {
        DeviceInfo d;
        d.path = path;
        d.card = reinterpret_cast<const char*>(cap.card);
        d.driver = reinterpret_cast<const char*>(cap.driver);
        d.bus_info = reinterpret_cast<const char*>(cap.bus_info);
        for (const FormatOption& o : enumerate(fd)) {
          if (std::find(d.formats.begin(), d.formats.end(), o.fourcc) == d.formats.end())
            d.formats.push_back(o.fourcc);
        }
        out.push_back(d);
      }
    }
    ::close(fd);
  }
  if (found_nodes == 0 && error != nullptr) *error = "no /dev/video* nodes";
  return out;
}

Camera::~Camera() { close(); }

std::string Camera::open(const Options& o) {
  close();
  opt_ = o;
  const std::string& dev = o.device;
  fd_ = ::open(dev.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
  if (fd_ < 0) return dev + ": " + std::strerror(errno);
  auto fail = [&](const std::string& what) {
    std::string msg = dev + ": " + what;
    close();
    return msg;
  };
  v4l2_capability cap{};
  std::memset(&cap, 0, sizeof cap);
  if (xioctl(fd_, VIDIOC_QUERYCAP, &cap) < 0) return fail("not a V4L2 device");
  const uint32_t caps = (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
  if (!(caps & V4L2_CAP_VIDEO_CAPTURE) || !(caps & V4L2_CAP_STREAMING))
    return fail("not a streaming capture device (metadata node?)");
  offered_ = enumerate(fd_);
  const FormatChoice choice = choose_format(offered_, o.request);
  if (!choice.ok) return fail(choice.why);
  v4l2_format fmt{};
  std::memset(&fmt, 0, sizeof fmt);
  fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  fmt.fmt.pix.width = static_cast<uint32_t>(choice.option.width);
  fmt.fmt.pix.height = static_cast<uint32_t>(choice.option.height);
  fmt.fmt.pix.pixelformat = choice.option.fourcc;
  fmt.fmt.pix.field = V4L2_FIELD_NONE;
  if (xioctl(fd_, VIDIOC_S_FMT, &fmt) < 0) return fail(std::string("VIDIOC_S_FMT: ") + std::strerror(errno));
  if (fmt.fmt.pix.pixelformat != choice.option.fourcc ||
      static_cast<int>(fmt.fmt.pix.width) != choice.option.width ||
      static_cast<int>(fmt.fmt.pix.height) != choice.option.height)
    return fail("the driver changed the requested format (verify after set failed)");
  active_ = choice.option;
  stride_ = static_cast<int>(fmt.fmt.pix.bytesperline);
  registration_.reset();
  if (o.depth_camera.present && choice.option.fourcc == kZ16) {
    const CameraIntrinsics& d = o.depth_camera.intrinsics;
    if (d.width != choice.option.width || d.height != choice.option.height) {
      return fail("depth stream " + std::to_string(choice.option.width) + "x" +
                  std::to_string(choice.option.height) + " but the rig's depth_camera is " +
                  std::to_string(d.width) + "x" + std::to_string(d.height));
    }
    try {
      registration_ = std::make_unique<DepthRegistration>(o.depth_camera, o.colour, o.rig_depth_scale_m);
    } catch (const std::invalid_argument& e) {
      return fail(e.what());
    }
    depth_scratch_.assign(static_cast<size_t>(d.width) * static_cast<size_t>(d.height), 0);
  }
  if (choice.option.fps > 0) {
    v4l2_streamparm parm{};
    std::memset(&parm, 0, sizeof parm);
    parm.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    parm.parm.capture.timeperframe.numerator = 1000;
    parm.parm.capture.timeperframe.denominator = static_cast<uint32_t>(std::lround(choice.option.fps * 1000));
    (void)xioctl(fd_, VIDIOC_S_PARM, &parm);  // best effort: some drivers fix the rate
  }
  v4l2_requestbuffers req{};
  std::memset(&req, 0, sizeof req);
  req.count = static_cast<uint32_t>(std::clamp(o.buffers, 2, BufferBook::kMaxBuffers));
  req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  req.memory = V4L2_MEMORY_MMAP;
  if (xioctl(fd_, VIDIOC_REQBUFS, &req) < 0 || req.count < 2) return fail("VIDIOC_REQBUFS (mmap) failed");
  book_.reset(static_cast<int>(req.count));
  for (uint32_t i = 0; i < req.count; ++i) {
    v4l2_buffer b{};
    std::memset(&b, 0, sizeof b);
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    b.index = i;
    if (xioctl(fd_, VIDIOC_QUERYBUF, &b) < 0) return fail("VIDIOC_QUERYBUF failed");
    void* p = mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_, b.m.offset);
    if (p == MAP_FAILED) return fail(std::string("mmap: ") + std::strerror(errno));
    maps_.push_back(Mapped{p, b.length});
    if (xioctl(fd_, VIDIOC_QBUF, &b) < 0) return fail("VIDIOC_QBUF failed");
    book_.on_queued(static_cast<int>(i));
  }
  if (active_.fourcc == kMjpeg)
    decode_scratch_.reserve(static_cast<size_t>(active_.width) * active_.height * 3);
  v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (xioctl(fd_, VIDIOC_STREAMON, &type) < 0)
    return fail(std::string("VIDIOC_STREAMON: ") + std::strerror(errno));
  return "";
}

void Camera::close() {
  if (fd_ >= 0) {
    v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    (void)xioctl(fd_, VIDIOC_STREAMOFF, &type);
  }
  for (const Mapped& m : maps_) munmap(m.ptr, m.len);
  maps_.clear();
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
}

GrabResult Camera::grab(int timeout_ms, ImageBuffer& dst, FrameMeta& meta) {
  if (fd_ < 0) return GrabResult::kError;
  pollfd p{fd_, POLLIN, 0};
  const int rc = poll(&p, 1, timeout_ms);
  if (rc == 0) {
    ++counters_.timeouts;
    return GrabResult::kTimeout;
  }
  if (rc < 0) {
    if (errno == EINTR) return GrabResult::kTimeout;
    ++counters_.errors;
    return GrabResult::kError;
  }
  v4l2_buffer b{};
  std::memset(&b, 0, sizeof b);
  b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  b.memory = V4L2_MEMORY_MMAP;
  if (xioctl(fd_, VIDIOC_DQBUF, &b) < 0) {
    if (errno == EAGAIN) return GrabResult::kTimeout;
    ++counters_.errors;
    return GrabResult::kError;
  }
  const int64_t t_recv = rt::now_ns();
  if (!book_.on_dequeued(static_cast<int>(b.index))) ++counters_.errors;
  int32_t exposure_us = 0;
  if (exposure_ctrl_ok_) {
    v4l2_control c{V4L2_CID_EXPOSURE_ABSOLUTE, 0};
    if (xioctl(fd_, VIDIOC_G_CTRL, &c) == 0) {
      exposure_us = c.value * 100;  // units of 100 us
    } else {
      exposure_ctrl_ok_ = false;
    }
  }
  const BufferTime bt = buffer_time(b.timestamp.tv_sec, b.timestamp.tv_usec, b.flags, t_recv);
  if (!bt.monotonic) ++counters_.non_monotonic;
  meta.t_buffer_ns = bt.t_ns;
  meta.t_ns = mid_exposure_ns(bt, exposure_us, opt_.readout_ns);
  meta.t_recv_ns = t_recv;
  meta.seq = b.sequence;
  meta.dropped_before = seq_.update(b.sequence);
  counters_.dropped = seq_.dropped();
  meta.exposure_us = exposure_us;
  meta.start_of_exposure = bt.start_of_exposure;
  meta.monotonic = bt.monotonic;

  const auto* src = static_cast<const uint8_t*>(maps_[b.index].ptr);
  const int w = active_.width, h = active_.height;
  // A registered depth frame has the colour camera's size.
  const int ow = registration_ ? registration_->colour_width() : w;
  const int oh = registration_ ? registration_->colour_height() : h;
  dst.t_ns = meta.t_ns;
  dst.width = ow;
  dst.height = oh;
  dst.format = output_format();
  bool ok = (b.flags & V4L2_BUF_FLAG_ERROR) == 0;
  const size_t need = static_cast<size_t>(ow) * oh * static_cast<size_t>(bytes_per_pixel(dst.format));
  if (ok && need <= dst.pixels.capacity()) {
    dst.pixels.resize(need);  // within the start-up reservation: no allocation
    switch (active_.fourcc) {
      case kYuyv:
        yuyv_to_rgb(src, w, h, stride_, dst.pixels.data(), w * 3);
        break;
      case kGrey:
        copy_rows(src, w, h, stride_, dst.pixels.data());
        break;
      case kZ16:
        if (registration_) {
          ok = z16_to_registered_depth(src, w, h, stride_, opt_.depth_scale_m, opt_.rig_depth_scale_m,
                                       *registration_, depth_scratch_.data(),
                                       reinterpret_cast<uint16_t*>(dst.pixels.data()), ow * 2);
        } else {
          z16_to_depth(src, w, h, stride_, opt_.depth_scale_m, opt_.rig_depth_scale_m,
                       reinterpret_cast<uint16_t*>(dst.pixels.data()));
        }
        break;
      case kMjpeg: {
        // Decoded into the destination buffer; libjpeg's own scratch is the
        // one allocation on this path (YUYV avoids it; docs/drivers/README.md).
        cv::Mat out(h, w, CV_8UC3, dst.pixels.data());
        cv::Mat in(1, static_cast<int>(b.bytesused), CV_8UC1, const_cast<uint8_t*>(src));
        cv::Mat bgr = cv::imdecode(in, cv::IMREAD_COLOR);
        if (bgr.empty() || bgr.cols != w || bgr.rows != h) {
          ++counters_.decode_errors;
          ok = false;
        } else {
          cv::cvtColor(bgr, out, cv::COLOR_BGR2RGB);
        }
        break;
      }
      default:
        ok = false;
    }
  } else {
    ok = false;
  }
  if (xioctl(fd_, VIDIOC_QBUF, &b) < 0 || !book_.on_queued(static_cast<int>(b.index))) ++counters_.errors;
  if (!ok) {
    ++counters_.errors;
    return GrabResult::kError;
  }
  ++counters_.frames;
  return GrabResult::kFrame;
}

#else

bool v4l2_built() { return false; }
std::vector<DeviceInfo> list_devices(std::string* error) {
  if (error) *error = "V4L2 support not built (no <linux/videodev2.h>)";
  return {};
}
Camera::~Camera() = default;
std::string Camera::open(const Options& o) {
  return o.device + ": V4L2 support not built (no <linux/videodev2.h> at build time)";
}
void Camera::close() {}
GrabResult Camera::grab(int, ImageBuffer&, FrameMeta&) { return GrabResult::kError; }

#endif

}  // namespace kestrel::drivers::v4l2

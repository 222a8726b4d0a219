#include "kestrel/drivers/d4xx_camera.hpp"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <stdexcept>

#include "kestrel/rt/clock.hpp"

#if KESTREL_WITH_V4L2
#include <fcntl.h>
#include <linux/videodev2.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>
#endif

namespace kestrel::drivers::d4xx {

namespace {
constexpr uint32_t kBufFlagError = 0x00000040;  // V4L2_BUF_FLAG_ERROR
}

const char* stream_name(StreamKind k) {
  switch (k) {
    case StreamKind::kColor:
      return "color";
    case StreamKind::kDepth:
      return "depth";
    case StreamKind::kInfrared:
      return "infrared";
  }
  return "?";
}

// ---- node grouping (pure) -----------------------------------------------------------------
std::vector<NodeSet> group_d4xx_nodes(const std::vector<ProbedNode>& nodes, const std::string& card_match) {
  std::vector<ProbedNode> sorted;
  for (const ProbedNode& n : nodes)
    if (n.card.find(card_match) != std::string::npos) sorted.push_back(n);
  std::sort(sorted.begin(), sorted.end(),
            [](const ProbedNode& a, const ProbedNode& b) { return a.minor < b.minor; });
  std::vector<NodeSet> sets;
  auto set_of = [&](const ProbedNode& n) -> NodeSet& {
    for (NodeSet& s : sets)
      if (s.bus_info == n.bus_info) return s;
    sets.push_back(NodeSet{});
    sets.back().bus_info = n.bus_info;
    sets.back().card = n.card;
    return sets.back();
  };
  auto has = [](const ProbedNode& n, uint32_t f) {
    return std::find(n.formats.begin(), n.formats.end(), f) != n.formats.end();
  };
  for (size_t i = 0; i < sorted.size(); ++i) {
    const ProbedNode& n = sorted[i];
    if (n.metadata) continue;
    NodeSet& s = set_of(n);
    // Its metadata node: the next minor on the same bus.
    std::string meta;
    if (i + 1 < sorted.size() && sorted[i + 1].metadata && sorted[i + 1].minor == n.minor + 1 &&
        sorted[i + 1].bus_info == n.bus_info)
      meta = sorted[i + 1].path;
    if (has(n, v4l2::kZ16)) {
      if (s.depth.empty()) s.depth = n.path, s.depth_meta = meta;
    } else if (has(n, kY8i) || (has(n, v4l2::kGrey) && !has(n, v4l2::kYuyv))) {
      if (s.infrared.empty()) s.infrared = n.path, s.infrared_meta = meta;
    } else if (has(n, v4l2::kYuyv) || has(n, kRgb24)) {
      if (s.color.empty()) s.color = n.path, s.color_meta = meta;
    }
  }
  return sets;
}

// ---- device clock ----------------------------------------------------------------------------
int64_t DeviceClock::unwrap_ns(uint32_t device_us) const {
  if (!have_) return static_cast<int64_t>(device_us) * 1000;
  const auto delta = static_cast<int32_t>(device_us - last_us_);
  return (last_unwrapped_us_ + delta) * 1000;
}

void DeviceClock::observe(uint32_t pts_us, int64_t host_ns) {
  const int64_t d_ns = unwrap_ns(pts_us);
  have_ = true;
  last_us_ = pts_us;
  last_unwrapped_us_ = d_ns / 1000;
  (void)sync_.add(d_ns, host_ns);  // a jump resets the fit; counted in sync_.jumps()
  ++observations_;
  if (shared_ != nullptr) shared_->publish(ClockLine::of(sync_, d_ns, observations_));
}

// ---- one stream ------------------------------------------------------------------------------
Stream::Stream(StreamKind kind, std::unique_ptr<Node> video, std::unique_ptr<Node> meta)
    : kind_(kind), video_(std::move(video)), meta_(std::move(meta)) {}

void Stream::drain_metadata() {
  if (!has_metadata()) return;
  NodeBuffer b;
  while (meta_->dequeue(b)) {
    Pending& p = pending_[b.sequence % kPendingMeta];
    if (p.used && p.seq != b.sequence) ++c_.metadata_orphans;
    p.used = true;
    p.seq = b.sequence;
    p.status = parse_metadata_buffer(b.data, b.bytes_used, p.md);
    if (!meta_->requeue(b)) ++c_.errors;
  }
}

bool Stream::pending_has(uint32_t seq) const {
  const Pending& p = pending_[seq % kPendingMeta];
  return p.used && p.seq == seq;
}

void Stream::stamp(const NodeBuffer& b, DeviceClock& clock, bool feeds_clock, int64_t readout_ns,
                   int64_t t_recv_ns, StreamFrame& out) {
  out = StreamFrame{};
  const v4l2::BufferTime bt = v4l2::buffer_time(b.tv_sec, b.tv_usec, b.flags, t_recv_ns);
  out.t_buffer_ns = bt.t_ns;
  out.t_recv_ns = t_recv_ns;
  out.seq = b.sequence;
  (void)seq_.update(b.sequence);
  c_.dropped = seq_.dropped();
  c_.restarts = seq_.restarts();
  // Metadata of frames before this one will never be claimed.
  for (Pending& p : pending_) {
    if (p.used && static_cast<int32_t>(p.seq - b.sequence) < 0) {
      p.used = false;
      ++c_.metadata_orphans;
    }
  }
  Pending* mine = nullptr;
  if (pending_has(b.sequence)) mine = &pending_[b.sequence % kPendingMeta];
  if (mine == nullptr) {
    out.source = StampSource::kKernelNoMetadata;
    ++c_.metadata_missing;
  } else {
    mine->used = false;
    out.metadata_status = mine->status;
    const FrameMetadata& md = mine->md;
    if (mine->status == ParseStatus::kOk) {
      if (feeds_clock && md.has_pts) clock.observe(md.pts_us, md.host_ns);
      out.exposure_us = static_cast<int32_t>(std::min<uint32_t>(md.exposure_us(), 10'000'000));
      if (md.timing.present && (md.timing.flags & kTimingFrameCounterValid)) {
        out.frame_counter = md.timing.frame_counter;
        if (have_counter_ && md.timing.frame_counter != last_counter_ + 1) ++c_.frame_counter_gaps;
        have_counter_ = true;
        last_counter_ = md.timing.frame_counter;
      }
      if (md.has_sensor_timestamp() && clock.valid()) {
        out.t_device_ns = clock.unwrap_ns(md.timing.sensor_timestamp_us);
        out.t_ns = clock.to_host_ns(md.timing.sensor_timestamp_us);
        out.source = StampSource::kHardware;
        ++c_.hardware_stamps;
        return;
      }
      out.source = StampSource::kKernelNoTimestamp;
      ++c_.metadata_no_timestamp;
    } else if (mine->status == ParseStatus::kNoD4xxBlocks) {
      out.source = StampSource::kKernelNoTimestamp;
      ++c_.metadata_no_timestamp;
    } else {
      out.source = StampSource::kKernelCorrupt;
      ++c_.metadata_corrupt;
    }
  }
  out.t_ns = v4l2::mid_exposure_ns(bt, out.exposure_us, readout_ns);
}

Stream::Result Stream::next(int timeout_ms, int metadata_wait_ms, DeviceClock& clock, bool feeds_clock,
                            int64_t readout_ns, NodeBuffer& b, StreamFrame& out) {
  if (!video_->dequeue(b)) {
    const NodeWait w = video_->wait(timeout_ms);
    if (w == NodeWait::kError) {
      ++c_.errors;
      return Result::kError;
    }
    if (w == NodeWait::kTimeout || !video_->dequeue(b)) {
      ++c_.timeouts;
      return Result::kTimeout;
    }
  }
  const int64_t t_recv = rt::now_ns();
  if (has_metadata()) {
    drain_metadata();
    // uvcvideo completes the metadata buffer just before the frame's; a
    // short wait covers the two descriptors waking in the other order.
    if (!pending_has(b.sequence) && metadata_wait_ms > 0 && meta_->wait(metadata_wait_ms) == NodeWait::kReady)
      drain_metadata();
  }
  stamp(b, clock, feeds_clock, readout_ns, t_recv, out);
  if (b.flags & kBufFlagError) {
    ++c_.errors;
    release(b);
    return Result::kError;
  }
  ++c_.frames;
  return Result::kFrame;
}

void Stream::release(const NodeBuffer& b) {
  if (!video_->requeue(b)) ++c_.errors;
}

// ---- camera --------------------------------------------------------------------------------------
Camera::Camera(NodeFactory factory) : factory_(std::move(factory)) {}
Camera::~Camera() { close(); }

void Camera::close() {
  image_ = nullptr;
  color_.reset();
  depth_.reset();
  infrared_.reset();
  registration_.reset();
}

std::string Camera::open(const Options& o) {
  close();
  opt_ = o;
  depth_held_ = ir_held_ = false;
  sets_ = unpaired_ = depth_skipped_ = 0;
  clock_ = DeviceClock(o.clock);
  clock_.publish_to(o.shared_clock);
  std::string errors;
  auto add_error = [&](const std::string& e) { errors += (errors.empty() ? "" : "\n") + e; };
  auto open_stream = [&](StreamKind kind, const StreamOptions& so) -> std::unique_ptr<Stream> {
    if (!so.enabled) return nullptr;
    const std::string what = std::string("D4xx ") + stream_name(kind);
    if (so.video_device.empty()) {
      add_error(what + ": no video device (configure it, or let auto-find name it)");
      return nullptr;
    }
    std::unique_ptr<Node> video = factory_();
    NodeRequest r;
    r.format = so.request;
    r.buffers = o.buffers;
    std::string e = video->open(so.video_device, r);
    if (!e.empty()) {
      add_error(what + ": " + e);
      return nullptr;
    }
    std::unique_ptr<Node> meta;
    if (!so.meta_device.empty()) {
      meta = factory_();
      NodeRequest mr;
      mr.metadata = true;
      mr.buffers = std::max(o.buffers, 4);
      e = meta->open(so.meta_device, mr);
      if (!e.empty()) {
        add_error(what + " metadata: " + e);
        return nullptr;
      }
    }
    return std::make_unique<Stream>(kind, std::move(video), std::move(meta));
  };
  color_ = open_stream(StreamKind::kColor, o.color);
  depth_ = open_stream(StreamKind::kDepth, o.depth);
  infrared_ = open_stream(StreamKind::kInfrared, o.infrared);
  if (!errors.empty()) {
    close();
    return errors;
  }
  image_ = o.infrared_is_image ? infrared_.get() : color_.get();
  if (image_ == nullptr) {
    close();
    return o.infrared_is_image ? "D4xx: infrared_is_image needs the infrared stream"
                               : "D4xx: the colour stream is off";
  }
  const NodeFormat& f = image_->video().format();
  if (f.fps > 0) period_ns_ = static_cast<int64_t>(1e9 / f.fps);
  const bool y8i_image = image_ == infrared_.get() && f.fourcc == kY8i;
  const size_t img_px = static_cast<size_t>(f.width) * static_cast<size_t>(f.height);
  image_buf_.pixels.reserve(img_px * (image_ == color_.get() ? 3 : 1));
  if (y8i_image) ir2_buf_.pixels.reserve(img_px);
  if (depth_) {
    const NodeFormat& df = depth_->video().format();
    if (df.fourcc != v4l2::kZ16) {
      std::string e = "D4xx depth: " + v4l2::fourcc_name(df.fourcc) + " is not Z16";
      close();
      return e;
    }
    size_t out_px = static_cast<size_t>(df.width) * static_cast<size_t>(df.height);
    if (o.depth_camera.present && !o.infrared_is_image) {
      const CameraIntrinsics& di = o.depth_camera.intrinsics;
      if (di.width != df.width || di.height != df.height) {
        std::string e = "D4xx depth: stream " + std::to_string(df.width) + "x" + std::to_string(df.height) +
                        " but the rig's depth_camera is " + std::to_string(di.width) + "x" +
                        std::to_string(di.height);
        close();
        return e;
      }
      try {
        registration_ =
            std::make_unique<DepthRegistration>(o.depth_camera, o.image_camera, o.rig_depth_scale_m);
      } catch (const std::invalid_argument& ex) {
        close();
        return std::string("D4xx depth registration: ") + ex.what();
      }
      depth_scratch_.assign(out_px, 0);
      out_px = static_cast<size_t>(registration_->colour_width()) *
               static_cast<size_t>(registration_->colour_height());
    }
    depth_buf_.pixels.reserve(out_px * 2);
  }
  if (infrared_ && image_ != infrared_.get()) {
    const NodeFormat& inf = infrared_->video().format();
    const size_t px = static_cast<size_t>(inf.width) * static_cast<size_t>(inf.height);
    ir1_buf_.pixels.reserve(px);
    if (inf.fourcc == kY8i) ir2_buf_.pixels.reserve(px);
  }
  return "";
}

bool Camera::convert(StreamKind kind, const NodeBuffer& b, const NodeFormat& f, ImageBuffer& dst,
                     ImageBuffer* ir2) {
  const int w = f.width, h = f.height;
  const int bpp_in = f.fourcc == v4l2::kZ16 || f.fourcc == v4l2::kYuyv || f.fourcc == kY8i ? 2
                     : f.fourcc == kRgb24                                                  ? 3
                                                                                           : 1;
  const int stride = f.stride > 0 ? f.stride : w * bpp_in;
  if (w <= 0 || h <= 0 || stride < w * bpp_in || b.data == nullptr ||
      b.bytes_used <
          static_cast<size_t>(stride) * static_cast<size_t>(h - 1) + static_cast<size_t>(w * bpp_in))
    return false;
  auto size_to = [&](ImageBuffer& img, int iw, int ih, PixelFormat pf) {
    const size_t need =
        static_cast<size_t>(iw) * static_cast<size_t>(ih) * static_cast<size_t>(bytes_per_pixel(pf));
    if (need > img.pixels.capacity()) return false;  // sized at open(): never grow here
    img.pixels.resize(need);
    img.width = iw;
    img.height = ih;
    img.format = pf;
    return true;
  };
  switch (kind) {
    case StreamKind::kColor:
      if (f.fourcc == v4l2::kYuyv) {
        if (!size_to(dst, w, h, PixelFormat::kRgb8)) return false;
        v4l2::yuyv_to_rgb(b.data, w, h, stride, dst.pixels.data(), w * 3);
      } else if (f.fourcc == kRgb24) {
        if (!size_to(dst, w, h, PixelFormat::kRgb8)) return false;
        v4l2::copy_rows(b.data, w * 3, h, stride, dst.pixels.data());
      } else {
        return false;
      }
      return true;
    case StreamKind::kDepth:
      if (f.fourcc != v4l2::kZ16) return false;
      if (registration_) {
        if (!size_to(dst, registration_->colour_width(), registration_->colour_height(),
                     PixelFormat::kDepthU16))
          return false;
        return v4l2::z16_to_registered_depth(b.data, w, h, stride, opt_.depth_unit_m, opt_.rig_depth_scale_m,
                                             *registration_, depth_scratch_.data(),
                                             reinterpret_cast<uint16_t*>(dst.pixels.data()), dst.width * 2);
      }
      if (!size_to(dst, w, h, PixelFormat::kDepthU16)) return false;
      v4l2::z16_to_depth(b.data, w, h, stride, opt_.depth_unit_m, opt_.rig_depth_scale_m,
                         reinterpret_cast<uint16_t*>(dst.pixels.data()));
      return true;
    case StreamKind::kInfrared:
      if (!size_to(dst, w, h, PixelFormat::kGray8)) return false;
      if (f.fourcc == v4l2::kGrey) {
        v4l2::copy_rows(b.data, w, h, stride, dst.pixels.data());
        return true;
      }
      if (f.fourcc != kY8i) return false;
      if (ir2 != nullptr && !size_to(*ir2, w, h, PixelFormat::kGray8)) return false;
      for (int y = 0; y < h; ++y) {
        const uint8_t* s = b.data + static_cast<size_t>(y) * static_cast<size_t>(stride);
        uint8_t* l = dst.pixels.data() + static_cast<size_t>(y) * static_cast<size_t>(w);
        uint8_t* r =
            ir2 != nullptr ? ir2->pixels.data() + static_cast<size_t>(y) * static_cast<size_t>(w) : nullptr;
        for (int x = 0; x < w; ++x) {
          l[x] = s[2 * x];
          if (r != nullptr) r[x] = s[2 * x + 1];
        }
      }
      return true;
  }
  return false;
}

Stream::Result Camera::grab_partner(Stream& s, int timeout_ms, const StreamFrame& lead, ImageBuffer& dst,
                                    ImageBuffer* ir2, StreamFrame& meta, bool& paired) {
  paired = false;
  const int64_t tol = opt_.pair_tolerance_ns > 0 ? opt_.pair_tolerance_ns : period_ns_ / 2;
  bool& held = &s == depth_.get() ? depth_held_ : ir_held_;
  StreamFrame& held_meta = &s == depth_.get() ? depth_held_meta_ : ir_held_meta_;
  if (held) {
    if (held_meta.t_ns < lead.t_ns - tol) {
      held = false;  // too old for this lead and every later one
      ++depth_skipped_;
    } else if (held_meta.t_ns <= lead.t_ns + tol) {
      held = false;
      meta = held_meta;
      paired = true;
      return Stream::Result::kFrame;
    } else {
      return Stream::Result::kFrame;  // still newer than this lead: it waits for the next
    }
  }
  // A few stale frames at most (a partner that fell behind catches up here).
  for (int tries = 0; tries < 4; ++tries) {
    NodeBuffer b;
    StreamFrame m;
    const Stream::Result r = s.next(timeout_ms, opt_.metadata_wait_ms, clock_, false, opt_.readout_ns, b, m);
    if (r != Stream::Result::kFrame) return r;
    const bool ok = convert(s.kind(), b, s.video().format(), dst, ir2);
    s.release(b);
    if (!ok) {
      s.count_error();
      continue;
    }
    dst.t_ns = m.t_ns;
    dst.t_recv_ns = m.t_recv_ns;
    dst.seq = m.seq;
    if (ir2 != nullptr) ir2->t_ns = m.t_ns, ir2->t_recv_ns = m.t_recv_ns, ir2->seq = m.seq;
    if (m.t_ns < lead.t_ns - tol) {
      ++depth_skipped_;
      continue;
    }
    if (m.t_ns <= lead.t_ns + tol) {
      meta = m;
      paired = true;
      return Stream::Result::kFrame;
    }
    held = true;
    held_meta = m;
    return Stream::Result::kFrame;
  }
  return Stream::Result::kFrame;
}

Camera::Result Camera::grab(int timeout_ms, Frame& out) {
  out = Frame{};
  if (image_ == nullptr) return Result::kError;
  NodeBuffer b;
  StreamFrame m;
  const Stream::Result r =
      image_->next(timeout_ms, opt_.metadata_wait_ms, clock_, true, opt_.readout_ns, b, m);
  if (r == Stream::Result::kTimeout) return Result::kTimeout;
  if (r == Stream::Result::kError) return Result::kError;
  const NodeFormat& f = image_->video().format();
  ImageBuffer* image_ir2 = image_ == infrared_.get() && f.fourcc == kY8i ? &ir2_buf_ : nullptr;
  const bool ok = convert(image_->kind(), b, f, image_buf_, image_ir2);
  image_->release(b);
  if (!ok) {
    image_->count_error();
    return Result::kError;
  }
  image_buf_.t_ns = m.t_ns;
  image_buf_.t_recv_ns = m.t_recv_ns;
  image_buf_.seq = m.seq;
  out.image_meta = m;
  out.image = &image_buf_;
  if (image_ir2 != nullptr) {
    ir2_buf_.t_ns = m.t_ns;
    out.ir2 = &ir2_buf_;
  }
  // A partner waits at most two frame periods: a dead depth node must not stall the image stream.
  const int partner_ms = std::max(1, std::min(timeout_ms, static_cast<int>(2 * period_ns_ / 1'000'000)));
  if (depth_) {
    bool paired = false;
    (void)grab_partner(*depth_, partner_ms, m, depth_buf_, nullptr, out.depth_meta, paired);
    if (paired) {
      out.depth = &depth_buf_;
    } else {
      ++unpaired_;
    }
  }
  if (infrared_ && image_ != infrared_.get()) {
    const bool y8i = infrared_->video().format().fourcc == kY8i;
    bool paired = false;
    StreamFrame irm;
    (void)grab_partner(*infrared_, partner_ms, m, ir1_buf_, y8i ? &ir2_buf_ : nullptr, irm, paired);
    if (paired) {
      out.ir1 = &ir1_buf_;
      out.ir2 = y8i ? &ir2_buf_ : nullptr;
    }
  }
  ++sets_;
  return Result::kFrame;
}

Counters Camera::counters() const {
  Counters c;
  if (color_) c.color = color_->counters();
  if (depth_) c.depth = depth_->counters();
  if (infrared_) c.infrared = infrared_->counters();
  c.sets = sets_;
  c.unpaired = unpaired_;
  c.depth_skipped = depth_skipped_;
  c.clock_jumps = clock_.sync().jumps();
  return c;
}

std::string Camera::report() const {
  std::string s;
  auto line = [&](const Stream* st) {
    if (st == nullptr) return;
    const StreamCounters& c = st->counters();
    const uint32_t mf = st->metadata_format();
    const std::string meta = mf == 0             ? "no metadata node"
                             : mf == kMetaFmtUvc ? "metadata UVCH (no D4xx blocks: kernel stamps)"
                                                 : "metadata " + v4l2::fourcc_name(mf);
    char b[640];
    std::snprintf(
        b, sizeof b,
        "D4xx %s (%s): %llu frames, %llu dropped, %llu hardware stamps; kernel stamps: %llu no metadata, "
        "%llu "
        "corrupt metadata, %llu no sensor timestamp; %llu orphan metadata, %llu frame-counter gaps, %llu "
        "errors, %llu timeouts\n",
        stream_name(st->kind()), meta.c_str(), static_cast<unsigned long long>(c.frames),
        static_cast<unsigned long long>(c.dropped), static_cast<unsigned long long>(c.hardware_stamps),
        static_cast<unsigned long long>(c.metadata_missing),
        static_cast<unsigned long long>(c.metadata_corrupt),
        static_cast<unsigned long long>(c.metadata_no_timestamp),
        static_cast<unsigned long long>(c.metadata_orphans),
        static_cast<unsigned long long>(c.frame_counter_gaps), static_cast<unsigned long long>(c.errors),
        static_cast<unsigned long long>(c.timeouts));
    s += b;
  };
  line(color_.get());
  line(depth_.get());
  line(infrared_.get());
  char b[256];
  std::snprintf(
      b, sizeof b,
      "D4xx clock: %llu observations, skew %.1f ppm, %llu jumps, mean excess latency %.0f us; %llu sets, "
      "%llu without depth, %llu stale partners skipped",
      static_cast<unsigned long long>(clock_.observations()), 1e6 * clock_.sync().skew(),
      static_cast<unsigned long long>(clock_.sync().jumps()), 1e-3 * clock_.sync().mean_excess_latency_ns(),
      static_cast<unsigned long long>(sets_), static_cast<unsigned long long>(unpaired_),
      static_cast<unsigned long long>(depth_skipped_));
  s += b;
  return s;
}

// ---- the kernel's nodes ---------------------------------------------------------------------------
#if KESTREL_WITH_V4L2

namespace {
int xioctl(int fd, unsigned long req, void* arg) {
  int r;
  do r = ioctl(fd, req, arg);
  while (r < 0 && errno == EINTR);
  return r;
}

std::vector<v4l2::FormatOption> enumerate_video(int fd) {
  std::vector<v4l2::FormatOption> out;
  v4l2_fmtdesc d{};
  std::memset(&d, 0, sizeof d);
  d.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  for (d.index = 0; xioctl(fd, VIDIOC_ENUM_FMT, &d) == 0; ++d.index) {
    v4l2_frmsizeenum fs{};
    std::memset(&fs, 0, sizeof fs);
    fs.pixel_format = d.pixelformat;
    for (fs.index = 0; xioctl(fd, VIDIOC_ENUM_FRAMESIZES, &fs) == 0; ++fs.index) {
      if (fs.type != V4L2_FRMSIZE_TYPE_DISCRETE) break;
      v4l2_frmivalenum fi{};
      std::memset(&fi, 0, sizeof fi);
      fi.pixel_format = fs.pixel_format;
      fi.width = fs.discrete.width;
      fi.height = fs.discrete.height;
      bool any = false;
      for (fi.index = 0; xioctl(fd, VIDIOC_ENUM_FRAMEINTERVALS, &fi) == 0; ++fi.index) {
        if (fi.type != V4L2_FRMIVAL_TYPE_DISCRETE || fi.discrete.numerator == 0) break;
        out.push_back({fs.pixel_format, static_cast<int>(fs.discrete.width),
                       static_cast<int>(fs.discrete.height),
                       static_cast<double>(fi.discrete.denominator) / fi.discrete.numerator});
        any = true;
      }
      if (!any) {
        out.push_back({fs.pixel_format, static_cast<int>(fs.discrete.width),
                       static_cast<int>(fs.discrete.height), 0.0});
      }
    }
  }
  return out;
}

class V4l2Node final : public Node {
 public:
  ~V4l2Node() override { close(); }
  std::string open(const std::string& path, const NodeRequest& r) override {
    close();
    type_ = r.metadata ? V4L2_BUF_TYPE_META_CAPTURE : V4L2_BUF_TYPE_VIDEO_CAPTURE;
    fd_ = ::open(path.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
    if (fd_ < 0) return path + ": " + std::strerror(errno);
    auto fail = [&](const std::string& what) {
      std::string msg = path + ": " + what;
      close();
      return msg;
    };
    v4l2_capability cap{};
    std::memset(&cap, 0, sizeof cap);
    if (xioctl(fd_, VIDIOC_QUERYCAP, &cap) < 0) return fail("not a V4L2 device");
    const uint32_t caps = (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
    if (r.metadata) {
      if (!(caps & V4L2_CAP_META_CAPTURE)) return fail("not a metadata capture node");
      v4l2_format fmt{};
      std::memset(&fmt, 0, sizeof fmt);
      fmt.type = V4L2_BUF_TYPE_META_CAPTURE;
      fmt.fmt.meta.dataformat = kMetaFmtD4xx;  // passes Intel's blocks on kernels that know the D4xx
      if (xioctl(fd_, VIDIOC_S_FMT, &fmt) < 0) {
        std::memset(&fmt, 0, sizeof fmt);
        fmt.type = V4L2_BUF_TYPE_META_CAPTURE;
        if (xioctl(fd_, VIDIOC_G_FMT, &fmt) < 0) return fail("VIDIOC_G_FMT (metadata) failed");
      }
      if (fmt.fmt.meta.dataformat != kMetaFmtD4xx && fmt.fmt.meta.dataformat != kMetaFmtUvc) {
        return fail("metadata format " + v4l2::fourcc_name(fmt.fmt.meta.dataformat) +
                    " is neither UVCH nor D4XX");
      }
      format_.fourcc = fmt.fmt.meta.dataformat;
      format_.buffer_bytes = fmt.fmt.meta.buffersize;
    } else {
      if (!(caps & V4L2_CAP_VIDEO_CAPTURE) || !(caps & V4L2_CAP_STREAMING))
        return fail("not a streaming video capture node");
      const v4l2::FormatChoice choice = v4l2::choose_format(enumerate_video(fd_), r.format);
      if (!choice.ok) return fail(choice.why);
      v4l2_format fmt{};
      std::memset(&fmt, 0, sizeof fmt);
      fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      fmt.fmt.pix.width = static_cast<uint32_t>(choice.option.width);
      fmt.fmt.pix.height = static_cast<uint32_t>(choice.option.height);
      fmt.fmt.pix.pixelformat = choice.option.fourcc;
      fmt.fmt.pix.field = V4L2_FIELD_NONE;
      if (xioctl(fd_, VIDIOC_S_FMT, &fmt) < 0)
        return fail(std::string("VIDIOC_S_FMT: ") + std::strerror(errno));
      if (fmt.fmt.pix.pixelformat != choice.option.fourcc ||
          static_cast<int>(fmt.fmt.pix.width) != choice.option.width ||
          static_cast<int>(fmt.fmt.pix.height) != choice.option.height)
        return fail("the driver changed the requested format");
      format_.fourcc = choice.option.fourcc;
      format_.width = choice.option.width;
      format_.height = choice.option.height;
      format_.fps = choice.option.fps;
      format_.stride = static_cast<int>(fmt.fmt.pix.bytesperline);
      format_.buffer_bytes = fmt.fmt.pix.sizeimage;
      if (choice.option.fps > 0) {
        v4l2_streamparm parm{};
        std::memset(&parm, 0, sizeof parm);
        parm.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        parm.parm.capture.timeperframe.numerator = 1000;
        parm.parm.capture.timeperframe.denominator =
            static_cast<uint32_t>(std::lround(choice.option.fps * 1000));
        (void)xioctl(fd_, VIDIOC_S_PARM, &parm);
      }
    }
    v4l2_requestbuffers req{};
    std::memset(&req, 0, sizeof req);
    req.count = static_cast<uint32_t>(std::clamp(r.buffers, 2, v4l2::BufferBook::kMaxBuffers));
    req.type = type_;
    req.memory = V4L2_MEMORY_MMAP;
    if (xioctl(fd_, VIDIOC_REQBUFS, &req) < 0 || req.count < 2) return fail("VIDIOC_REQBUFS (mmap) failed");
    book_.reset(static_cast<int>(req.count));
    for (uint32_t i = 0; i < req.count; ++i) {
      v4l2_buffer b{};
      std::memset(&b, 0, sizeof b);
      b.type = type_;
      b.memory = V4L2_MEMORY_MMAP;
      b.index = i;
      if (xioctl(fd_, VIDIOC_QUERYBUF, &b) < 0) return fail("VIDIOC_QUERYBUF failed");
      void* p = mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_, b.m.offset);
      if (p == MAP_FAILED) return fail(std::string("mmap: ") + std::strerror(errno));
      maps_.push_back({p, b.length});
      if (xioctl(fd_, VIDIOC_QBUF, &b) < 0) return fail("VIDIOC_QBUF failed");
      book_.on_queued(static_cast<int>(i));
    }
    int t = static_cast<int>(type_);
    if (xioctl(fd_, VIDIOC_STREAMON, &t) < 0)
      return fail(std::string("VIDIOC_STREAMON: ") + std::strerror(errno));
    return "";
  }
  void close() override {
    if (fd_ >= 0) {
      int t = static_cast<int>(type_);
      (void)xioctl(fd_, VIDIOC_STREAMOFF, &t);
    }
    for (const auto& m : maps_) munmap(m.first, m.second);
    maps_.clear();
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
  }
  bool is_open() const override { return fd_ >= 0; }
  const NodeFormat& format() const override { return format_; }
  NodeWait wait(int timeout_ms) override {
    if (fd_ < 0) return NodeWait::kError;
    pollfd p{fd_, POLLIN, 0};
    const int rc = poll(&p, 1, timeout_ms);
    if (rc == 0 || (rc < 0 && errno == EINTR)) return NodeWait::kTimeout;
    if (rc < 0 || (p.revents & (POLLERR | POLLHUP | POLLNVAL))) return NodeWait::kError;
    return NodeWait::kReady;
  }
  bool dequeue(NodeBuffer& out) override {
    if (fd_ < 0) return false;
    v4l2_buffer b{};
    std::memset(&b, 0, sizeof b);
    b.type = type_;
    b.memory = V4L2_MEMORY_MMAP;
    if (xioctl(fd_, VIDIOC_DQBUF, &b) < 0) return false;
    if (!book_.on_dequeued(static_cast<int>(b.index)) || b.index >= maps_.size()) return false;
    out.index = static_cast<int>(b.index);
    out.data = static_cast<const uint8_t*>(maps_[b.index].first);
    out.bytes_used = std::min<size_t>(b.bytesused, maps_[b.index].second);
    out.sequence = b.sequence;
    out.flags = b.flags;
    out.tv_sec = b.timestamp.tv_sec;
    out.tv_usec = b.timestamp.tv_usec;
    return true;
  }
  bool requeue(const NodeBuffer& nb) override {
    if (fd_ < 0) return false;
    v4l2_buffer b{};
    std::memset(&b, 0, sizeof b);
    b.type = type_;
    b.memory = V4L2_MEMORY_MMAP;
    b.index = static_cast<uint32_t>(nb.index);
    return xioctl(fd_, VIDIOC_QBUF, &b) == 0 && book_.on_queued(nb.index);
  }

 private:
  int fd_ = -1;
  v4l2_buf_type type_ = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  NodeFormat format_;
  std::vector<std::pair<void*, size_t>> maps_;
  v4l2::BufferBook book_;
};
}  // namespace

std::unique_ptr<Node> make_v4l2_node() { return std::make_unique<V4l2Node>(); }

std::vector<ProbedNode> probe_v4l2_nodes(std::string* error) {
  std::vector<ProbedNode> out;
  int seen = 0;
  for (int i = 0; i < 64; ++i) {
    const std::string path = "/dev/video" + std::to_string(i);
    const int fd = ::open(path.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0) continue;
    ++seen;
    v4l2_capability cap{};
    std::memset(&cap, 0, sizeof cap);
    if (xioctl(fd, VIDIOC_QUERYCAP, &cap) == 0) {
      const uint32_t caps = (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
      ProbedNode n;
      n.path = path;
      n.minor = i;
      n.card = reinterpret_cast<const char*>(cap.card);
      n.bus_info = reinterpret_cast<const char*>(cap.bus_info);
      n.metadata = (caps & V4L2_CAP_META_CAPTURE) != 0 && !(caps & V4L2_CAP_VIDEO_CAPTURE);
      if (!n.metadata) {
        for (const auto& o : enumerate_video(fd)) {
          if (std::find(n.formats.begin(), n.formats.end(), o.fourcc) == n.formats.end())
            n.formats.push_back(o.fourcc);
        }
      }
      out.push_back(n);
    }
    ::close(fd);
  }
  if (seen == 0 && error != nullptr) *error = "no /dev/video* nodes";
  return out;
}

#else

namespace {
class NotBuiltNode final : public Node {
 public:
  std::string open(const std::string& path, const NodeRequest&) override {
    return path + ": V4L2 support not built (no <linux/videodev2.h> at build time)";
  }
  void close() override {}
  bool is_open() const override { return false; }
  const NodeFormat& format() const override { return f_; }
  NodeWait wait(int) override { return NodeWait::kError; }
  bool dequeue(NodeBuffer&) override { return false; }
  bool requeue(const NodeBuffer&) override { return false; }

 private:
  NodeFormat f_;
};
}  // namespace
std::unique_ptr<Node> make_v4l2_node() { return std::make_unique<NotBuiltNode>(); }
std::vector<ProbedNode> probe_v4l2_nodes(std::string* error) {
  if (error) *error = "V4L2 support not built";
  return {};
}

#endif

}  // namespace kestrel::drivers::d4xx

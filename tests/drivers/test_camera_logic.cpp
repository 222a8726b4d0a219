// Camera drivers without a camera: format negotiation, buffer bookkeeping,
// sequence gaps, buffer timestamps, pixel conversions, and the "no device"
// path's message.
#include <gtest/gtest.h>

#include <cstring>
#include <string>
#include <vector>

#include "kestrel/drivers/openni2_camera.hpp"
#include "kestrel/drivers/v4l2_camera.hpp"

namespace kestrel::drivers::v4l2 {
namespace {

std::vector<FormatOption> realsense_like() {
  // A D435 colour node and the depth node's Z16, as VIDIOC_ENUM_* would list them.
  return {{kYuyv, 1280, 720, 15}, {kYuyv, 640, 480, 15}, {kYuyv, 640, 480, 30}, {kYuyv, 640, 480, 60},
          {kMjpeg, 640, 480, 30}, {kZ16, 640, 480, 30},  {kZ16, 640, 480, 90},  {kGrey, 640, 480, 30}};
}

TEST(V4l2Format, PicksThePreferredFormatAndTheSlowestSufficientRate) {
  FormatRequest r;
  r.preferred = {kYuyv, kMjpeg};
  FormatChoice c = choose_format(realsense_like(), r);
  ASSERT_TRUE(c.ok);
  EXPECT_EQ(c.option.fourcc, kYuyv);
  EXPECT_DOUBLE_EQ(c.option.fps, 30);
  r.fps = 45;
  c = choose_format(realsense_like(), r);
  EXPECT_DOUBLE_EQ(c.option.fps, 60);
  r.fps = 120;  // nothing that fast: the fastest there is
  c = choose_format(realsense_like(), r);
  EXPECT_DOUBLE_EQ(c.option.fps, 60);
  r = FormatRequest{};
  r.preferred = {kZ16};
  c = choose_format(realsense_like(), r);
  ASSERT_TRUE(c.ok);
  EXPECT_EQ(c.option.fourcc, kZ16);
  EXPECT_DOUBLE_EQ(c.option.fps, 30);
}

TEST(V4l2Format, NoMatchSaysWhatIsOffered) {
  FormatRequest r;
  r.width = 848;
  r.preferred = {kYuyv};
  const FormatChoice c = choose_format(realsense_like(), r);
  EXPECT_FALSE(c.ok);
  EXPECT_NE(c.why.find("848x480"), std::string::npos);
  EXPECT_NE(c.why.find("YUYV 640x480@30"), std::string::npos);
  EXPECT_EQ(fourcc_name(kZ16), "Z16 ");
  EXPECT_EQ(fourcc_from_name("mjpeg"), kMjpeg);
  EXPECT_EQ(fourcc_from_name("h264"), 0u);
}

TEST(V4l2Time, MonotonicSoeAndFallback) {
  // timeval -> ns, start of exposure: mid = stamp + exposure / 2.
  BufferTime t = buffer_time(12, 345678, kBufFlagTimestampMonotonic | kBufFlagTstampSrcSoe, 99);
  EXPECT_TRUE(t.monotonic);
  EXPECT_TRUE(t.start_of_exposure);
  EXPECT_EQ(t.t_ns, 12'345'678'000);
  EXPECT_EQ(mid_exposure_ns(t, 10'000, 7'000'000), 12'345'678'000 + 5'000'000);
  // End of frame (UVC default): mid = stamp - readout - exposure / 2.
  t = buffer_time(12, 345678, kBufFlagTimestampMonotonic, 99);
  EXPECT_FALSE(t.start_of_exposure);
  EXPECT_EQ(mid_exposure_ns(t, 10'000, 7'000'000), 12'345'678'000 - 7'000'000 - 5'000'000);
  // Unknown / copied clock: the dequeue time, never trusted as start of exposure.
  t = buffer_time(12, 345678, 0x4000 | kBufFlagTstampSrcSoe, 777);
  EXPECT_FALSE(t.monotonic);
  EXPECT_FALSE(t.start_of_exposure);
  EXPECT_EQ(t.t_ns, 777);
}

TEST(V4l2Sequence, GapsWrapAndRestarts) {
  SequenceTracker s;
  EXPECT_EQ(s.update(10), 0u);
  EXPECT_EQ(s.update(11), 0u);
  EXPECT_EQ(s.update(14), 2u);
  EXPECT_EQ(s.update(0xFFFFFFFFu), 0u);  // restart far behind -> counted as a restart... (d < 0)
  EXPECT_EQ(s.restarts(), 1u);
  EXPECT_EQ(s.update(0), 0u);  // wraps cleanly
  EXPECT_EQ(s.update(3), 2u);
  EXPECT_EQ(s.dropped(), 4u);
}

TEST(V4l2Buffers, BookkeepingCatchesDoubleQueueAndStarvation) {
  BufferBook b(4);
  for (int i = 0; i < 4; ++i) EXPECT_TRUE(b.on_queued(i));
  EXPECT_FALSE(b.on_queued(2));  // already with the driver
  EXPECT_EQ(b.errors(), 1u);
  EXPECT_TRUE(b.on_dequeued(1));
  EXPECT_FALSE(b.on_dequeued(1));  // dequeued twice
  EXPECT_FALSE(b.on_dequeued(7));  // no such buffer
  EXPECT_EQ(b.queued(), 3);
  EXPECT_EQ(b.dequeued(), 1);
  for (int i : {0, 2, 3}) EXPECT_TRUE(b.on_dequeued(i));
  EXPECT_TRUE(b.starved());
  EXPECT_TRUE(b.on_queued(3));
  EXPECT_FALSE(b.starved());
  EXPECT_EQ(b.errors(), 3u);
}

TEST(V4l2Convert, YuyvToRgbFixture) {
  // Two rows of 2 pixels: (Y0 U Y1 V). Limited-range black, white, and pure red-ish.
  const uint8_t src[] = {16, 128, 235, 128, /*row stride pad*/ 0, 0, 81, 90, 81, 240, 0, 0};
  uint8_t dst[2 * 2 * 3];
  yuyv_to_rgb(src, 2, 2, 6, dst, 6);
  EXPECT_EQ(dst[0], 0);
  EXPECT_EQ(dst[1], 0);
  EXPECT_EQ(dst[2], 0);
  EXPECT_EQ(dst[3], 255);
  EXPECT_EQ(dst[4], 255);
  EXPECT_EQ(dst[5], 255);
  // BT.601 red (Y 81, U 90, V 240) -> about (255, 0, 0).
  EXPECT_GE(dst[6], 250);
  EXPECT_LE(dst[7], 3);
  EXPECT_LE(dst[8], 3);
}

TEST(V4l2Convert, Z16ToDepthKeepsInvalidAndRescales) {
  const uint16_t src[] = {0, 1000, 65535, 42, /*pad*/ 7, 1, 2, 3, 4, 9};
  uint16_t dst[8];
  z16_to_depth(reinterpret_cast<const uint8_t*>(src), 4, 2, 10, 0.001, 0.001, dst);
  EXPECT_EQ(dst[1], 1000);
  EXPECT_EQ(dst[4], 1);  // second row starts after the stride
  // Device in 1 mm, rig in 0.25 mm: x4; 0 stays invalid; overflow becomes invalid.
  z16_to_depth(reinterpret_cast<const uint8_t*>(src), 4, 2, 10, 0.001, 0.00025, dst);
  EXPECT_EQ(dst[0], 0);
  EXPECT_EQ(dst[1], 4000);
  EXPECT_EQ(dst[2], 0);
  EXPECT_EQ(dst[3], 168);
}

// A RealSense-style depth node with its own camera: the driver's depth path
// converts units and registers to colour in one go, into the colour size.
TEST(V4l2Convert, Z16FromASeparateDepthCameraIsRegisteredToColour) {
  DepthCamera dc;
  dc.present = true;
  dc.intrinsics.width = 8, dc.intrinsics.height = 4;
  dc.intrinsics.fx = dc.intrinsics.fy = 8;
  dc.intrinsics.cx = 3.5, dc.intrinsics.cy = 1.5;
  dc.T_CD[3] = -0.25;  // 25 cm baseline: 1 px of disparity at 2 m
  CameraIntrinsics colour = dc.intrinsics;
  colour.width = 10, colour.height = 6;
  colour.cx = 4.5, colour.cy = 2.5;
  const DepthRegistration reg(dc, colour, 0.001);
  // Device units of 0.25 mm: 8000 = 2 m; one invalid pixel.
  uint16_t src[8 * 4];
  for (uint16_t& v : src) v = 8000;
  src[0] = 0;
  uint16_t scratch[8 * 4], out[10 * 6];
  RegistrationStats st;
  ASSERT_TRUE(z16_to_registered_depth(reinterpret_cast<const uint8_t*>(src), 8, 4, 16, 0.00025, 0.001, reg,
                                      scratch, out, 20, &st));
  EXPECT_EQ(st.valid_in, 31);
  // Depth pixel (u, v) lands at colour (u, v + 1): the principal points differ
  // by (1, 1) and the baseline takes 1 px back in x. 2000 mm; the colour
  // border the depth camera does not cover stays 0.
  EXPECT_EQ(out[1 * 10 + 0], 0);  // the invalid pixel (0, 0)
  EXPECT_EQ(out[1 * 10 + 2], 2000);
  EXPECT_EQ(out[4 * 10 + 7], 2000);
  EXPECT_EQ(out[0 * 10 + 5], 0);
  EXPECT_EQ(out[5 * 10 + 5], 0);
  EXPECT_EQ(out[2 * 10 + 8], 0);
  EXPECT_EQ(out[2 * 10 + 9], 0);
  // A frame of another size is refused.
  EXPECT_FALSE(z16_to_registered_depth(reinterpret_cast<const uint8_t*>(src), 4, 4, 8, 0.00025, 0.001, reg,
                                       scratch, out, 20));
}

// A frame source standing in for the kernel's V4L2 queue: frames arrive every
// 33 ms into a queued buffer, or are dropped (sequence still advances, as the
// kernel does) when the application holds every buffer.
class FakeV4l2Queue {
 public:
  explicit FakeV4l2Queue(int n) : queued_(static_cast<size_t>(n), true) {}
  // Kernel side at time t: fill the lowest queued buffer or drop.
  void frame(int64_t t_ns) {
    for (size_t i = 0; i < queued_.size(); ++i)
      if (queued_[i]) {
        queued_[i] = false;
        done_.push_back({static_cast<int>(i), seq_++, t_ns});
        return;
      }
    ++seq_;
    ++dropped_;
  }
  struct Done {
    int index;
    uint32_t seq;
    int64_t t_ns;
  };
  bool dqbuf(Done& d) {
    if (done_.empty()) return false;
    d = done_.front();
    done_.erase(done_.begin());
    return true;
  }
  void qbuf(int i) { queued_[static_cast<size_t>(i)] = true; }
  uint64_t dropped() const { return dropped_; }
  size_t pending() const { return done_.size(); }

 private:
  std::vector<bool> queued_;
  std::vector<Done> done_;
  uint32_t seq_ = 100;
  uint64_t dropped_ = 0;
};

TEST(V4l2Stream, SlowConsumerDropsAreCountedAndBuffersAlwaysReturn) {
  FakeV4l2Queue q(4);
  BufferBook book(4);
  for (int i = 0; i < 4; ++i) book.on_queued(i);
  SequenceTracker seq;
  uint64_t frames = 0;
  int64_t last_t = 0;
  // 30 Hz for 20 s; the consumer stalls for 400 ms every 5 s (a disk hiccup).
  for (int k = 0; k < 600; ++k) {
    const int64_t t = static_cast<int64_t>(k) * 33'333'333;
    q.frame(t);
    const bool stalled = (k % 150) >= 100 && (k % 150) < 112;
    FakeV4l2Queue::Done d;
    while (!stalled && q.dqbuf(d)) {
      ASSERT_TRUE(book.on_dequeued(d.index));
      seq.update(d.seq);
      ASSERT_GT(d.t_ns, last_t - 1);
      last_t = d.t_ns;
      ++frames;
      q.qbuf(d.index);  // re-queued at once, after the copy into the pool
      ASSERT_TRUE(book.on_queued(d.index));
    }
  }
  EXPECT_GT(q.dropped(), 0u);
  EXPECT_EQ(seq.dropped(), q.dropped());
  // Every frame the kernel made is accounted for: consumed, dropped, or still waiting.
  EXPECT_EQ(frames + q.dropped() + q.pending(), 600u);
  EXPECT_EQ(book.errors(), 0u);
  EXPECT_FALSE(book.starved());
}

TEST(V4l2Device, MissingDeviceGivesAClearError) {
  Camera cam;
  Options o;
  o.device = "/dev/video-kestrel-none";
  o.request.preferred = {kYuyv};
  const std::string e = cam.open(o);
  EXPECT_FALSE(e.empty());
  EXPECT_NE(e.find("/dev/video-kestrel-none"), std::string::npos);
  EXPECT_FALSE(cam.is_open());
}

TEST(OpenNi2, PairingAndNoDevice) {
  EXPECT_TRUE(openni2::stamps_pair(1'000'000, 1'010'000, 30));
  EXPECT_FALSE(openni2::stamps_pair(1'000'000, 1'020'000, 30));
  if (!openni2::openni2_built()) GTEST_SKIP() << "OpenNI2 not built";
  openni2::Camera cam;
  openni2::Options o;
  o.uri = "kestrel://no-such-device";
  const std::string e = cam.open(o);
  EXPECT_FALSE(e.empty());
  std::printf("OpenNI2 open without a device: %s\n", e.c_str());
}

}  // namespace
}  // namespace kestrel::drivers::v4l2

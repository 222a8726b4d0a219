// RealSense D4xx without a camera: the UVC metadata parser against byte
// fixtures, the device clock, node grouping, and the real D4xx driver code
// run against fake V4L2 nodes (the Node seam, realsense_fake_nodes.hpp) fed
// with colour / Z16 / IR / metadata buffers. The simulated flight scored
// through `kestrel` is test_realsense_d4xx_flight.cpp.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "kestrel/drivers/d4xx_camera.hpp"
#include "kestrel/drivers/d4xx_metadata.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/tools/config_file.hpp"
#include "realsense_fake_nodes.hpp"

namespace kestrel::drivers::d4xx {
namespace {

// ---- byte fixtures -----------------------------------------------------------------------
void put(std::vector<uint8_t>& v, uint64_t x, int bytes) {
  for (int i = 0; i < bytes; ++i) v.push_back(static_cast<uint8_t>(x >> (8 * i)));
}

// One record written byte by byte from the layouts (not through encode_record).
std::vector<uint8_t> hand_record() {
  std::vector<uint8_t> b;
  put(b, 0x0000001122334455ull, 8);             // ns
  put(b, 0x0123, 2);                            // sof
  const size_t hlen = 2 + 4 + 6 + 40 + 8 + 40;  // header + PTS + SCR + timing + unknown block + configuration
  b.push_back(static_cast<uint8_t>(hlen));
  b.push_back(0x8d);      // EOH | SCR | PTS | FID
  put(b, 1'000'000, 4);   // PTS us
  put(b, 0xAABBCCDD, 4);  // SCR STC
  put(b, 0x0456, 2);      // SCR SOF
  put(b, 0x80000001, 4);  // md_capture_timing
  put(b, 40, 4);
  put(b, 1, 4);           // version
  put(b, 0x3f, 4);        // every field valid
  put(b, 77, 4);          // frame counter
  put(b, 990'000, 4);     // sensor timestamp us
  put(b, 9'000, 4);       // readout
  put(b, 2'000, 4);       // exposure
  put(b, 33'333, 4);      // frame interval
  put(b, 12'000, 4);      // pipe latency
  put(b, 0x12345678, 4);  // a block this parser does not know
  put(b, 8, 4);
  put(b, 0x80000002, 4);  // md_configuration
  put(b, 40, 4);
  put(b, 1, 4);
  put(b, 0x7f, 4);
  b.push_back(2);   // hw type
  b.push_back(9);   // sku
  put(b, 0, 4);     // cookie
  put(b, 0x1f, 2);  // format
  put(b, 848, 2);
  put(b, 480, 2);
  put(b, 30, 2);
  put(b, 0, 2);  // trigger
  put(b, 5, 2);  // calibration count
  put(b, 0, 6);
  return b;
}

TEST(RealSenseMetadata, HandBuiltRecordParses) {
  const std::vector<uint8_t> b = hand_record();
  FrameMetadata m;
  ASSERT_EQ(parse_metadata_buffer(b.data(), b.size(), m), ParseStatus::kOk);
  EXPECT_EQ(m.host_ns, 0x0000001122334455ll);
  EXPECT_EQ(m.usb_sof, 0x0123);
  EXPECT_TRUE(m.has_pts);
  EXPECT_TRUE(m.has_scr);
  EXPECT_EQ(m.pts_us, 1'000'000u);
  EXPECT_EQ(m.scr_stc, 0xAABBCCDDu);
  EXPECT_EQ(m.scr_sof, 0x0456);
  ASSERT_TRUE(m.has_sensor_timestamp());
  EXPECT_EQ(m.timing.frame_counter, 77u);
  EXPECT_EQ(m.timing.sensor_timestamp_us, 990'000u);
  EXPECT_EQ(m.timing.pipe_latency_us, 12'000u);
  EXPECT_EQ(m.exposure_us(), 2'000u);
  EXPECT_TRUE(m.configuration.present);
  EXPECT_EQ(m.configuration.width, 848);
  EXPECT_EQ(m.configuration.height, 480);
  EXPECT_EQ(m.configuration.fps, 30);
  EXPECT_EQ(m.configuration.calibration_count, 5);
  EXPECT_EQ(m.blocks, 3);
  EXPECT_EQ(m.unknown_blocks, 1);
  EXPECT_EQ(m.records, 1);
}

TEST(RealSenseMetadata, EncoderRoundTripsEveryField) {
  FrameMetadata m;
  m.host_ns = 123'456'789'012;
  m.usb_sof = 2047;
  m.pts_us = 0xFFFFFFF0u;
  m.scr_stc = 17;
  m.scr_sof = 99;
  m.timing.flags = kTimingSensorTimestampValid | kTimingFrameCounterValid;
  m.timing.frame_counter = 5;
  m.timing.sensor_timestamp_us = 0xFFFFFF00u;
  m.configuration.width = 640;
  m.configuration.height = 480;
  m.control.flags = kRgbControlManualExposureValid | kDepthControlExposureValid;
  m.control.exposure_us = 15'600;
  std::array<uint8_t, 400> buf{};
  for (bool depth : {false, true}) {
    EncodeOptions o;
    o.depth_control = depth;
    const size_t n = encode_record(m, o, buf.data(), buf.size());
    ASSERT_GT(n, 0u);
    FrameMetadata back;
    ASSERT_EQ(parse_metadata_buffer(buf.data(), n, back), ParseStatus::kOk);
    EXPECT_EQ(back.host_ns, m.host_ns);
    EXPECT_EQ(back.pts_us, m.pts_us);
    EXPECT_EQ(back.timing.sensor_timestamp_us, m.timing.sensor_timestamp_us);
    EXPECT_EQ(back.control.rgb, !depth);
    EXPECT_EQ(back.exposure_us(), 15'600u);  // RGB: 100 us units; depth: us
    EXPECT_EQ(back.configuration.width, 640);
  }
  EXPECT_EQ(encode_record(m, EncodeOptions{}, buf.data(), 20), 0u);  // too small: nothing written
}

TEST(RealSenseMetadata, EveryTruncationIsRefusedNeverOverread) {
  const std::vector<uint8_t> b = hand_record();
  for (size_t n = 0; n < b.size(); ++n) {
    // A copy of exactly n bytes on the heap: ASan catches a read past it.
    std::unique_ptr<uint8_t[]> p(new uint8_t[n == 0 ? 1 : n]);
    std::memcpy(p.get(), b.data(), n);
    FrameMetadata m;
    const ParseStatus s = parse_metadata_buffer(p.get(), n, m);
    EXPECT_NE(s, ParseStatus::kOk) << n << " bytes";
  }
}

TEST(RealSenseMetadata, BadLengthsAreNamed) {
  std::vector<uint8_t> b = hand_record();
  FrameMetadata m;
  std::vector<uint8_t> x = b;
  x[10] = 1;  // bLength < 2
  EXPECT_EQ(parse_metadata_buffer(x.data(), x.size(), m), ParseStatus::kBadHeaderLength);
  x = b;
  x[10] = 8;  // PTS + SCR announced, 8 bytes cannot hold them
  EXPECT_EQ(parse_metadata_buffer(x.data(), x.size(), m), ParseStatus::kBadHeaderLength);
  x = b;
  x[10 + 12 + 4] = 4;  // capture timing's md_size < 8
  EXPECT_EQ(parse_metadata_buffer(x.data(), x.size(), m), ParseStatus::kBadBlock);
  x = b;
  x[10 + 12 + 4] = 200;  // past the header
  EXPECT_EQ(parse_metadata_buffer(x.data(), x.size(), m), ParseStatus::kBadBlock);
  x = b;
  x[10 + 12 + 4] = 24;  // a capture timing too short for its fields
  EXPECT_EQ(parse_metadata_buffer(x.data(), x.size(), m), ParseStatus::kBadBlockSize);
  // A plain UVC header (no vendor bytes) is valid but carries no D4xx time.
  std::vector<uint8_t> plain;
  put(plain, 5, 8);
  put(plain, 0, 2);
  plain.push_back(12);
  plain.push_back(0x0c);
  put(plain, 1, 4);
  put(plain, 2, 6);
  EXPECT_EQ(parse_metadata_buffer(plain.data(), plain.size(), m), ParseStatus::kNoD4xxBlocks);
  EXPECT_EQ(m.pts_us, 1u);
  // Plain + D4xx records in one buffer: the D4xx one is described.
  plain.insert(plain.end(), b.begin(), b.end());
  ASSERT_EQ(parse_metadata_buffer(plain.data(), plain.size(), m), ParseStatus::kOk);
  EXPECT_EQ(m.records, 2);
  EXPECT_EQ(m.timing.frame_counter, 77u);
  EXPECT_EQ(parse_metadata_buffer(nullptr, 0, m), ParseStatus::kEmpty);
  EXPECT_STREQ(parse_status_name(ParseStatus::kBadBlock), "metadata block size < 8 or past the header");
}

TEST(RealSenseClock, UnwrapsThe32BitCounterAndMapsWithSkew) {
  DeviceClock c;
  // Device us counter 20 ppm slow; host = 5 s + device * (1 + 20e-6) + 300 us latency.
  const double skew = 20e-6;
  uint32_t dev = 0xFFFF0000u;  // about to wrap
  int64_t dev64 = dev;
  for (int i = 0; i < 300; ++i) {
    const int64_t h =
        5'000'000'000 + static_cast<int64_t>(std::llround((dev64 * 1000.0) * (1 + skew))) + 300'000;
    c.observe(dev, h);
    dev += 33'333;
    dev64 += 33'333;
  }
  EXPECT_GT(dev64, int64_t{1} << 32);  // wrapped
  EXPECT_EQ(c.unwrap_ns(dev - 10), (dev64 - 10) * 1000);
  EXPECT_EQ(c.unwrap_ns(dev + 100), (dev64 + 100) * 1000);
  const int64_t expect =
      5'000'000'000 + static_cast<int64_t>(std::llround((dev64 * 1000.0) * (1 + skew))) + 300'000;
  EXPECT_NEAR(static_cast<double>(c.to_host_ns(dev)), static_cast<double>(expect), 2'000.0);
  EXPECT_NEAR(c.sync().skew(), skew, 1e-6);
  EXPECT_EQ(c.sync().jumps(), 0u);
  // The line published for another thread maps the same.
  SharedDeviceClock shared;
  c.publish_to(&shared);
  c.observe(dev, expect);
  ClockLine line;
  ASSERT_TRUE(shared.read(line));
  EXPECT_NEAR(static_cast<double>(line.to_host_ns(c.unwrap_ns(dev))), static_cast<double>(c.to_host_ns(dev)),
              1.0);
}

TEST(RealSenseNodes, GroupsEachCamerasNodesByBusWithTheirMetadata) {
  std::vector<ProbedNode> n = {
      {"/dev/video0",
       0,
       "Intel(R) RealSense(TM) Depth Camera 435i Depth",
       "usb-0000:00:14.0-2",
       false,
       {v4l2::kZ16}},
      {"/dev/video1", 1, "Intel(R) RealSense(TM) Depth Camera 435i Depth", "usb-0000:00:14.0-2", true, {}},
      {"/dev/video2",
       2,
       "Intel(R) RealSense(TM) Depth Camera 435i Depth",
       "usb-0000:00:14.0-2",
       false,
       {v4l2::kGrey, kY8i}},
      {"/dev/video3", 3, "Intel(R) RealSense(TM) Depth Camera 435i Depth", "usb-0000:00:14.0-2", true, {}},
      {"/dev/video4",
       4,
       "Intel(R) RealSense(TM) Depth Camera 435i RGB",
       "usb-0000:00:14.0-2",
       false,
       {v4l2::kYuyv}},
      {"/dev/video5", 5, "Intel(R) RealSense(TM) Depth Camera 435i RGB", "usb-0000:00:14.0-2", true, {}},
      {"/dev/video6", 6, "HD Webcam", "usb-0000:00:14.0-5", false, {v4l2::kYuyv, v4l2::kMjpeg}},
      {"/dev/video8",
       8,
       "Intel(R) RealSense(TM) Depth Camera 455 RGB",
       "usb-0000:00:14.0-3",
       false,
       {v4l2::kYuyv}},
  };
  const std::vector<NodeSet> s = group_d4xx_nodes(n, kDefaultCardMatch);
  ASSERT_EQ(s.size(), 2u);
  EXPECT_EQ(s[0].depth, "/dev/video0");
  EXPECT_EQ(s[0].depth_meta, "/dev/video1");
  EXPECT_EQ(s[0].infrared, "/dev/video2");
  EXPECT_EQ(s[0].infrared_meta, "/dev/video3");
  EXPECT_EQ(s[0].color, "/dev/video4");
  EXPECT_EQ(s[0].color_meta, "/dev/video5");
  EXPECT_EQ(s[1].color, "/dev/video8");
  EXPECT_EQ(s[1].color_meta, "");  // no metadata node (kernel without it): kernel stamps
}

// ---- a short synthetic stream: pairing, fallbacks, faults ----------------------------------------
struct Small {
  FakeDevice dev;
  DeviceTime dt;
  static constexpr int kW = 8, kH = 6, kFrames = 120;
  static constexpr int64_t kPeriod = 33'333'333, kExposure = 4'000'000, kReadout = 10'000'000;
  std::vector<int64_t> t_mid;  // host truth per frame
  Small() {
    dev["/dev/video4"].format = video_format(kRgb24, kW, kH, 30, 3);
    dev["/dev/video5"].format = meta_format();
    dev["/dev/video0"].format = video_format(v4l2::kZ16, kW, kH, 30, 2);
    dev["/dev/video1"].format = meta_format();
    dev["/dev/video2"].format = video_format(kY8i, kW, kH, 30, 2);
    for (int i = 0; i < kFrames; ++i) {
      const int64_t t = 2'000'000'000 + i * kPeriod;
      t_mid.push_back(t);
      const int64_t lat = 150'000 + (i * 7919 % 500) * 1000;  // 150..650 us
      FakeBuf c;
      c.seq = static_cast<uint32_t>(i);
      c.bytes.assign(kW * kH * 3, static_cast<uint8_t>(i));
      c.t_ns = t + kExposure / 2 + kReadout + lat;  // uvcvideo's stamp: roughly when the frame began arriving
      dev["/dev/video4"].bufs.push_back(c);
      FakeBuf cm{frame_metadata(dt, t, kExposure, kReadout, lat, static_cast<uint32_t>(i), false),
                 static_cast<uint32_t>(i), v4l2::kBufFlagTimestampMonotonic, c.t_ns};
      dev["/dev/video5"].bufs.push_back(cm);
      FakeBuf d;
      d.seq = static_cast<uint32_t>(i);
      d.bytes.resize(kW * kH * 2);
      for (size_t k = 0; k < d.bytes.size(); k += 2) d.bytes[k] = static_cast<uint8_t>(i), d.bytes[k + 1] = 3;
      d.t_ns = c.t_ns + 100'000;
      dev["/dev/video0"].bufs.push_back(d);
      FakeBuf dm{frame_metadata(dt, t, kExposure, kReadout, lat + 100'000, static_cast<uint32_t>(i), true),
                 static_cast<uint32_t>(i), v4l2::kBufFlagTimestampMonotonic, d.t_ns};
      dev["/dev/video1"].bufs.push_back(dm);
      FakeBuf ir;
      ir.seq = static_cast<uint32_t>(i);
      ir.bytes.resize(kW * kH * 2);
      for (size_t k = 0; k < ir.bytes.size(); k += 2) ir.bytes[k] = 10, ir.bytes[k + 1] = 20;
      ir.t_ns = d.t_ns;
      dev["/dev/video2"].bufs.push_back(ir);
    }
    gate();
  }
  void gate() {
    dev["/dev/video5"].gate = &dev["/dev/video4"];
    dev["/dev/video1"].gate = &dev["/dev/video0"];
  }
  Options options() const {
    Options o;
    o.color = {true, "/dev/video4", "/dev/video5", {}};
    o.depth = {true, "/dev/video0", "/dev/video1", {}};
    return o;
  }
};

TEST(RealSenseD4xx, HardwareStampsPairDepthAndCountEveryFault) {
  Small s;
  // Faults: colour metadata of frames 30..32 never arrives; frame 50's is
  // corrupt; frame 60's metadata says the sensor timestamp is not valid;
  // colour frame 70 is lost (its metadata stays an orphan); depth frame 90 is lost.
  auto& cm = s.dev["/dev/video5"].bufs;
  cm.erase(cm.begin() + 30, cm.begin() + 33);
  auto at = [&](uint32_t seq) -> FakeBuf& {
    for (FakeBuf& b : cm)
      if (b.seq == seq) return b;
    throw std::runtime_error("no such metadata");
  };
  at(50).bytes[10] = 1;  // bLength 1
  {
    FrameMetadata m;
    ASSERT_EQ(parse_metadata_buffer(at(60).bytes.data(), at(60).bytes.size(), m), ParseStatus::kOk);
    m.timing.flags &= ~kTimingSensorTimestampValid;
    at(60).bytes.resize(512);
    at(60).bytes.resize(encode_record(m, EncodeOptions{}, at(60).bytes.data(), 512));
  }
  auto& cv = s.dev["/dev/video4"].bufs;
  cv.erase(cv.begin() + 70);
  auto& dv = s.dev["/dev/video0"].bufs;
  dv.erase(dv.begin() + 90);

  Camera cam(fake_factory(s.dev));
  Options o = s.options();
  o.clock.latency_floor_ns = 150'000;
  ASSERT_EQ(cam.open(o), "");
  Frame f;
  int frames = 0, with_depth = 0;
  double worst_hw_us = 0;
  while (cam.grab(10, f) == Camera::Result::kFrame) {
    ++frames;
    const uint32_t i = f.image_meta.seq;
    ASSERT_NE(f.image, nullptr);
    EXPECT_EQ(f.image->pixels[0], static_cast<uint8_t>(i));
    const bool fault = (i >= 30 && i <= 32) || i == 50 || i == 60;
    if (i > 0 && !fault) {
      EXPECT_EQ(f.image_meta.source, StampSource::kHardware) << i;
      worst_hw_us = std::max(worst_hw_us, std::abs(f.image_meta.t_ns - s.t_mid[i]) * 1e-3);
    }
    if (i >= 30 && i <= 32) {
      EXPECT_EQ(f.image_meta.source, StampSource::kKernelNoMetadata) << i;
    }
    if (i == 50) {
      EXPECT_EQ(f.image_meta.source, StampSource::kKernelCorrupt);
    }
    if (i == 60) {
      EXPECT_EQ(f.image_meta.source, StampSource::kKernelNoTimestamp);
    }
    if (fault) {
      // Kernel fallback: the buffer stamp is end-of-frame; minus readout and half the exposure.
      const int64_t expect =
          s.dev["/dev/video4"].bufs[i].t_ns / 1000 * 1000 - o.readout_ns - f.image_meta.exposure_us * 500;
      EXPECT_EQ(f.image_meta.t_ns, expect) << i;
    }
    if (f.depth != nullptr) {
      ++with_depth;
      EXPECT_EQ(f.depth_meta.seq, i);  // the partner is this frame's exposure
      EXPECT_EQ(f.depth->pixels[0], static_cast<uint8_t>(i));
      EXPECT_EQ(f.depth->format, PixelFormat::kDepthU16);
    } else {
      EXPECT_EQ(i, 90u);
    }
  }
  EXPECT_EQ(frames, Small::kFrames - 1);
  EXPECT_EQ(with_depth, Small::kFrames - 2);  // colour 70 and depth 90 have no partner
  // Hardware stamps: within the clock fit's error (its window is short here) and the us quantisation.
  EXPECT_LT(worst_hw_us, 150.0);
  const Counters c = cam.counters();
  EXPECT_EQ(c.color.frames, static_cast<uint64_t>(Small::kFrames - 1));
  EXPECT_EQ(c.color.dropped, 1u);
  EXPECT_EQ(c.color.metadata_missing, 3u);
  EXPECT_EQ(c.color.metadata_corrupt, 1u);
  EXPECT_EQ(c.color.metadata_no_timestamp, 1u);
  EXPECT_EQ(c.color.metadata_orphans, 1u);    // frame 70's metadata
  EXPECT_EQ(c.color.frame_counter_gaps, 3u);  // the counter jumps at 33 (30..32 unseen), 51 (50 corrupt), 71
  EXPECT_EQ(c.depth.dropped, 1u);
  EXPECT_EQ(c.unpaired, 1u);               // colour 90 (colour 70 never came)
  EXPECT_EQ(c.depth_skipped, 1u);          // depth 70: its colour frame was lost
  EXPECT_EQ(s.dev["/dev/video4"].out, 0);  // every buffer went back to the driver
  EXPECT_EQ(s.dev["/dev/video5"].out, 0);
  EXPECT_NE(cam.report().find("3 no metadata, 1 corrupt metadata"), std::string::npos) << cam.report();
}

TEST(RealSenseD4xx, UvchMetadataWithoutBlocksFallsBackLoudly) {
  // A kernel that offers only 'UVCH' cuts the header after PTS and SCR: no sensor timestamp.
  Small s;
  s.dev["/dev/video5"].format.fourcc = kMetaFmtUvc;
  for (FakeBuf& b : s.dev["/dev/video5"].bufs) {
    FrameMetadata m;
    ASSERT_EQ(parse_metadata_buffer(b.bytes.data(), b.bytes.size(), m), ParseStatus::kOk);
    EncodeOptions o;
    o.capture_timing = o.configuration = o.control = false;
    b.bytes.resize(512);
    b.bytes.resize(encode_record(m, o, b.bytes.data(), 512));
  }
  Camera cam(fake_factory(s.dev));
  ASSERT_EQ(cam.open(s.options()), "");
  Frame f;
  int n = 0;
  while (cam.grab(10, f) == Camera::Result::kFrame) {
    EXPECT_EQ(f.image_meta.source, StampSource::kKernelNoTimestamp);
    EXPECT_EQ(f.image_meta.metadata_status, ParseStatus::kNoD4xxBlocks);
    ++n;
  }
  EXPECT_EQ(n, Small::kFrames);
  EXPECT_EQ(cam.counters().color.metadata_no_timestamp, static_cast<uint64_t>(Small::kFrames));
  EXPECT_EQ(cam.counters().color.hardware_stamps, 0u);
  EXPECT_NE(cam.report().find("D4xx color (metadata UVCH (no D4xx blocks: kernel stamps))"),
            std::string::npos)
      << cam.report();
}

TEST(RealSenseD4xx, InfraredY8iSplitsTheImagersAndCanBeTheImage) {
  Small s;
  Camera cam(fake_factory(s.dev));
  Options o;
  o.infrared = {true, "/dev/video2", "", {}};
  o.depth = {true, "/dev/video0", "/dev/video1", {}};
  o.infrared_is_image = true;
  ASSERT_EQ(cam.open(o), "");
  Frame f;
  ASSERT_EQ(cam.grab(10, f), Camera::Result::kFrame);
  ASSERT_NE(f.image, nullptr);
  ASSERT_NE(f.ir2, nullptr);
  EXPECT_EQ(f.image->format, PixelFormat::kGray8);
  EXPECT_EQ(f.image->pixels[0], 10);  // left imager: the low byte
  EXPECT_EQ(f.ir2->pixels[0], 20);
  EXPECT_EQ(f.image_meta.source, StampSource::kKernelNoMetadata);  // no metadata node configured
  EXPECT_NE(f.depth, nullptr);
  // Missing nodes are named.
  Camera bad(fake_factory(s.dev));
  Options b = s.options();
  b.color.meta_device = "/dev/video9";
  EXPECT_EQ(bad.open(b), "D4xx color metadata: /dev/video9: No such file or directory");
  b = s.options();
  b.depth.video_device = "/dev/video5";  // a metadata node where a video node belongs
  EXPECT_EQ(bad.open(b), "D4xx depth: /dev/video5: wrong node kind");
}

TEST(RealSenseD4xx, DepthIsRegisteredToColourWithTheRigsExtrinsic) {
  Small s;
  // A wide baseline: the registered image is DepthRegistration's output for the same input, not a copy.
  Options o = s.options();
  CameraIntrinsics k;
  k.width = Small::kW;
  k.height = Small::kH;
  k.fx = k.fy = 6;
  k.cx = 3.5;
  k.cy = 2.5;
  o.image_camera = k;
  o.depth_camera.present = true;
  o.depth_camera.intrinsics = k;
  o.depth_camera.T_CD = {1, 0, 0, 0.3, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};  // ~2 px of disparity at 0.77 m
  Camera cam(fake_factory(s.dev));
  ASSERT_EQ(cam.open(o), "");
  Frame f;
  ASSERT_EQ(cam.grab(10, f), Camera::Result::kFrame);
  ASSERT_NE(f.depth, nullptr);
  DepthRegistration reg(o.depth_camera, k, 0.001);
  std::vector<uint16_t> raw(Small::kW * Small::kH), expect(Small::kW * Small::kH);
  std::memcpy(raw.data(), s.dev["/dev/video0"].bufs[0].bytes.data(), raw.size() * 2);
  ASSERT_TRUE(reg.register_into(ImageView{Small::kW, Small::kH, Small::kW * 2, PixelFormat::kDepthU16,
                                          reinterpret_cast<const uint8_t*>(raw.data())},
                                expect.data(), Small::kW * 2));
  EXPECT_EQ(std::memcmp(f.depth->pixels.data(), expect.data(), expect.size() * 2), 0);
  EXPECT_NE(std::memcmp(f.depth->pixels.data(), raw.data(), raw.size() * 2), 0);
}

TEST(RealSenseD4xx, SteadyStateAllocatesNothing) {
  if (!rt::alloc_hook_linked()) GTEST_FAIL() << "the allocation hook is not linked: this test cannot count";
  Small s;
  Camera cam(fake_factory(s.dev));
  ASSERT_EQ(cam.open(s.options()), "");
  Frame f;
  for (int i = 0; i < 5; ++i) ASSERT_EQ(cam.grab(10, f), Camera::Result::kFrame);  // warm-up
  const uint64_t before = rt::alloc_count_this_thread();
  for (int i = 0; i < 100; ++i) ASSERT_EQ(cam.grab(10, f), Camera::Result::kFrame);
  EXPECT_EQ(rt::alloc_count_this_thread() - before, 0u);
}

// ---- live config ----------------------------------------------------------------------------------
TEST(RealSenseConfig, TemplatesParseAndKeysHaveTheirDefaults) {
  const std::string dir = std::string(KESTREL_SOURCE_DIR) + "/configs/";
  for (const char* f : {"realsense_d435i.yaml", "realsense_d455.yaml"}) {
    const LiveConfig c = kestrel::tools::load_live_config(dir + f);
    EXPECT_EQ(c.drivers.camera.type, CameraType::kD4xx) << f;
    EXPECT_TRUE(c.rig.depth_camera.present) << f;
    EXPECT_EQ(c.drivers.camera.d4xx.card_match, "RealSense");
    EXPECT_EQ(c.drivers.camera.d4xx.image, "color");
    EXPECT_TRUE(c.drivers.camera.d4xx.depth);
    EXPECT_EQ(c.rig.time_offset_cam_imu_ns, 0);
  }
  const std::string rig =
      "rig:\n  camera: {width_px: 640, height_px: 480, fx_px: 500, fy_px: 500, cx_px: 320, cy_px: 240}\n";
  const LiveConfig d =
      kestrel::tools::live_config_from_yaml(rig + "drivers:\n  camera: {type: d4xx}\n", "x.yaml");
  const CameraSettings::D4xx& x = d.drivers.camera.d4xx;
  EXPECT_EQ(x.infrared, "off");
  EXPECT_EQ(x.metadata_wait_ms, 2);
  EXPECT_EQ(x.buffers, 4);
  EXPECT_DOUBLE_EQ(x.depth_unit_m, 0.001);
  EXPECT_EQ(x.pair_tolerance_ns, 0);
  const LiveConfig e =
      kestrel::tools::live_config_from_yaml(rig +
                                                "drivers:\n  camera:\n    type: d4xx\n    d4xx: {image: "
                                                "infrared1, infrared: y8i, pair_tolerance_us: 500, "
                                                "color_meta_device: none, depth_device: /dev/video0}\n",
                                            "x.yaml");
  EXPECT_EQ(e.drivers.camera.d4xx.pair_tolerance_ns, 500'000);
  EXPECT_EQ(e.drivers.camera.d4xx.color_meta_device, "none");
  EXPECT_EQ(e.drivers.camera.d4xx.depth_device, "/dev/video0");
  auto error = [&](const std::string& d4xx) {
    try {
      kestrel::tools::live_config_from_yaml(
          rig + "drivers:\n  camera:\n    type: d4xx\n    d4xx: " + d4xx + "\n", "x.yaml");
    } catch (const std::runtime_error& err) {
      return std::string(err.what());
    }
    return std::string("(no error)");
  };
  EXPECT_NE(error("{image: infrared1}").find("x.yaml: drivers.camera.d4xx.infrared: must be y8 or y8i"),
            std::string::npos)
      << error("{image: infrared1}");
  // Without the device: LiveSensors names the stream and the node.
  const LiveConfig none = kestrel::tools::live_config_from_yaml(
      rig +
          "drivers:\n  camera:\n    type: d4xx\n    d4xx: {color_device: /dev/kestrel-no-such-video, "
          "color_meta_device: none, depth: false}\n",
      "x.yaml");
  try {
    LiveSensors live(none);
    ADD_FAILURE() << "opened a camera that does not exist";
  } catch (const std::runtime_error& err) {
    const std::string want =
        "camera (RealSense D4xx): D4xx color: /dev/kestrel-no-such-video: No such file or directory";
    EXPECT_NE(std::string(err.what()).find(want), std::string::npos) << err.what();
  }
  EXPECT_NE(error("{metadata_wait: 2}").find("metadata_wait"),
            std::string::npos);  // a unit-less key is refused
  EXPECT_NE(error("{infrared: both}").find("drivers.camera.d4xx.infrared"), std::string::npos);
}

}  // namespace
}  // namespace kestrel::drivers::d4xx

// The live rig configs: both shipped files parse (rig part through the rig
// schema), errors name file and key, and opening sensors that are not there
// fails with a message naming each one.
#include <gtest/gtest.h>

#include <string>

#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/tools/config_file.hpp"

namespace kestrel::drivers {
namespace {

const std::string kConfigs = std::string(KESTREL_SOURCE_DIR) + "/configs/";

TEST(LiveConfig, ShippedConfigsParse) {
  const LiveConfig a = kestrel::tools::load_live_config(kConfigs + "openni2_bmx055_i2c.yaml");
  EXPECT_EQ(a.drivers.camera.type, CameraType::kOpenNi2);
  EXPECT_EQ(a.drivers.imu.type, ImuType::kBmx055I2c);
  EXPECT_EQ(a.drivers.imu.bmx055.drdy, bmx055::DataReadyMode::kGpio);
  EXPECT_EQ(a.drivers.imu.gpio_line, 17);
  EXPECT_EQ(a.drivers.imu.bmx055.gyro_bw, bmx055::gyro::Bandwidth::k400Hz_47Hz);
  EXPECT_EQ(a.rig.imu_rate_hz, 400);
  const LiveConfig b = kestrel::tools::load_live_config(kConfigs + "realsense_v4l2_bmx055_usb.yaml");
  EXPECT_EQ(b.drivers.camera.type, CameraType::kV4l2);
  EXPECT_EQ(b.drivers.camera.v4l2_depth_format, "z16");
  EXPECT_EQ(b.drivers.imu.type, ImuType::kBmx055Usb);
  EXPECT_EQ(b.drivers.imu.usb.vid, 0x1209);
  EXPECT_EQ(b.drivers.imu.usb.clock.latency_floor_ns, 125'000);
  EXPECT_TRUE(b.drivers.strobe.enabled);
  EXPECT_EQ(b.drivers.strobe.initial_offset_ns, 33'000'000);
  // The shipped live rigs name their backend: one each of the small-board EKF and the window optimizer.
  EXPECT_EQ(kestrel::tools::load_config(kConfigs + "openni2_bmx055_i2c.yaml").estimator.backend, "ekf");
  EXPECT_EQ(kestrel::tools::load_config(kConfigs + "realsense_v4l2_bmx055_usb.yaml").estimator.backend,
            "window");
}

std::string with_drivers(const std::string& drivers) {
  return "rig:\n  camera: {width_px: 640, height_px: 480, fx_px: 500, fy_px: 500, cx_px: 320, cy_px: 240}\n"
         "drivers:\n" +
         drivers;
}

void expect_error(const std::string& text, const std::string& needle) {
  try {
    kestrel::tools::live_config_from_yaml(text, "x.yaml");
    ADD_FAILURE() << "no error for " << text;
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    EXPECT_EQ(std::string(e.what()).rfind("x.yaml", 0), 0u) << e.what();
  }
}

// Live stereo (docs/stereo.md, "Live stereo"): the V4L2 keys, and which
// camera settings can deliver a stereo rig's right image.
TEST(LiveConfig, StereoCameraSettingsAndTheirCapability) {
  const LiveConfig sbs = kestrel::tools::live_config_from_yaml(
      with_drivers(
          "  camera: {type: v4l2, v4l2: {color_device: /dev/video0, color_format: grey, stereo_layout: "
          "side_by_side}}\n"),
      "x.yaml");
  EXPECT_EQ(sbs.drivers.camera.v4l2_stereo_layout, "side_by_side");
  EXPECT_EQ(stereo_capability(sbs.drivers.camera), "");
  const LiveConfig two = kestrel::tools::live_config_from_yaml(
      with_drivers("  camera: {type: v4l2, v4l2: {color_device: /dev/video0, right_device: /dev/video2}}\n"),
      "x.yaml");
  EXPECT_EQ(two.drivers.camera.v4l2_right_device, "/dev/video2");
  EXPECT_EQ(stereo_capability(two.drivers.camera), "");
  const LiveConfig mono = kestrel::tools::live_config_from_yaml(
      with_drivers("  camera: {type: v4l2, v4l2: {color_device: /dev/video0}}\n"), "x.yaml");
  EXPECT_NE(stereo_capability(mono.drivers.camera).find("right_device or stereo_layout"), std::string::npos);
  const LiveConfig ir = kestrel::tools::live_config_from_yaml(
      with_drivers("  camera: {type: d4xx, d4xx: {image: infrared1, infrared: y8i, depth: false}}\n"),
      "x.yaml");
  EXPECT_EQ(stereo_capability(ir.drivers.camera), "");
  const LiveConfig ir1 = kestrel::tools::live_config_from_yaml(
      with_drivers("  camera: {type: d4xx, d4xx: {image: infrared1, infrared: y8}}\n"), "x.yaml");
  EXPECT_NE(stereo_capability(ir1.drivers.camera).find("infrared: y8i"), std::string::npos);
  expect_error(
      with_drivers("  camera: {type: v4l2, v4l2: {color_device: /dev/video0, right_device: /dev/video2, "
                   "stereo_layout: side_by_side}}\n"),
      "drivers.camera.v4l2.stereo_layout: side_by_side and right_device exclude each other");
  expect_error(
      with_drivers("  camera: {type: v4l2, v4l2: {color_device: /dev/video0, stereo_layout: top_bottom}}\n"),
      "drivers.camera.v4l2.stereo_layout");
}

TEST(LiveConfig, ASideBySideFrameSplitsIntoItsTwoHalvesWithoutAllocating) {
  ImageBuffer in, left, right;
  in.width = 8;
  in.height = 3;
  in.format = PixelFormat::kGray8;
  in.t_ns = 42;
  for (int y = 0; y < 3; ++y)
    for (int x = 0; x < 8; ++x) in.pixels.push_back(static_cast<uint8_t>(10 * y + x));
  left.pixels.reserve(12);
  right.pixels.reserve(12);
  ASSERT_TRUE(rt::alloc_hook_linked());
  {
    rt::AllocCountScope scope;
    ASSERT_TRUE(split_side_by_side(in, left, right));
    EXPECT_EQ(scope.count(), 0u);
  }
  EXPECT_EQ(left.width, 4);
  EXPECT_EQ(right.height, 3);
  EXPECT_EQ(right.t_ns, 42);
  EXPECT_EQ(left.pixels[4], 10);   // row 1, x 0
  EXPECT_EQ(right.pixels[4], 14);  // row 1, x 4
  EXPECT_EQ(right.pixels[11], 27);
  in.width = 7;  // odd: no halves
  EXPECT_FALSE(split_side_by_side(in, left, right));
  in.width = 8;
  ImageBuffer small;
  small.pixels.reserve(4);
  EXPECT_FALSE(split_side_by_side(in, small, right)) << "a half larger than its buffer must not allocate";
}

TEST(LiveConfig, ErrorsNameFileAndKey) {
  expect_error(with_drivers("  imu: {type: bmx055_i2c, acc_range_g: 3, i2c: {bus_device: /dev/i2c-1}}\n"),
               "drivers.imu.acc_range_g: expected one of 2, 4, 8, 16");
  expect_error(with_drivers("  imu: {type: bmx055_i2c, gyro_odr_hz: 400, gyro_bandwidth_hz: 116}\n"),
               "drivers.imu.gyro_odr_hz");
  expect_error(with_drivers("  imu: {type: bmx055_i2c, i2c: {bus_device: /dev/i2c-1, poll_period: 5}}\n"),
               "drivers.imu.i2c.poll_period: unknown key");
  expect_error(
      with_drivers("  imu: {type: bmx055_i2c, axis_remap: [+x, +x, +z], i2c: {bus_device: /dev/i2c-1}}\n"),
      "axis_remap");
  expect_error(with_drivers("  camera: {type: v4l2}\n"), "drivers.camera.v4l2.color_device: missing");
  expect_error(with_drivers("  camera: {type: kinect}\n"),
               "drivers.camera.type: expected one of none, openni2, v4l2");
  expect_error(with_drivers("  imu: {type: bmx055_i2c, i2c: {bus_device: /dev/i2c-1, acc_i2c_addr: 0x20}}\n"),
               "drivers.imu.i2c.acc_i2c_addr: must be in 24..25");
  expect_error("rig:\n  camera: {width_px: 640, height_px: 480, fx: 500}\ndrivers: {}\n", "rig.camera.fx");
  expect_error(with_drivers("  camera: {type: none}\n") + "extra: 1\n", "extra: unknown section");
}

TEST(LiveConfig, EstimatorSectionsAreTheEstimatorReadersAndChecked) {
  const auto backend = [](const std::string& text) {
    return kestrel::tools::config_from_yaml(text, "x.yaml").estimator.backend;
  };
  EXPECT_EQ(backend(with_drivers("  camera: {type: none}\n")), "auto");  // the command line's default
  EXPECT_EQ(backend(with_drivers("  camera: {type: none}\n") + "estimator: {backend: vo}\n"), "vo");
  // The estimator's sections are read by tools/config against core's options table, key by key.
  EXPECT_NO_THROW(backend(with_drivers("  camera: {type: none}\n") + "window: {recent_frames: 3}\n"));
  expect_error(with_drivers("  camera: {type: none}\n") + "window: {recent_framez: 3}\n",
               "window.recent_framez: unknown key");
  expect_error(with_drivers("  camera: {type: none}\n") + "estimator: ekf\n",
               "estimator: expected a mapping");
  expect_error(with_drivers("  camera: {type: none}\n") + "estimator: {backend: nope}\n",
               "estimator.backend: unknown backend 'nope'");
}

TEST(ThreadTable, AbsentSectionIsTheBuiltInDefaults) {
  const ThreadTable t =
      kestrel::tools::live_config_from_yaml(with_drivers("  camera: {type: none}\n"), "x.yaml").threads;
  const ThreadTable d = default_thread_table();
  EXPECT_FALSE(t.from_config);
  for (int i = 0; i < kPipelineThreads; ++i) {
    EXPECT_STREQ(t.spec[i].name, d.spec[i].name);
    EXPECT_EQ(t.spec[i].priority, d.spec[i].priority) << d.spec[i].name;
    EXPECT_EQ(t.spec[i].cpu, d.spec[i].cpu) << d.spec[i].name;
  }
  EXPECT_EQ(d[PipelineThread::kPropagate].priority, 60);  // the one FIFO thread of the replay harness
  EXPECT_EQ(d[PipelineThread::kEstimator].priority, 0);
}

TEST(ThreadTable, SectionParsesAndLeavesUnnamedThreadsAtTheirDefaults) {
  const ThreadTable t =
      kestrel::tools::live_config_from_yaml(with_drivers("  camera: {type: none}\n") +
                                                "threads:\n"
                                                "  kst-imu: {cpu: 1, policy: fifo, priority: 80}\n"
                                                "  kst-optimizer: {cpu: -1, policy: other}\n"
                                                "  kst-propagate: {cpu: 0}\n"
                                                "  kst-log: {cpu: 1, policy: other}\n",
                                            "x.yaml")
          .threads;
  EXPECT_TRUE(t.from_config);
  EXPECT_EQ(t[PipelineThread::kImu].cpu, 1);
  EXPECT_EQ(t[PipelineThread::kImu].priority, 80);
  EXPECT_EQ(t[PipelineThread::kOptimizer].priority, 0);
  EXPECT_EQ(t[PipelineThread::kOptimizer].cpu, -1);
  // Policy absent: the default policy and priority stay, only the CPU changes.
  EXPECT_EQ(t[PipelineThread::kPropagate].cpu, 0);
  EXPECT_EQ(t[PipelineThread::kPropagate].priority, 60);
  EXPECT_EQ(t[PipelineThread::kCamera].cpu, default_thread_table()[PipelineThread::kCamera].cpu);
  EXPECT_EQ(t[PipelineThread::kLog].cpu, 1);
  EXPECT_EQ(t[PipelineThread::kLog].priority, 0);
  EXPECT_STREQ(t[PipelineThread::kLog].name, "kst-log");
  // A replay config may hold the table alone (configs/replay_devbox.yaml); a
  // rig file holds the rig only, and says where the table goes.
  const ThreadTable dev = kestrel::tools::load_config(kConfigs + "replay_devbox.yaml").threads;
  EXPECT_TRUE(dev.from_config);
  EXPECT_EQ(dev[PipelineThread::kPropagate].priority, 60);
  EXPECT_NO_THROW(load_rig_file(kConfigs + "sim_rgbd_bmx055.yaml"));
  try {
    (void)rig_from_yaml(rig_to_yaml(Rig{}) + "threads: {kst-imu: {cpu: 1}}\n", "r.yaml");
    ADD_FAILURE() << "a rig file with threads: was accepted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("r.yaml: threads: belongs in a config file"), std::string::npos)
        << e.what();
  }
  // Both live rigs ship a table: the IMU driver outranks everything.
  for (const char* f : {"openni2_bmx055_i2c.yaml", "realsense_v4l2_bmx055_usb.yaml"}) {
    const ThreadTable l = kestrel::tools::load_live_config(kConfigs + f).threads;
    EXPECT_TRUE(l.from_config) << f;
    for (int i = 0; i < kPipelineThreads; ++i)
      EXPECT_LE(l.spec[i].priority, l[PipelineThread::kImu].priority) << f << " " << l.spec[i].name;
  }
}

TEST(ThreadTable, BadFieldsAndUnknownNamesAreErrorsNamingFileAndField) {
  const std::string base = with_drivers("  camera: {type: none}\n");
  expect_error(base + "threads:\n  kst-optimizer: {policy: fifo, priority: 120}\n",
               "x.yaml: threads.kst-optimizer.priority: expected 1..99");
  expect_error(base + "threads:\n  kst-optimizer: {policy: fifo, priority: 0}\n",
               "threads.kst-optimizer.priority: expected 1..99");
  expect_error(base + "threads:\n  kst-optimizer: {policy: fifo}\n",
               "threads.kst-optimizer.priority: missing");
  expect_error(base + "threads:\n  kst-imu: {policy: rr, priority: 5}\n",
               "threads.kst-imu.policy: expected one of fifo, other");
  expect_error(base + "threads:\n  kst-imu: {policy: other, priority: 5}\n", "threads.kst-imu.priority");
  expect_error(base + "threads:\n  kst-cam: {cpu: two}\n", "threads.kst-cam.cpu: expected an integer");
  expect_error(base + "threads:\n  kst-cam: {cpu: -2}\n", "threads.kst-cam.cpu: must be in -1..1023");
  expect_error(base + "threads:\n  kst-cam: {cpu: 0, nice: 3}\n", "threads.kst-cam.nice: unknown key");
  expect_error(base + "threads: [kst-imu]\n", "threads: expected a mapping");
  // Unknown thread names list the known ones.
  expect_error(base + "threads:\n  kst-track: {cpu: 0}\n",
               "threads.kst-track: unknown thread (expected one of: " + thread_names() + ")");
  EXPECT_NE(thread_names().find("kst-propagate"), std::string::npos);
  // Inside a live config's rig section the key stays unknown.
  expect_error(
      "rig:\n  camera: {width_px: 640, height_px: 480, fx_px: 500, fy_px: 500, cx_px: 320, cy_px: 240}\n"
      "  threads: {}\ndrivers: {camera: {type: none}}\n",
      "rig.threads: unknown key");
}

TEST(LiveSensors, MissingHardwareIsNamed) {
  LiveConfig c = kestrel::tools::live_config_from_yaml(
      with_drivers("  camera:\n    type: v4l2\n    v4l2: {color_device: /dev/video-kestrel-none}\n"
                   "  imu:\n    type: bmx055_i2c\n    i2c: {bus_device: /dev/i2c-kestrel-none}\n"),
      "test.yaml");
  try {
    LiveSensors s(c);
    FAIL() << "opened sensors that do not exist";
  } catch (const std::runtime_error& e) {
    const std::string m = e.what();
    EXPECT_NE(m.find("test.yaml"), std::string::npos) << m;
    EXPECT_NE(m.find("/dev/video-kestrel-none"), std::string::npos) << m;
    EXPECT_NE(m.find("/dev/i2c-kestrel-none"), std::string::npos) << m;
    EXPECT_NE(m.find("drivers in this build"), std::string::npos) << m;
    std::printf("%s\n", m.c_str());
  }
}

TEST(Devices, ProbeNeverThrows) {
  const DeviceReport r = probe_devices();
  std::printf("built: %s\nfound %zu device(s)\n", built_drivers_summary().c_str(), r.found.size());
  for (const auto& n : r.notes) std::printf("note: %s\n", n.c_str());
  SUCCEED();
}

}  // namespace
}  // namespace kestrel::drivers

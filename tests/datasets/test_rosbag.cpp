// ROS 1 bags: bags written here with the rosbag API, the export round trip,
// truncated and mistyped input.
#include <gtest/gtest.h>
#include <rosbag/bag.h>
#include <sensor_msgs/CameraInfo.h>
#include <sensor_msgs/Image.h>
#include <sensor_msgs/Imu.h>
#include <std_msgs/String.h>

#include <cstring>
#include <filesystem>

#include "dataset_fixtures.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_export.hpp"
#include "kestrel/drivers/open_log.hpp"

namespace kestrel::test {
namespace {

using drivers::RecordType;

ros::Time stamp(int64_t t_ns) {
  return ros::Time(static_cast<uint32_t>(t_ns / 1000000000), t_ns % 1000000000);
}

sensor_msgs::Image image_msg(int64_t t_ns, const std::string& enc, int bpp) {
  sensor_msgs::Image m;
  m.header.stamp = stamp(t_ns);
  m.width = 4;
  m.height = 3;
  m.encoding = enc;
  m.step = 4 * bpp + 2;  // row padding, as some drivers send
  m.data.assign(m.step * m.height, 0);
  for (size_t i = 0; i < m.data.size(); ++i) m.data[i] = static_cast<uint8_t>(i * 3 + 1);
  return m;
}

// A D435i-like bag: IMU at 200 Hz, colour (rgb8, then bgr8, then mono8) and 16UC1 / 32FC1 depth at 10 Hz.
void write_d435i_bag(const std::string& path, bool camera_info = true, bool stray_type = false,
                     rosbag::compression::CompressionType compression = rosbag::compression::Uncompressed) {
  rosbag::Bag bag(path, rosbag::bagmode::Write);
  bag.setCompression(compression);
  const int64_t t0 = 1'600'000'000'000'000'000;
  for (int i = 0; i < 60; ++i) {
    const int64_t t = t0 + int64_t{i} * 5'000'000;
    sensor_msgs::Imu m;
    m.header.stamp = stamp(t);
    m.angular_velocity.x = 0.001 * i;
    m.linear_acceleration.z = 9.81;
    bag.write("/camera/imu", stamp(t + 1'000'000), m);  // received 1 ms later
    if (i % 20 == 0) {
      const int k = i / 20;
      const char* enc = k == 0 ? "rgb8" : k == 1 ? "bgr8" : "mono8";
      bag.write("/camera/color/image_raw", stamp(t), image_msg(t, enc, k == 2 ? 1 : 3));
      // Depth stamped 3 ms after colour: associated, and carried on the colour stamp.
      sensor_msgs::Image d = image_msg(t + 3'000'000, k == 1 ? "32FC1" : "16UC1", k == 1 ? 4 : 2);
      if (k == 1) {
        for (uint32_t p = 0; p < 12; ++p) {
          const float v = p == 5 ? std::nanf("") : 0.5f + 0.25f * static_cast<float>(p);
          std::memcpy(d.data.data() + (p / 4) * d.step + (p % 4) * 4, &v, 4);
        }
      }
      bag.write("/camera/aligned_depth_to_color/image_raw", stamp(t + 3'000'000), d);
      if (camera_info) {
        sensor_msgs::CameraInfo ci;
        ci.header.stamp = stamp(t);
        ci.width = 4;
        ci.height = 3;
        ci.K = {610.5, 0, 2.25, 0, 611.25, 1.5, 0, 0, 1};
        ci.distortion_model = "plumb_bob";
        ci.D = {0.1, -0.05, 0.001, 0.002, 0.0};
        bag.write("/camera/color/camera_info", stamp(t), ci);
      }
    }
  }
  if (stray_type) {
    std_msgs::String s;
    s.data = "not an IMU";
    // On the IMU topic the bag reuses the Imu connection, so this is an Imu record with a String
    // payload (a damaged message); on its own topic it is a well-formed message of the wrong type.
    bag.write("/camera/imu", stamp(t0 + 400'000'000), s);
    bag.write("/string", stamp(t0 + 400'000'000), s);
  }
  bag.close();
}

TEST(RosbagReader, ReadsImuImagesAndCameraInfo) {
  ASSERT_TRUE(drivers::rosbag_built());
  const std::string dir = temp_dir("rosbag_read");
  write_d435i_bag(dir + "/d435i.bag");
  ASSERT_TRUE(drivers::is_rosbag_file(dir + "/d435i.bag"));
  auto log = drivers::open_log(dir + "/d435i.bag");
  ASSERT_EQ(log->format_name(), "rosbag");
  const Rig& r = log->rig();
  EXPECT_EQ(r.rgb.fx, 610.5);
  EXPECT_EQ(r.rgb.cy, 1.5);
  EXPECT_EQ(r.rgb.width, 4);
  EXPECT_EQ(r.rgb.distortion, DistortionModel::kRadTan);
  EXPECT_EQ(r.rgb.dist[3], 0.002);
  EXPECT_EQ(r.depth.scale_m_per_unit, 0.001);
  EXPECT_TRUE(has_problem(*log, "assumed", "/camera/imu"));

  const auto all = read_all(*log);
  const auto imu = of_type(all, RecordType::kImu);
  ASSERT_EQ(imu.size(), 60u);
  EXPECT_EQ(imu[7].imu.gyro_rps[0], 0.007);
  EXPECT_EQ(imu[7].imu.t_recv_ns - imu[7].imu.t_ns, 1'000'000) << "bag time is the receive time";
  const auto rgb = of_type(all, RecordType::kRgb), depth = of_type(all, RecordType::kDepth);
  ASSERT_EQ(rgb.size(), 3u);
  ASSERT_EQ(depth.size(), 3u);
  EXPECT_EQ(rgb[0].image.format, PixelFormat::kRgb8);
  EXPECT_EQ(rgb[1].image.format, PixelFormat::kBgr8);
  EXPECT_EQ(rgb[2].image.format, PixelFormat::kGray8);
  // Row padding removed: row 1 starts at byte step = 14 of the message.
  EXPECT_EQ(rgb[0].image.pixels[12], static_cast<uint8_t>(14 * 3 + 1));
  EXPECT_EQ(depth[0].image.t_ns, rgb[0].image.t_ns);
  EXPECT_EQ(depth[0].image.t_recv_ns - depth[0].image.t_ns, 3'000'000);
  uint16_t v;
  std::memcpy(&v, depth[1].image.pixels.data() + 2 * 2, 2);
  EXPECT_EQ(v, 1000) << "32FC1 metres become millimetres";
  std::memcpy(&v, depth[1].image.pixels.data() + 2 * 5, 2);
  EXPECT_EQ(v, 0) << "NaN depth is invalid";
}

TEST(RosbagReader, ReadsCompressedBags) {
  ASSERT_TRUE(drivers::rosbag_built());
  const std::string dir = temp_dir("rosbag_compressed");
  for (const auto c : {rosbag::compression::BZ2, rosbag::compression::LZ4}) {
    write_d435i_bag(dir + "/c.bag", true, false, c);
    drivers::RosbagReader log(dir + "/c.bag");
    const auto all = read_all(log);
    EXPECT_EQ(of_type(all, RecordType::kImu).size(), 60u);
    ASSERT_EQ(of_type(all, RecordType::kRgb).size(), 3u);
    EXPECT_EQ(of_type(all, RecordType::kRgb)[0].image.pixels[12], static_cast<uint8_t>(14 * 3 + 1));
  }
}

TEST(RosbagReader, MissingCameraInfoNamesTheFieldOrTakesTheRig) {
  ASSERT_TRUE(drivers::rosbag_built());
  const std::string dir = temp_dir("rosbag_noinfo");
  write_d435i_bag(dir + "/x.bag", false);
  try {
    drivers::RosbagReader log(dir + "/x.bag");
    FAIL() << "expected an error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("CameraInfo"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("intrinsics"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("--rig"), std::string::npos) << e.what();
  }
  const Rig rig = small_rig();
  drivers::RosbagReader log(dir + "/x.bag", {}, &rig);
  EXPECT_EQ(log.rig().rgb.fx, rig.rgb.fx);
  EXPECT_EQ(log.rig().T_BC, rig.T_BC);
}

TEST(RosbagReader, TruncatedBagIsAClearErrorNotACrash) {
  ASSERT_TRUE(drivers::rosbag_built());
  const std::string dir = temp_dir("rosbag_truncated");
  write_d435i_bag(dir + "/full.bag");
  const auto size = std::filesystem::file_size(dir + "/full.bag");
  for (const double frac : {0.0, 0.001, 0.01, 0.3, 0.7, 0.99}) {
    std::filesystem::copy_file(dir + "/full.bag", dir + "/cut.bag",
                               std::filesystem::copy_options::overwrite_existing);
    std::filesystem::resize_file(dir + "/cut.bag", static_cast<uintmax_t>(static_cast<double>(size) * frac));
    try {
      drivers::RosbagReader log(dir + "/cut.bag");
      read_all(log);  // if the index survived, reading must still be safe
      ADD_FAILURE() << "a bag cut at " << frac << " opened without an error";
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find("cut.bag"), std::string::npos) << e.what();
    }
  }
}

TEST(RosbagReader, DamagedOrMistypedMessagesAreSkippedAndCounted) {
  ASSERT_TRUE(drivers::rosbag_built());
  const std::string dir = temp_dir("rosbag_type");
  write_d435i_bag(dir + "/x.bag", true, true);
  drivers::RosbagReader log(dir + "/x.bag");
  EXPECT_EQ(of_type(read_all(log), RecordType::kImu).size(), 60u);
  EXPECT_TRUE(has_problem(log, "bad-payload", "/camera/imu#")) << problems_text(log);
  drivers::RosbagTopics t;
  t.imu = "/string";
  drivers::RosbagReader wrong(dir + "/x.bag", t);
  EXPECT_EQ(of_type(read_all(wrong), RecordType::kImu).size(), 0u);
  EXPECT_TRUE(has_problem(wrong, "bad-type", "/string#")) << problems_text(wrong);
}

TEST(RosbagExport, KlogToBagToKlogKeepsWhatTheFormatHolds) {
  ASSERT_TRUE(drivers::rosbag_built());
  const std::string dir = temp_dir("rosbag_roundtrip");
  write_small_klog(dir + "/a.klog", small_rig(), 10, PixelFormat::kBgr8);
  drivers::KlogReader a(dir + "/a.klog");
  const auto st = drivers::export_rosbag(a, dir + "/a.bag");
  EXPECT_EQ(st.imu, 200u);
  EXPECT_EQ(st.rgb, 10u);
  const Rig rig = a.rig();
  drivers::RosbagReader b(dir + "/a.bag", {}, &rig);
  EXPECT_EQ(b.rig().rgb.fx, rig.rgb.fx);
  EXPECT_EQ(b.rig().rgb.cy, rig.rgb.cy);
  const auto x = read_all(a), y = read_all(b);
  ASSERT_EQ(x.size(), y.size()) << problems_text(b);
  for (size_t i = 0; i < x.size(); ++i) {
    ASSERT_EQ(x[i].type, y[i].type) << i;
    switch (x[i].type) {
      case RecordType::kImu:
        EXPECT_EQ(x[i].imu.t_ns, y[i].imu.t_ns);
        EXPECT_EQ(x[i].imu.gyro_rps, y[i].imu.gyro_rps);
        EXPECT_EQ(x[i].imu.acc_mps2, y[i].imu.acc_mps2);
        break;
      case RecordType::kGroundTruth:
        EXPECT_EQ(x[i].gt.t_ns, y[i].gt.t_ns);
        EXPECT_EQ(x[i].gt.p_WB, y[i].gt.p_WB);
        EXPECT_EQ(x[i].gt.q_WB, y[i].gt.q_WB);
        break;
      default:
        EXPECT_EQ(x[i].image.t_ns, y[i].image.t_ns);
        EXPECT_EQ(x[i].image.format, y[i].image.format);
        EXPECT_EQ(x[i].image.pixels, y[i].image.pixels);
    }
  }
}

// A stereo log through a ROS 1 bag: the right images on their own topic with a
// CameraInfo whose P carries the baseline; read back with --right-topic, the
// pair is stereo again (the right camera placed by that baseline, said), each
// right image with its left one's stamp and pixels unchanged.
TEST(RosbagExport, AStereoLogKeepsItsRightImagesAndBaseline) {
  ASSERT_TRUE(drivers::rosbag_built());
  const std::string dir = temp_dir("rosbag_stereo");
  Rig rig = small_rig();
  rig.T_BC = kIdentity4;
  rig.stereo.present = true;
  rig.stereo.intrinsics = rig.rgb;
  rig.stereo.T_BC1 = kIdentity4;
  rig.stereo.T_BC1[3] = 0.08;
  {
    drivers::KlogWriter w;
    w.open(dir + "/s.klog", rig);
    for (uint32_t i = 0; i < 200; ++i) {
      const ImuSample s = imu_at(i);
      w.write_imu(s);
      if (i % 20 == 0) {
        w.write_image(drivers::RecordType::kRgb, image_at(s.t_ns, i / 20, PixelFormat::kGray8));
        w.write_image(drivers::RecordType::kRight, image_at(s.t_ns, 100 + i / 20, PixelFormat::kGray8));
      }
    }
  }
  drivers::KlogReader a(dir + "/s.klog");
  drivers::RosbagTopics t;
  t.right = "/stereo/right/image_raw";
  drivers::export_rosbag(a, dir + "/s.bag", t);
  drivers::RosbagReader b(dir + "/s.bag", t, nullptr);
  ASSERT_TRUE(b.rig().stereo.present) << problems_text(b);
  EXPECT_NEAR(b.rig().stereo.T_BC1[3], 0.08, 1e-12);
  EXPECT_EQ(b.rig().stereo.intrinsics.fx, rig.rgb.fx);
  EXPECT_NE(problems_text(b).find("placed by its CameraInfo's baseline"), std::string::npos)
      << problems_text(b);
  const auto x = read_all(a), y = read_all(b);
  const auto lx = of_type(x, drivers::RecordType::kRgb), rx = of_type(x, drivers::RecordType::kRight);
  const auto ly = of_type(y, drivers::RecordType::kRgb), ry = of_type(y, drivers::RecordType::kRight);
  ASSERT_EQ(rx.size(), 10u);
  ASSERT_EQ(ry.size(), rx.size()) << problems_text(b);
  for (size_t k = 0; k < rx.size(); ++k) {
    EXPECT_EQ(ry[k].image.t_ns, ly[k].image.t_ns);
    EXPECT_EQ(ry[k].image.pixels, rx[k].image.pixels);
  }
  // Without the right topic named, the same bag is monocular.
  drivers::RosbagReader mono(dir + "/s.bag", drivers::RosbagTopics{}, nullptr);
  EXPECT_FALSE(mono.rig().stereo.present);
}

}  // namespace
}  // namespace kestrel::test

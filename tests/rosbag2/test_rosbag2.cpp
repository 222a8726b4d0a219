// MCAP container, ROS 2 CDR messages and rosbag2 folders: byte layouts checked
// against the specifications by hand, round trips, damage and unknown input.
#include <gtest/gtest.h>
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "../datasets/dataset_fixtures.hpp"
#include "db3_fixture.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/mcap.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/drivers/ros2_msgs.hpp"
#include "kestrel/drivers/rosbag2.hpp"

namespace kestrel::test {
namespace {

namespace fs = std::filesystem;
namespace mcap = drivers::mcap;
namespace ros2 = drivers::ros2;
using drivers::RecordType;

std::string tmp(const std::string& name) {
  static const std::string dir = temp_dir("rosbag2");
  return dir + "/" + name;
}

std::vector<uint8_t> file_bytes(const std::string& p) {
  std::ifstream f(p, std::ios::binary);
  return std::vector<uint8_t>(std::istreambuf_iterator<char>(f), {});
}

TEST(Rosbag2Cdr, HeaderAlignmentAndStringsFollowTheSpec) {
  // std_msgs/Header{stamp 1.5 s, "ab"} then a float64: the string's length counts
  // its NUL, and the double is aligned to 8 from the byte after the 4-byte
  // encapsulation header, not from the buffer's start.
  std::vector<uint8_t> b;
  ros2::CdrWriter w(b);
  w.header(1'500'000'000, "ab");
  w.f64(2.0);
  const std::vector<uint8_t> want = {0x00, 0x01, 0x00, 0x00,               // CDR_LE
                                     0x01, 0x00, 0x00, 0x00,               // sec 1
                                     0x00, 0x65, 0xcd, 0x1d,               // nanosec 5e8
                                     0x03, 0x00, 0x00, 0x00, 'a', 'b', 0,  // "ab\0"
                                     0,                                    // pad to payload offset 16
                                     0,    0,    0,    0,    0,   0,   0, 0x40};
  EXPECT_EQ(b, want);
  ros2::CdrReader r(b.data(), b.size());
  std::string frame;
  EXPECT_EQ(r.header(&frame), 1'500'000'000);
  EXPECT_EQ(frame, "ab");
  EXPECT_EQ(r.f64("x"), 2.0);
  EXPECT_THROW(r.u8("past the end"), std::runtime_error);
}

TEST(Rosbag2Cdr, MessagesRoundTripAndTruncationIsNamed) {
  ros2::Imu m;
  m.t_ns = 1'700'000'000'123'456'789;
  m.frame_id = "imu";
  m.angular_velocity = {0.1, -0.2, 0.3};
  m.linear_acceleration = {1.5, 2.5, 9.81};
  std::vector<uint8_t> b;
  ros2::encode(m, b);
  // stamp 8, "imu" 4 + 4 (ends at payload offset 16: no padding before the doubles), 37 doubles.
  EXPECT_EQ(b.size(), 4u + 8 + 8 + (4 + 9 + 3 + 9 + 3 + 9) * 8);
  ros2::Imu d;
  ros2::decode(b.data(), b.size(), d);
  EXPECT_EQ(d.t_ns, m.t_ns);
  EXPECT_EQ(d.frame_id, "imu");
  EXPECT_EQ(d.angular_velocity, m.angular_velocity);
  EXPECT_EQ(d.linear_acceleration, m.linear_acceleration);
  EXPECT_EQ(d.orientation_covariance[0], -1.0);
  for (size_t n = 0; n < b.size(); ++n) {
    try {
      ros2::decode(b.data(), n, d);
      ADD_FAILURE() << "decoded " << n << " of " << b.size() << " bytes";
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()), "");
    }
  }
  // A big-endian encapsulation is named, not misread.
  b[1] = 0x00;
  try {
    ros2::decode(b.data(), b.size(), d);
    ADD_FAILURE();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("CDR_LE"), std::string::npos);
  }

  ros2::Odometry o;
  o.t_ns = 42;
  o.frame_id = "odom";
  o.child_frame_id = "base_link";
  o.pose.position = {1, 2, 3};
  o.pose.orientation_xyzw = {0, 0, 0.6, 0.8};
  o.pose_covariance[35] = 0.25;
  o.linear = {4, 5, 6};
  ros2::encode(o, b);
  ros2::Odometry od;
  ros2::decode(b.data(), b.size(), od);
  EXPECT_EQ(od.child_frame_id, "base_link");
  EXPECT_EQ(od.pose.orientation_xyzw, o.pose.orientation_xyzw);
  EXPECT_EQ(od.pose_covariance[35], 0.25);
  EXPECT_EQ(od.linear, o.linear);

  std::vector<ros2::TransformStamped> tf(2), tfd;
  tf[1].child_frame_id = "cam";
  tf[1].translation = {0.1, 0.2, 0.3};
  ros2::encode(tf, b);
  ros2::decode(b.data(), b.size(), tfd);
  ASSERT_EQ(tfd.size(), 2u);
  EXPECT_EQ(tfd[1].translation, tf[1].translation);
  // A corrupt sequence length cannot make the decoder allocate billions of elements.
  b[4] = 0xff, b[5] = 0xff, b[6] = 0xff, b[7] = 0x7f;
  EXPECT_THROW(ros2::decode(b.data(), b.size(), tfd), std::runtime_error);
}

TEST(Rosbag2Cdr, SchemaTextsCarryTheirDependencies) {
  const std::string s = ros2::schema_text("sensor_msgs/msg/Imu");
  EXPECT_EQ(s.rfind("std_msgs/Header header\n", 0), 0u);
  EXPECT_NE(s.find("\n" + std::string(80, '=') + "\nMSG: std_msgs/Header\n"), std::string::npos);
  EXPECT_NE(s.find("MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"), std::string::npos);
  EXPECT_NE(ros2::schema_text("nav_msgs/msg/Odometry").find("MSG: geometry_msgs/TwistWithCovariance"),
            std::string::npos);
  EXPECT_NE(ros2::schema_text("sensor_msgs/msg/PointCloud2").find("MSG: sensor_msgs/PointField\n"),
            std::string::npos);
  EXPECT_NE(
      ros2::schema_text("visualization_msgs/msg/MarkerArray").find("MSG: visualization_msgs/MeshFile\n"),
      std::string::npos);
  EXPECT_EQ(ros2::schema_text("sensor_msgs/msg/LaserScan"), "");  // a type this file does not know
}

void write_mcap(const std::string& path, const std::string& compression, size_t chunk) {
  mcap::WriterOptions o;
  o.compression = compression;
  o.chunk_size_bytes = chunk;
  mcap::Writer w;
  w.open(path, o);
  const uint16_t s = w.add_schema("test/msg/Blob", "ros2msg", "uint8[] data\n");
  const uint16_t a = w.add_channel(s, "/a", "cdr", {{"k", "v"}});
  const uint16_t b = w.add_channel(s, "/b", "cdr");
  for (uint32_t i = 0; i < 300; ++i) {
    std::vector<uint8_t> p(1 + i % 50, static_cast<uint8_t>(i));
    w.write(i % 3 == 0 ? b : a, 1000 + i, 2000 + i, p.data(), p.size());
  }
  w.add_metadata("kestrel", {{"x", "y"}});
  w.close();
}

TEST(Mcap, WriterLayoutMatchesTheSpec) {
  const std::string p = tmp("layout.mcap");
  write_mcap(p, "", 1024);
  const auto b = file_bytes(p);
  ASSERT_GT(b.size(), 16u + 37);
  EXPECT_EQ(std::memcmp(b.data(), mcap::kMagic, 8), 0);
  EXPECT_EQ(std::memcmp(b.data() + b.size() - 8, mcap::kMagic, 8), 0);
  // Footer: opcode, length 20, summary_start, summary_offset_start, crc.
  const uint8_t* f = b.data() + b.size() - 8 - 29;
  EXPECT_EQ(f[0], mcap::kFooter);
  uint64_t len, summary_start, offset_start;
  uint32_t crc;
  std::memcpy(&len, f + 1, 8);
  std::memcpy(&summary_start, f + 9, 8);
  std::memcpy(&offset_start, f + 17, 8);
  std::memcpy(&crc, f + 25, 4);
  EXPECT_EQ(len, 20u);
  ASSERT_LT(summary_start, offset_start);
  EXPECT_EQ(b[summary_start], mcap::kSchema);
  EXPECT_EQ(b[offset_start], mcap::kSummaryOffset);
  // The summary CRC covers the summary up to the footer's summary_offset_start.
  EXPECT_EQ(crc, static_cast<uint32_t>(::crc32(0, b.data() + summary_start,
                                               static_cast<uInt>(b.size() - 8 - 4 - summary_start))));
  // DataEnd right before the summary, its CRC over everything before it.
  const uint8_t* de = b.data() + summary_start - 13;
  EXPECT_EQ(de[0], mcap::kDataEnd);
  uint32_t dcrc;
  std::memcpy(&dcrc, de + 9, 4);
  EXPECT_EQ(dcrc, static_cast<uint32_t>(::crc32(0, b.data(), static_cast<uInt>(summary_start - 13))));
}

TEST(Mcap, EveryCompressionRoundTrips) {
  for (const auto& [comp, chunk] : std::vector<std::pair<std::string, size_t>>{
           {"zstd", 1024}, {"lz4", 1024}, {"", 1024}, {"", 0}, {"zstd", 1u << 20}}) {
    SCOPED_TRACE("compression '" + comp + "' chunk " + std::to_string(chunk));
    const std::string p = tmp("rt.mcap");
    write_mcap(p, comp, chunk);
    mcap::Reader r(p);
    std::vector<mcap::MessageRef> refs;
    std::vector<std::vector<uint8_t>> data;
    EXPECT_EQ(r.scan([&](const mcap::MessageRef& m, const uint8_t* d, size_t n) {
      refs.push_back(m);
      data.emplace_back(d, d + n);
    }),
              300u);
    EXPECT_TRUE(r.problems().empty()) << r.problems().front().kind << ": " << r.problems().front().detail;
    EXPECT_EQ(r.profile(), "ros2");
    ASSERT_EQ(r.channels().size(), 2u);
    EXPECT_EQ(r.channels().at(0).metadata.at("k"), "v");
    EXPECT_EQ(r.schemas().at(1).name, "test/msg/Blob");
    EXPECT_EQ(r.metadata().at("kestrel").at("x"), "y");
    if (chunk > 0) {
      EXPECT_GT(r.chunk_count(), 0u);
    }
    std::vector<uint8_t> scratch;
    // Fetched again later, in reverse order, as a replay after a sort would.
    for (size_t i = refs.size(); i-- > 0;) {
      EXPECT_EQ(refs[i].log_time_ns, 1000 + i);
      EXPECT_EQ(refs[i].publish_time_ns, 2000 + i);
      EXPECT_EQ(refs[i].channel_id, i % 3 == 0 ? 1 : 0);
      const uint8_t* d = nullptr;
      ASSERT_TRUE(r.load(refs[i], scratch, d));
      ASSERT_EQ(refs[i].size, 1 + i % 50);
      EXPECT_EQ(std::vector<uint8_t>(d, d + refs[i].size), data[i]);
      EXPECT_EQ(d[0], static_cast<uint8_t>(i));
    }
  }
}

TEST(Mcap, TruncatedFilesAreReadUpToTheDamage) {
  for (size_t chunk : {size_t{0}, size_t{1024}}) {
    const std::string p = tmp("full.mcap");
    write_mcap(p, "zstd", chunk);
    const auto b = file_bytes(p);
    size_t last = 0;
    for (size_t cut = 8; cut < b.size(); cut += 97) {
      mcap::Reader r(b.data(), cut);
      const size_t n = r.scan([](const mcap::MessageRef&, const uint8_t*, size_t) {});
      EXPECT_GE(n, last) << "cut at " << cut;  // more file, never fewer messages
      last = n;
      if (n < 300) {
        EXPECT_FALSE(r.problems().empty()) << "cut at " << cut;
      }
    }
    EXPECT_GT(last, 250u);
  }
  // A corrupt chunk size cannot make the reader allocate it.
  const std::string p = tmp("big.mcap");
  write_mcap(p, "zstd", 1024);
  auto b = file_bytes(p);
  size_t at = 8;
  while (b[at] != mcap::kChunk) {
    uint64_t len;
    std::memcpy(&len, b.data() + at + 1, 8);
    at += 9 + len;
  }
  const uint64_t huge = 1ull << 40;
  std::memcpy(b.data() + at + 9 + 16, &huge, 8);
  mcap::Reader r(b.data(), b.size());
  r.scan([](const mcap::MessageRef&, const uint8_t*, size_t) {});
  bool named = false;
  for (const auto& pr : r.problems()) named = named || pr.kind == "bad-length";
  EXPECT_TRUE(named);
}

// The .klog -> rosbag2 -> records round trip: every value comes back exactly.
TEST(Rosbag2, ExportThenReadGivesTheSameRecords) {
  const std::string klog = tmp("small.klog");
  write_small_klog(klog);
  for (const std::string comp : {"zstd", "lz4", ""}) {
    SCOPED_TRACE("compression '" + comp + "'");
    const std::string dir = tmp("bag_" + (comp.empty() ? std::string("none") : comp));
    drivers::KlogReader src(klog);
    drivers::Rosbag2WriteOptions wo;
    wo.mcap.compression = comp;
    wo.mcap.chunk_size_bytes = 4096;
    const auto st = drivers::export_rosbag2(src, dir, wo);
    EXPECT_EQ(st.imu, 200u);
    EXPECT_EQ(st.rgb, 10u);
    EXPECT_EQ(st.depth, 10u);
    EXPECT_EQ(st.ground_truth, 50u);
    std::ifstream meta(dir + "/metadata.yaml");
    const std::string y((std::istreambuf_iterator<char>(meta)), {});
    EXPECT_NE(y.find("version: 5"), std::string::npos);
    EXPECT_NE(y.find("storage_identifier: mcap"), std::string::npos);
    EXPECT_NE(y.find("type: sensor_msgs/msg/Image"), std::string::npos);

    ASSERT_TRUE(drivers::is_rosbag2(dir));
    auto back = drivers::open_log(dir);
    EXPECT_EQ(back->format_name(), "rosbag2");
    EXPECT_TRUE(drivers::rig_equal(back->rig(), src.rig())) << drivers::rig_to_yaml(back->rig());
    const auto a = read_all(src), b = read_all(*back);
    ASSERT_EQ(a.size(), b.size()) << problems_text(*back);
    for (size_t i = 0; i < a.size(); ++i) {
      ASSERT_EQ(a[i].type, b[i].type) << i;
      switch (a[i].type) {
        case RecordType::kImu:
          EXPECT_EQ(a[i].imu.t_ns, b[i].imu.t_ns);
          EXPECT_EQ(a[i].imu.gyro_rps, b[i].imu.gyro_rps);
          EXPECT_EQ(a[i].imu.acc_mps2, b[i].imu.acc_mps2);
          break;
        case RecordType::kRgb:
        case RecordType::kDepth:
          EXPECT_EQ(a[i].image.t_ns, b[i].image.t_ns);
          EXPECT_EQ(a[i].image.format, b[i].image.format);
          EXPECT_EQ(a[i].image.pixels, b[i].image.pixels);
          break;
        case RecordType::kGroundTruth:
          EXPECT_EQ(a[i].gt.t_ns, b[i].gt.t_ns);
          EXPECT_EQ(a[i].gt.p_WB, b[i].gt.p_WB);
          EXPECT_EQ(a[i].gt.q_WB, b[i].gt.q_WB);
          break;
        default:
          break;
      }
    }
    // The single .mcap opens too.
    auto single = drivers::open_log(dir + "/" + fs::path(dir).filename().string() + "_0.mcap");
    EXPECT_EQ(read_all(*single).size(), a.size());
  }
}

// A bag without Kestrel's rig metadata (as ros2 bag record writes it): the rig
// from CameraInfo and /tf_static, unknown types and encodings named.
TEST(Rosbag2, RigFromCameraInfoAndTfStaticUnknownTypesNamed) {
  const std::string p = tmp("foreign.mcap");
  {
    mcap::Writer w;
    w.open(p);
    auto ch = [&](const char* type, const char* topic, const char* enc = "cdr") {
      return w.add_channel(w.add_schema(type, "ros2msg", ros2::schema_text(type)), topic, enc);
    };
    const uint16_t imu = ch("sensor_msgs/msg/Imu", "/d435i/imu"),
                   rgb = ch("sensor_msgs/msg/Image", "/d435i/color"),
                   dep = ch("sensor_msgs/msg/Image", "/d435i/depth"),
                   info = ch("sensor_msgs/msg/CameraInfo", "/d435i/camera_info"),
                   tf = ch("tf2_msgs/msg/TFMessage", "/tf_static"),
                   pc = ch("sensor_msgs/msg/PointCloud2", "/points"),
                   js = ch("sensor_msgs/msg/Imu", "/json", "json");
    std::vector<uint8_t> b;
    std::vector<ros2::TransformStamped> t(2);
    t[0].frame_id = t[1].frame_id = "base";
    t[0].child_frame_id = "imu_f";
    t[0].translation = {0.01, 0, 0};
    t[1].child_frame_id = "cam_f";
    t[1].translation = {0, 0.02, 0};
    t[1].rotation_xyzw = {0, 0, std::sqrt(0.5), std::sqrt(0.5)};  // 90 degrees about z
    ros2::encode(t, b);
    w.write(tf, 1, 1, b.data(), b.size());
    w.write(pc, 1, 1, b.data(), b.size());
    w.write(js, 1, 1, b.data(), b.size());
    for (int i = 0; i < 40; ++i) {
      const int64_t ts = 1'000'000'000 + i * 5'000'000;
      ros2::Imu m;
      m.t_ns = ts;
      m.frame_id = "imu_f";
      m.linear_acceleration = {0, 0, 9.81};
      ros2::encode(m, b);
      w.write(imu, ts, ts, b.data(), b.size());
      if (i % 10 == 0) {
        std::vector<uint8_t> px(4 * 3 * 3, static_cast<uint8_t>(i));
        ros2::Image im;
        im.t_ns = ts;
        im.frame_id = "cam_f";
        im.width = 4, im.height = 3, im.step = 12, im.encoding = "bgr8";
        im.data = px.data(), im.data_size = static_cast<uint32_t>(px.size());
        ros2::encode(im, b);
        w.write(rgb, ts, ts, b.data(), b.size());
        std::vector<float> dm(12, 1.25f);  // 32FC1 metres
        im.t_ns = ts + 2'000'000, im.encoding = "32FC1", im.step = 16;
        im.data = reinterpret_cast<const uint8_t*>(dm.data()), im.data_size = 48;
        ros2::encode(im, b);
        w.write(dep, ts, ts, b.data(), b.size());
        ros2::CameraInfo ci;
        ci.t_ns = ts;
        ci.frame_id = "cam_f";
        ci.width = 4, ci.height = 3;
        ci.k = {600, 0, 2, 0, 601, 1.5, 0, 0, 1};
        ci.distortion_model = "plumb_bob";
        ci.d = {0.1, -0.05, 0, 0, 0};
        ros2::encode(ci, b);
        w.write(info, ts, ts, b.data(), b.size());
      }
    }
    w.close();
  }
  drivers::Rosbag2Reader r(p);
  const Rig& rig = r.rig();
  EXPECT_EQ(rig.rgb.fx, 600);
  EXPECT_EQ(rig.rgb.cy, 1.5);
  EXPECT_EQ(rig.rgb.distortion, DistortionModel::kRadTan);
  EXPECT_EQ(rig.rgb.dist[0], 0.1);
  // T_BC = T_imu_base * T_base_cam: camera at (-0.01, 0.02, 0) in the IMU frame, rotated 90 degrees.
  EXPECT_NEAR(rig.T_BC[3], -0.01, 1e-12);
  EXPECT_NEAR(rig.T_BC[7], 0.02, 1e-12);
  EXPECT_NEAR(rig.T_BC[1], -1.0, 1e-12);
  EXPECT_TRUE(has_problem(r, "unsupported-type", "/points")) << problems_text(r);
  EXPECT_TRUE(has_problem(r, "bad-encoding", "/json")) << problems_text(r);
  bool named = false;
  for (const auto& pr : r.problems())
    named = named || pr.detail.find("sensor_msgs/msg/PointCloud2") != std::string::npos;
  EXPECT_TRUE(named);
  const auto recs = read_all(r);
  const auto rgb = of_type(recs, RecordType::kRgb), dep = of_type(recs, RecordType::kDepth);
  ASSERT_EQ(rgb.size(), 4u);
  ASSERT_EQ(dep.size(), 4u);
  EXPECT_EQ(rgb[0].image.format, PixelFormat::kBgr8);
  EXPECT_EQ(dep[1].image.t_ns, rgb[1].image.t_ns);  // depth carried on the colour stamp
  EXPECT_NEAR(depth_m(dep[1].image, 5, rig.depth.scale_m_per_unit), 1.25, 1e-9);
  EXPECT_EQ(of_type(recs, RecordType::kImu).size(), 40u);
}

TEST(Rosbag2, TruncatedBagReplaysUpToTheDamageAndSqliteIsNamed) {
  const std::string klog = tmp("trunc.klog");
  write_small_klog(klog);
  const std::string dir = tmp("trunc_bag");
  drivers::KlogReader src(klog);
  drivers::Rosbag2WriteOptions wo;
  wo.mcap.chunk_size_bytes = 0;  // unchunked: every record before the cut is readable
  drivers::export_rosbag2(src, dir, wo);
  const std::string file = dir + "/trunc_bag_0.mcap";
  const auto size = fs::file_size(file);
  fs::resize_file(file, size * 6 / 10);
  drivers::Rosbag2Reader r(dir);
  const auto recs = read_all(r);
  EXPECT_TRUE(has_problem(r, "truncated", "trunc_bag_0.mcap")) << problems_text(r);
  const size_t imu = of_type(recs, RecordType::kImu).size();
  EXPECT_GT(imu, 80u);
  EXPECT_LT(imu, 200u);

  const std::string sq = tmp("sqlite_bag");
  fs::create_directories(sq);
  write_text(sq + "/metadata.yaml",
             "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: sqlite3\n"
             "  relative_file_paths:\n    - a_0.db3\n");
  // sqlite3 storage is read now: a missing .db3 is an error naming it.
  try {
    drivers::open_log(sq);
    ADD_FAILURE();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("a_0.db3"), std::string::npos) << e.what();
  }
}

// ---- rosbag2's sqlite3 storage, CompressedImage, --topics ------------------------------------------------

void expect_same_records(const std::vector<drivers::LogRecord>& a, const std::vector<drivers::LogRecord>& b) {
  ASSERT_EQ(a.size(), b.size());
  for (size_t i = 0; i < a.size(); ++i) {
    ASSERT_EQ(a[i].type, b[i].type) << i;
    if (a[i].type == RecordType::kImu) {
      EXPECT_EQ(a[i].imu.t_ns, b[i].imu.t_ns) << i;
      EXPECT_EQ(a[i].imu.gyro_rps, b[i].imu.gyro_rps) << i;
      EXPECT_EQ(a[i].imu.acc_mps2, b[i].imu.acc_mps2) << i;
    } else if (a[i].type == RecordType::kRgb || a[i].type == RecordType::kDepth) {
      EXPECT_EQ(a[i].image.t_ns, b[i].image.t_ns) << i;
      EXPECT_EQ(a[i].image.format, b[i].image.format) << i;
      EXPECT_EQ(a[i].image.pixels, b[i].image.pixels) << i;
    } else if (a[i].type == RecordType::kGroundTruth) {
      EXPECT_EQ(a[i].gt.t_ns, b[i].gt.t_ns) << i;
      EXPECT_EQ(a[i].gt.p_WB, b[i].gt.p_WB) << i;
    }
  }
}

std::string mcap_bag_of_small_klog(const std::string& stem) {
  const std::string klog = tmp(stem + ".klog");
  write_small_klog(klog);
  const std::string dir = tmp(stem + "_mcap");
  drivers::KlogReader src(klog);
  drivers::export_rosbag2(src, dir, {});
  return dir;
}

TEST(Rosbag2Sqlite, Db3GivesTheSameRecordsAsTheMcapItHolds) {
  const std::string bag = mcap_bag_of_small_klog("sq");
  const std::string mcap_file = bag + "/" + fs::path(bag).filename().string() + "_0.mcap";
  const std::string dir = tmp("sq_db3");
  write_db3_from_mcap(mcap_file, dir, "sq_0.db3");
  auto ref = drivers::open_log(bag);
  auto db = drivers::open_log(dir);
  EXPECT_EQ(db->format_name(), "rosbag2");
  const auto a = read_all(*ref), b = read_all(*db);
  EXPECT_EQ(of_type(b, RecordType::kImu).size(), 200u) << problems_text(*db);
  EXPECT_EQ(of_type(b, RecordType::kRgb).size(), 10u);
  expect_same_records(a, b);
  // No Kestrel metadata in a .db3: the rig comes from CameraInfo and /tf_static, as from `ros2 bag record`.
  EXPECT_EQ(db->rig().rgb.fx, ref->rig().rgb.fx);
  EXPECT_EQ(db->rig().rgb.width, ref->rig().rgb.width);
  for (int k = 0; k < 16; ++k) EXPECT_NEAR(db->rig().T_BC[k], ref->rig().T_BC[k], 1e-12) << k;
  // The lone .db3 opens too (by extension and SQLite's header).
  ASSERT_TRUE(drivers::is_rosbag2(dir + "/sq_0.db3"));
  auto lone = drivers::open_log(dir + "/sq_0.db3");
  EXPECT_EQ(read_all(*lone).size(), a.size());
}

TEST(Rosbag2Sqlite, DamagedDb3IsReadUpToTheDamageOrNamed) {
  const std::string bag = mcap_bag_of_small_klog("sqcut");
  const std::string dir = tmp("sqcut_db3");
  write_db3_from_mcap(bag + "/sqcut_mcap_0.mcap", dir, "c_0.db3");
  const std::string f = dir + "/c_0.db3";
  const size_t full = read_all(*drivers::open_log(dir)).size();
  // Cut: the pages past the cut are gone; every message row on the pages before it is read.
  fs::resize_file(f, fs::file_size(f) * 6 / 10);
  {
    drivers::Rosbag2Reader r(dir);
    const auto recs = read_all(r);
    std::printf("cut .db3: %zu of %zu records read\n%s", recs.size(), full, problems_text(r).c_str());
    EXPECT_LT(recs.size(), full);
    EXPECT_GT(of_type(recs, RecordType::kImu).size(), 50u);
    EXPECT_TRUE(has_problem(r, "truncated", "c_0.db3")) << problems_text(r);
  }
  // Not a database at all: named.
  write_text(f, "this is not SQLite");
  try {
    drivers::Rosbag2Reader r(dir);
    ADD_FAILURE() << "a text file opened as a .db3";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("c_0.db3"), std::string::npos) << e.what();
  }
}

// The bag's Image messages rewritten as CompressedImage the way image_transport's
// plugins write them: colour PNG / JPEG of BGR ("rgb8; png compressed bgr8"),
// depth "16UC1; compressedDepth png" (12-byte header, then a 16-bit PNG).
std::string compressed_copy(const std::string& mcap_file, const std::string& out,
                            const std::string& colour_ext) {
  mcap::Reader r(mcap_file);
  mcap::Writer w;
  w.open(out);
  std::map<uint16_t, uint16_t> ch_out;
  std::map<uint16_t, bool> is_image;
  std::vector<uint8_t> b, enc;
  r.scan([&](const mcap::MessageRef& m, const uint8_t* data, size_t n) {
    if (!ch_out.count(m.channel_id)) {
      const auto& ch = r.channels().at(m.channel_id);
      const std::string type = r.schemas().at(ch.schema_id).name;
      is_image[m.channel_id] = type == "sensor_msgs/msg/Image";
      const std::string t = is_image[m.channel_id] ? "sensor_msgs/msg/CompressedImage" : type;
      ch_out[m.channel_id] = w.add_channel(w.add_schema(t, "ros2msg", ros2::schema_text(t)),
                                           ch.topic + (is_image[m.channel_id] ? "/compressed" : ""), "cdr");
    }
    if (!is_image[m.channel_id]) {
      w.write(ch_out[m.channel_id], m.log_time_ns, m.publish_time_ns, data, n);
      return;
    }
    ros2::Image im;
    ros2::decode(data, n, im);
    ros2::CompressedImage c;
    c.t_ns = im.t_ns;
    c.frame_id = im.frame_id;
    std::vector<uchar> png;
    if (im.encoding == "16UC1") {
      cv::Mat d(static_cast<int>(im.height), static_cast<int>(im.width), CV_16UC1,
                const_cast<uint8_t*>(im.data), im.step);
      cv::imencode(".png", d, png);
      enc.assign(12, 0);  // format 0 (INV_DEPTH unused for 16UC1), depthQuantA, depthQuantB
      enc.insert(enc.end(), png.begin(), png.end());
      c.format = "16UC1; compressedDepth png";
    } else {
      cv::Mat rgb(static_cast<int>(im.height), static_cast<int>(im.width), CV_8UC3,
                  const_cast<uint8_t*>(im.data), im.step);
      cv::Mat bgr;
      cv::cvtColor(rgb, bgr, im.encoding == "rgb8" ? cv::COLOR_RGB2BGR : cv::COLOR_BGR2RGB);
      if (im.encoding == "bgr8") bgr = rgb;
      cv::imencode(colour_ext, bgr, png);
      enc.assign(png.begin(), png.end());
      c.format = im.encoding + (colour_ext == ".png" ? "; png compressed bgr8" : "; jpeg compressed bgr8");
    }
    c.data = enc.data();
    c.data_size = static_cast<uint32_t>(enc.size());
    ros2::encode(c, b);
    w.write(ch_out[m.channel_id], m.log_time_ns, m.publish_time_ns, b.data(), b.size());
  });
  w.close();
  return out;
}

TEST(Rosbag2Compressed, PngAndCompressedDepthAreLosslessJpegIsClose) {
  const std::string bag = mcap_bag_of_small_klog("cmp");
  const std::string src = bag + "/cmp_mcap_0.mcap";
  const auto ref = read_all(*drivers::open_log(src));
  const auto ref_rgb = of_type(ref, RecordType::kRgb), ref_dep = of_type(ref, RecordType::kDepth);
  ASSERT_EQ(ref_rgb.size(), 10u);
  for (const std::string ext : {".png", ".jpg"}) {
    SCOPED_TRACE(ext);
    drivers::Rosbag2Reader r(compressed_copy(src, tmp("cmp" + ext + ".mcap"), ext));
    const auto recs = read_all(r);
    const auto rgb = of_type(recs, RecordType::kRgb), dep = of_type(recs, RecordType::kDepth);
    ASSERT_EQ(rgb.size(), ref_rgb.size()) << problems_text(r);
    ASSERT_EQ(dep.size(), ref_dep.size()) << problems_text(r);
    for (size_t i = 0; i < rgb.size(); ++i) {
      EXPECT_EQ(rgb[i].image.t_ns, ref_rgb[i].image.t_ns);
      EXPECT_EQ(rgb[i].image.format, PixelFormat::kBgr8);  // OpenCV decodes to BGR
      ASSERT_EQ(rgb[i].image.pixels.size(), ref_rgb[i].image.pixels.size());
      // Back to the reference's channel order, then compared.
      const bool ref_rgb8 = ref_rgb[i].image.format == PixelFormat::kRgb8;
      double abs_sum = 0;
      int max_diff = 0;
      const auto& a = rgb[i].image.pixels;
      const auto& e = ref_rgb[i].image.pixels;
      for (size_t k = 0; k < a.size(); ++k) {
        const size_t c = k % 3;
        const size_t ka = ref_rgb8 ? k - c + (2 - c) : k;
        const int d = std::abs(int(a[ka]) - int(e[k]));
        abs_sum += d;
        max_diff = std::max(max_diff, d);
      }
      if (ext == ".png") {
        EXPECT_EQ(max_diff, 0) << i;
      } else {
        // JPEG (quality 95, 4:2:0) on the fixture's tiny, busy images: 8-12 grey levels on average. Channel
        // order and strides are proven exactly by the PNG pass (the same path after decoding); this bounds
        // the lossy path against garbage.
        EXPECT_LT(abs_sum / a.size(), 16.0) << i;
      }
      EXPECT_EQ(dep[i].image.pixels, ref_dep[i].image.pixels) << i;  // compressedDepth PNG: exact millimetres
    }
  }
}

TEST(Rosbag2Topics, OnlyTheChosenTopicsAreReadAndAnUnknownOneIsNamed) {
  const std::string bag = mcap_bag_of_small_klog("top");
  drivers::Rosbag2ReadOptions o;
  o.topics = {"/camera/imu"};
  drivers::Rosbag2Reader r(bag, o);
  const auto recs = read_all(r);
  EXPECT_EQ(of_type(recs, RecordType::kImu).size(), 200u);
  EXPECT_EQ(of_type(recs, RecordType::kRgb).size(), 0u);
  EXPECT_EQ(of_type(recs, RecordType::kGroundTruth).size(), 0u);
  EXPECT_TRUE(has_problem(r, "missing-file", "")) << problems_text(r);  // "no colour images", said
  o.topics = {"/camera/imu", "/nope"};
  try {
    drivers::Rosbag2Reader bad(bag, o);
    ADD_FAILURE();
  } catch (const std::runtime_error& e) {
    const std::string w = e.what();
    EXPECT_NE(w.find("/nope"), std::string::npos) << w;
    EXPECT_NE(w.find("/camera/color/image_raw"), std::string::npos) << w;  // what the bag has
  }
  // Through open_log, as --topics passes it.
  drivers::LogOpenOptions lo;
  lo.topics = {"/camera/imu", "/camera/color/image_raw", "/camera/aligned_depth_to_color/image_raw"};
  const auto all = read_all(*drivers::open_log(bag, lo));
  EXPECT_EQ(of_type(all, RecordType::kRgb).size(), 10u);
  EXPECT_EQ(of_type(all, RecordType::kGroundTruth).size(), 0u);
}

}  // namespace
}  // namespace kestrel::test

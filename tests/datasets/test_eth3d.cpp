// ETH3D SLAM folders: hand-written fixtures, the export round trip, malformed input.
#include <gtest/gtest.h>

#include <cstring>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>

#include "dataset_fixtures.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_export.hpp"
#include "kestrel/drivers/open_log.hpp"

namespace kestrel::test {
namespace {

using drivers::RecordType;

// Four synchronised RGB-D frames (t = 10.0 + 0.04 k s), IMU at 200 Hz, ground truth at each frame.
std::string write_eth3d_fixture(const std::string& name, bool with_assoc = true) {
  const std::string dir = temp_dir(name);
  std::filesystem::create_directories(dir + "/rgb");
  std::filesystem::create_directories(dir + "/depth");
  std::string rgb = "# timestamp filename\n", depth = rgb, assoc, gt = "# timestamp tx ty tz qx qy qz qw\n";
  for (int k = 0; k < 4; ++k) {
    const std::string t = "10." + std::string(k < 3 ? "0" : "") + std::to_string(4 * k) + "0000";
    const std::string ts = k == 0 ? "10.000000" : t;
    cv::Mat c(6, 8, CV_8UC3, cv::Scalar(10 * k, 20, 30));  // BGR on disk
    cv::Mat d(6, 8, CV_16UC1, cv::Scalar(5000 + k));       // 1.0002 m .. at 5000 units per metre
    cv::imwrite(dir + "/rgb/" + ts + ".png", c);
    cv::imwrite(dir + "/depth/" + ts + ".png", d);
    rgb += ts + " rgb/" + ts + ".png\n";
    depth += ts + " depth/" + ts + ".png\n";
    assoc += ts + " rgb/" + ts + ".png " + ts + " depth/" + ts + ".png\n";
    gt += ts + " " + std::to_string(k) + " 2 3 0 0 0 1\n";
  }
  write_text(dir + "/rgb.txt", rgb);
  write_text(dir + "/depth.txt", depth);
  if (with_assoc) write_text(dir + "/associated.txt", assoc);
  write_text(dir + "/groundtruth.txt", gt);
  write_text(dir + "/calibration.txt", "726.28 726.28 354.6 186.5\n");
  std::string imu = "# timestamp gx gy gz ax ay az\n";
  for (int i = 0; i < 30; ++i) {
    char b[128];
    std::snprintf(b, sizeof b, "10.%06d 0.%d 0.2 0.3 1.5 -0.5 9.8%d\n", i * 5000, i % 10, i % 10);
    imu += b;
  }
  write_text(dir + "/imu.txt", imu);
  return dir;
}

TEST(Eth3dReader, ReadsTheDocumentedLayout) {
  const std::string dir = write_eth3d_fixture("eth3d_layout");
  ASSERT_TRUE(drivers::is_eth3d_folder(dir));
  auto log = drivers::open_log(dir);
  ASSERT_EQ(log->format_name(), "eth3d") << "ETH3D must be detected before TUM (both have rgb.txt)";
  const Rig& r = log->rig();
  EXPECT_EQ(r.rgb.fx, 726.28);
  EXPECT_EQ(r.rgb.cy, 186.5);
  EXPECT_EQ(r.rgb.width, 8) << "the image size comes from the first colour image";
  EXPECT_EQ(r.rgb.height, 6);
  EXPECT_EQ(r.depth.scale_m_per_unit, 1.0 / 5000.0);
  EXPECT_TRUE(has_problem(*log, "assumed", "calibration.txt")) << "T_BC = I must be said out loud";
  EXPECT_TRUE(has_problem(*log, "assumed", "imu.txt")) << "so must the IMU noise figures";
  EXPECT_GT(r.imu.gyro_random_walk_rad_s2_sqrthz, 0.0);
  EXPECT_GT(r.imu.acc_noise_density_mps2_sqrthz, 0.0);

  const auto all = read_all(*log);
  const auto imu = of_type(all, RecordType::kImu);
  const auto rgb = of_type(all, RecordType::kRgb);
  const auto depth = of_type(all, RecordType::kDepth);
  const auto gt = of_type(all, RecordType::kGroundTruth);
  ASSERT_EQ(imu.size(), 30u);
  ASSERT_EQ(rgb.size(), 4u);
  ASSERT_EQ(depth.size(), 4u);
  ASSERT_EQ(gt.size(), 4u);
  EXPECT_EQ(imu[3].imu.t_ns, 10'015'000'000);
  EXPECT_EQ(imu[3].imu.gyro_rps[0], 0.3) << "columns are t gx gy gz ax ay az";
  EXPECT_EQ(imu[3].imu.acc_mps2[2], 9.83);
  EXPECT_EQ(rgb[2].image.format, PixelFormat::kRgb8);
  EXPECT_EQ(rgb[2].image.pixels[0], 30) << "BGR on disk becomes R G B";
  EXPECT_EQ(rgb[2].image.pixels[2], 20);
  EXPECT_EQ(depth[1].image.t_ns, rgb[1].image.t_ns);
  EXPECT_DOUBLE_EQ(depth_m(depth[1].image, 0, r.depth.scale_m_per_unit), 5001.0 / 5000.0);
  EXPECT_EQ(gt[3].gt.p_WB[0], 3.0);
  EXPECT_EQ(gt[3].gt.q_WB[0], 1.0) << "TUM order qx qy qz qw becomes w x y z";
  for (size_t i = 1; i < all.size(); ++i) {
    const auto t = [](const drivers::LogRecord& x) {
      return x.type == RecordType::kImu           ? x.imu.t_ns
             : x.type == RecordType::kGroundTruth ? x.gt.t_ns
                                                  : x.image.t_ns;
    };
    EXPECT_LE(t(all[i - 1]), t(all[i])) << "record " << i;
  }
}

TEST(Eth3dReader, AssociatesWithoutAssociatedTxt) {
  const std::string dir = write_eth3d_fixture("eth3d_noassoc", false);
  drivers::Eth3dReader log(dir);
  EXPECT_EQ(log.associated_pairs(), 4u);
  EXPECT_EQ(log.depth_count(), 4u);
}

TEST(Eth3dReader, MissingCalibrationNamesTheFieldOrTakesTheRig) {
  const std::string dir = write_eth3d_fixture("eth3d_nocalib");
  std::filesystem::remove(dir + "/calibration.txt");
  try {
    drivers::Eth3dReader log(dir);
    FAIL() << "expected an error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("calibration.txt"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("fx fy cx cy"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("--rig"), std::string::npos) << e.what();
  }
  const Rig rig = small_rig();
  drivers::Eth3dReader log(dir, &rig);
  EXPECT_EQ(log.rig().rgb.fx, rig.rgb.fx);
  EXPECT_EQ(log.rig().T_BC, rig.T_BC);
  EXPECT_EQ(log.rig().depth.scale_m_per_unit, 1.0 / 5000.0) << "the files' depth units win over the rig's";
  EXPECT_FALSE(has_problem(log, "assumed", "")) << "the rig gives T_BC";
}

TEST(Eth3dReader, BadCalibrationLineIsAnErrorWithFileAndLine) {
  const std::string dir = write_eth3d_fixture("eth3d_badcalib");
  write_text(dir + "/calibration.txt", "# fx fy cx cy\n726.28 726.28 354.6\n");
  try {
    drivers::Eth3dReader log(dir);
    FAIL() << "expected an error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("calibration.txt:2"), std::string::npos) << e.what();
  }
}

TEST(Eth3dReader, MalformedRowsAreReportedWithFileAndLineNeverACrash) {
  const std::string dir = write_eth3d_fixture("eth3d_malformed");
  // imu.txt: a row missing columns (line 3), a duplicate stamp (line 5), an unsorted one (line 6).
  write_text(dir + "/imu.txt",
             "# timestamp gx gy gz ax ay az\n"
             "10.000 0 0 0 0 0 9.8\n"
             "10.005 0 0 0 0 0\n"
             "10.010 0 0 0 0 0 9.8\n"
             "10.010 1 1 1 0 0 9.8\n"
             "10.007 0 0 0 0 0 9.8\n"
             "10.020 x 0 0 0 0 9.8\n");
  // associated.txt: a listed image that does not exist, a duplicate row.
  std::string assoc;
  {
    std::ifstream f(dir + "/associated.txt");
    std::string l;
    while (std::getline(f, l)) assoc += l + "\n";
  }
  assoc +=
      "10.200000 rgb/nothere.png 10.200000 depth/nothere.png\n10.200000 rgb/x.png 10.200000 depth/x.png\n";
  write_text(dir + "/associated.txt", assoc);
  // An 8-bit PNG where 16-bit depth belongs.
  cv::imwrite(dir + "/depth/10.080000.png", cv::Mat(6, 8, CV_8UC1, cv::Scalar(7)));

  drivers::Eth3dReader log(dir);
  const auto all = read_all(log);
  EXPECT_TRUE(has_problem(log, "bad-row", "imu.txt:3")) << problems_text(log);
  EXPECT_TRUE(has_problem(log, "bad-row", "imu.txt:7")) << problems_text(log);
  EXPECT_TRUE(has_problem(log, "duplicate", "imu.txt:5")) << problems_text(log);
  EXPECT_TRUE(has_problem(log, "time-order", "imu.txt:6")) << problems_text(log);
  EXPECT_TRUE(has_problem(log, "missing-file", "associated.txt:5")) << problems_text(log);
  EXPECT_TRUE(has_problem(log, "duplicate", "associated.txt:6")) << problems_text(log);
  EXPECT_TRUE(has_problem(log, "bad-image", "associated.txt:3")) << problems_text(log);
  const auto imu = of_type(all, RecordType::kImu);
  ASSERT_EQ(imu.size(), 3u);  // lines 2, 6 and 4, in time order
  for (size_t i = 1; i < imu.size(); ++i) EXPECT_LT(imu[i - 1].imu.t_ns, imu[i].imu.t_ns);
  EXPECT_EQ(of_type(all, RecordType::kDepth).size(), 3u) << "the 8-bit depth frame is skipped";
  // Problems are reported once, also across rewinds.
  const size_t n = log.problems().size();
  read_all(log);
  EXPECT_EQ(log.problems().size(), n);
}

TEST(Eth3dExport, KlogToEth3dToKlogKeepsWhatTheFormatHolds) {
  const std::string dir = temp_dir("eth3d_roundtrip");
  write_small_klog(dir + "/a.klog");
  drivers::KlogReader a(dir + "/a.klog");
  const auto st = drivers::export_eth3d(a, dir + "/eth3d");
  EXPECT_EQ(st.imu, 200u);
  EXPECT_EQ(st.rgb, 10u);
  EXPECT_EQ(st.depth, 10u);
  EXPECT_EQ(st.ground_truth, 50u);

  const Rig rig = a.rig();
  drivers::Eth3dReader b(dir + "/eth3d", &rig);  // T_BC, IMU noise: not in the format, from the rig
  EXPECT_TRUE(b.problems().empty()) << problems_text(b);
  const auto ra = read_all(a), rb = read_all(b);
  const auto ia = of_type(ra, RecordType::kImu), ib = of_type(rb, RecordType::kImu);
  ASSERT_EQ(ia.size(), ib.size());
  for (size_t i = 0; i < ia.size(); ++i) {
    EXPECT_EQ(ia[i].imu.t_ns, ib[i].imu.t_ns);
    EXPECT_EQ(ia[i].imu.gyro_rps, ib[i].imu.gyro_rps);
    EXPECT_EQ(ia[i].imu.acc_mps2, ib[i].imu.acc_mps2);
  }
  const auto ca = of_type(ra, RecordType::kRgb), cb = of_type(rb, RecordType::kRgb);
  ASSERT_EQ(ca.size(), cb.size());
  for (size_t i = 0; i < ca.size(); ++i) {
    EXPECT_EQ(ca[i].image.t_ns, cb[i].image.t_ns);
    EXPECT_EQ(ca[i].image.pixels, cb[i].image.pixels);
  }
  const auto da = of_type(ra, RecordType::kDepth), db = of_type(rb, RecordType::kDepth);
  ASSERT_EQ(da.size(), db.size());
  for (size_t i = 0; i < da.size(); ++i) {
    EXPECT_EQ(da[i].image.t_ns, db[i].image.t_ns);
    for (size_t k = 0; k < 48; ++k)
      EXPECT_NEAR(depth_m(da[i].image, k, 0.001), depth_m(db[i].image, k, b.rig().depth.scale_m_per_unit),
                  1e-12);
  }
  // Ground truth travels as the camera pose and comes back as the body pose.
  const auto ga = of_type(ra, RecordType::kGroundTruth), gb = of_type(rb, RecordType::kGroundTruth);
  ASSERT_EQ(ga.size(), gb.size());
  for (size_t i = 0; i < ga.size(); ++i) {
    EXPECT_EQ(ga[i].gt.t_ns, gb[i].gt.t_ns);
    for (int k = 0; k < 3; ++k) EXPECT_NEAR(ga[i].gt.p_WB[k], gb[i].gt.p_WB[k], 1e-12);
    // q and -q are one rotation; the reader returns w >= 0.
    double dot = 0;
    for (int k = 0; k < 4; ++k) dot += ga[i].gt.q_WB[k] * gb[i].gt.q_WB[k];
    for (int k = 0; k < 4; ++k) EXPECT_NEAR(ga[i].gt.q_WB[k], (dot < 0 ? -1 : 1) * gb[i].gt.q_WB[k], 1e-12);
  }
  const Rig& rb_rig = b.rig();
  EXPECT_EQ(rb_rig.rgb.fx, rig.rgb.fx);
  EXPECT_EQ(rb_rig.rgb.fy, rig.rgb.fy);
  EXPECT_EQ(rb_rig.rgb.cx, rig.rgb.cx);
  EXPECT_EQ(rb_rig.rgb.cy, rig.rgb.cy);
  EXPECT_EQ(rb_rig.rgb.width, rig.rgb.width);
  EXPECT_EQ(rb_rig.T_BC, rig.T_BC);

  // .klog -> ETH3D -> .klog -> ETH3D -> .klog: the second trip changes nothing at all. (With the
  // body at the camera, so no pose is re-composed in floating point.)
  Rig at_camera = small_rig();
  at_camera.T_BC = kIdentity4;
  at_camera.depth.scale_m_per_unit = 1.0 / 5000.0;
  write_small_klog(dir + "/i.klog", at_camera);
  auto to_klog = [](drivers::LogSource& s, const std::string& path) {
    drivers::KlogWriter w;
    w.open(path, s.rig());
    for (const auto& r : read_all(s)) {
      if (r.type == RecordType::kImu)
        w.write_imu(r.imu);
      else if (r.type == RecordType::kGroundTruth)
        w.write_ground_truth(r.gt);
      else
        w.write_image(r.type, r.image);
    }
  };
  drivers::KlogReader ki(dir + "/i.klog");
  drivers::export_eth3d(ki, dir + "/eth3d_i");
  drivers::Eth3dReader bi(dir + "/eth3d_i", &at_camera);
  to_klog(bi, dir + "/b.klog");
  drivers::KlogReader kb(dir + "/b.klog");
  drivers::export_eth3d(kb, dir + "/eth3d_b");
  drivers::Eth3dReader ci(dir + "/eth3d_b", &at_camera);
  to_klog(ci, dir + "/c.klog");
  const auto bytes = [](const std::string& p) {
    std::ifstream f(p, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(f), {});
  };
  EXPECT_GT(bytes(dir + "/b.klog").size(), 10000u);
  EXPECT_EQ(bytes(dir + "/b.klog"), bytes(dir + "/c.klog"));
  // And against the original: every IMU sample, image and pose bit-identical.
  const auto ri = read_all(ki), rbi = read_all(bi);
  ASSERT_EQ(ri.size(), rbi.size());
  for (size_t i = 0; i < ri.size(); ++i) {
    ASSERT_EQ(ri[i].type, rbi[i].type) << i;
    if (ri[i].type == RecordType::kImu) {
      EXPECT_EQ(ri[i].imu.gyro_rps, rbi[i].imu.gyro_rps);
      EXPECT_EQ(ri[i].imu.acc_mps2, rbi[i].imu.acc_mps2);
    } else if (ri[i].type == RecordType::kGroundTruth) {
      EXPECT_EQ(ri[i].gt.p_WB, rbi[i].gt.p_WB);
      EXPECT_EQ(ri[i].gt.q_WB, rbi[i].gt.q_WB);
    } else {
      EXPECT_EQ(ri[i].image.pixels, rbi[i].image.pixels);
    }
  }
}

}  // namespace
}  // namespace kestrel::test

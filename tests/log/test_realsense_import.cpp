// `rs-enumerate-devices -c` -> Rig (drivers/rig realsense_import.hpp): every
// mapped field, the distortion fit,
// missing sections named, bad input refused with file, line and field.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <string>

#include "kestrel/drivers/realsense_import.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "realsense_fixtures.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

std::string replace(std::string s, const std::string& from, const std::string& to) {
  const size_t at = s.find(from);
  if (at == std::string::npos)
    ADD_FAILURE() << "fixture lacks: " << from;
  else
    s.replace(at, from.size(), to);
  return s;
}

// Cuts the block starting at `header` up to the next blank line after `lines` lines.
std::string cut_block(std::string s, const std::string& header, int lines) {
  size_t at = s.find(header);
  if (at == std::string::npos) {
    ADD_FAILURE() << "fixture lacks: " << header;
    return s;
  }
  size_t end = at;
  for (int i = 0; i < lines && end != std::string::npos; ++i) end = s.find('\n', end + 1);
  s.erase(at, end == std::string::npos ? std::string::npos : end + 1 - at);
  return s;
}

Rig base() {
  Rig r;
  r.name = "base";
  r.camera_rate_hz = 30;
  r.imu.acc_random_walk_mps3_sqrthz = 3e-3;
  r.imu.gyro_random_walk_rad_s2_sqrthz = 2e-5;
  r.imu.acc_noise_density_mps2_sqrthz = 1e-2;
  r.imu.gyro_noise_density_rad_s_sqrthz = 1e-3;
  return r;
}

std::string error_of(const std::string& dump, const drivers::RealSenseImportOptions& o = {}) {
  try {
    drivers::import_realsense_text(dump, "d435i.txt", o, base());
  } catch (const std::runtime_error& e) {
    return e.what();
  }
  return "(no error)";
}

Mat4d mul(const Mat4d& a, const Mat4d& b) {
  Mat4d c{};
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j)
      for (int k = 0; k < 4; ++k) c[4 * i + j] += a[4 * i + k] * b[4 * k + j];
  return c;
}

TEST(RealSenseImport, DumpParsesEveryBlock) {
  const drivers::RealSenseDump d = drivers::parse_realsense_dump(kRealSenseD435iDump, "d435i.txt");
  EXPECT_EQ(d.device_name, "Intel RealSense D435I");
  EXPECT_EQ(d.serial, "843112070123");
  EXPECT_EQ(d.intrinsics.size(), 6u);
  EXPECT_EQ(d.motion.size(), 2u);
  EXPECT_EQ(d.extrinsics.size(), 11u);
  const drivers::RsIntrinsics* c = d.find("Color", 1280, 720);
  ASSERT_NE(c, nullptr);
  EXPECT_DOUBLE_EQ(c->fx, 923.844299316406);
  EXPECT_DOUBLE_EQ(c->ppy, 360.937042236328);
  EXPECT_EQ(c->model, "Inverse Brown Conrady");
  EXPECT_EQ(c->formats, "{RGB8/RGBA8/BGR8/BGRA8/Y16/YUYV}");
  const drivers::RsExtrinsics* pose = d.find_extrinsics("Depth", "Pose");
  ASSERT_NE(pose, nullptr);
  EXPECT_FALSE(pose->available);  // "N/A"
  const drivers::RsMotionIntrinsics* g = d.find_motion("Gyro");
  ASSERT_NE(g, nullptr);
  EXPECT_TRUE(g->has_sensitivity);
  EXPECT_DOUBLE_EQ(g->noise_variances[1], 1.19e-5);
  EXPECT_EQ(d.sizes_of("Depth"), "640x480, 848x480");
}

TEST(RealSenseImport, ColourCameraDepthRegisteredImuFromGyro) {
  const drivers::RealSenseImport imp = drivers::import_realsense_text(
      kRealSenseD435iDump, "d435i.txt", drivers::RealSenseImportOptions{}, base());
  const Rig& r = imp.rig;
  EXPECT_EQ(r.rgb.width, 640);
  EXPECT_DOUBLE_EQ(r.rgb.fx, 615.896179199219);
  EXPECT_DOUBLE_EQ(r.rgb.fy, 616.076416015625);
  EXPECT_DOUBLE_EQ(r.rgb.cx, 321.17333984375);
  EXPECT_DOUBLE_EQ(r.rgb.cy, 240.62467956543);
  EXPECT_EQ(r.rgb.distortion, DistortionModel::kNone);  // all-zero Inverse Brown Conrady
  ASSERT_TRUE(r.depth_camera.present);
  EXPECT_DOUBLE_EQ(r.depth_camera.intrinsics.fx, 384.902587890625);
  EXPECT_EQ(r.depth_camera.intrinsics.width, 640);
  // T_CD is Depth -> Color as printed (row by row), p_C = T_CD p_D.
  EXPECT_NEAR(r.depth_camera.T_CD[3], 0.0147160086780787, 1e-12);
  EXPECT_NEAR(r.depth_camera.T_CD[1], -0.00590259, 2e-6);  // row 0, column 1
  EXPECT_NEAR(r.depth_camera.T_CD[4], 0.00589996, 2e-6);   // row 1, column 0
  // T_BC = (Gyro -> Color)^-1: composed with the printed transform it is the identity.
  const Mat4d T_CG = {0.999982,   -0.00590259, -0.00108582, 0.020278759963896,
                      0.00589996, 0.99998,     -0.00240645, -0.00490168678215574,
                      0.0011,     0.0024,      0.999997,    -0.0113540282909766,
                      0,          0,           0,           1};
  const Mat4d I = mul(r.T_BC, T_CG);
  for (int i = 0; i < 16; ++i) EXPECT_NEAR(I[i], kIdentity4[i], 2e-5) << i;
  // The camera's origin in the IMU frame: -t_DG - R_CD^T t_CD (the fixture's Gyro -> Depth is (0.00552,
  // -0.0051, -0.01174) with no rotation).
  EXPECT_NEAR(r.T_BC[3], -0.00552 - 0.014716, 1e-4);
  EXPECT_NEAR(r.T_BC[7], 0.0051 - 0.000137, 1e-4);
  EXPECT_NEAR(r.T_BC[11], 0.01174 - 0.000392, 1e-4);
  // Noise: sqrt(variance / rate).
  EXPECT_NEAR(r.imu.acc_noise_density_mps2_sqrthz, std::sqrt(5.4e-4 / 250), 1e-12);
  EXPECT_NEAR(r.imu.gyro_noise_density_rad_s_sqrthz, std::sqrt(1.19e-5 / 200), 1e-12);
  EXPECT_DOUBLE_EQ(r.imu_rate_hz, 200);
  // From the base rig, and named.
  EXPECT_DOUBLE_EQ(r.imu.acc_random_walk_mps3_sqrthz, 3e-3);
  EXPECT_EQ(r.name, "Intel RealSense D435I 843112070123");
  EXPECT_TRUE(imp.missing.empty());
  std::string notes;
  for (const std::string& n : imp.notes) notes += n + "\n";
  for (const char* what :
       {"random walks", "depth unit", "time_offset_cam_imu_ns", "camera.rate_hz", "Infrared 1"})
    EXPECT_NE(notes.find(what), std::string::npos) << what << " not named in:\n" << notes;
  EXPECT_TRUE(drivers::rig_equal(drivers::rig_from_yaml(drivers::rig_to_yaml(r), "x"), r));
}

TEST(RealSenseImport, InfraredCameraHasDepthInItsFrame) {
  drivers::RealSenseImportOptions o;
  o.camera = "Infrared 1";
  o.width = 848;
  o.height = 480;
  const drivers::RealSenseImport imp =
      drivers::import_realsense_text(kRealSenseD435iDump, "d435i.txt", o, base());
  EXPECT_FALSE(imp.rig.depth_camera.present);
  EXPECT_DOUBLE_EQ(imp.rig.rgb.fx, 427.877685546875);
  EXPECT_NEAR(imp.rig.T_BC[3], -0.00552, 1e-9);  // Gyro -> Infrared 1 inverted: no rotation
  EXPECT_NEAR(imp.rig.T_BC[7], 0.0051, 1e-9);
  EXPECT_NEAR(imp.rig.T_BC[11], 0.01174, 1e-9);
}

TEST(RealSenseImport, InverseBrownConradyFittedAsRadtan) {
  const drivers::RealSenseImport imp = drivers::import_realsense_text(
      kRealSenseD455Dump, "d455.txt", drivers::RealSenseImportOptions{}, base());
  const CameraIntrinsics& c = imp.rig.rgb;
  ASSERT_EQ(c.distortion, DistortionModel::kRadTan);
  std::string notes;
  for (const std::string& n : imp.notes) notes += n + "\n";
  EXPECT_NE(notes.find("\"Inverse Brown Conrady\" fitted as radtan"), std::string::npos) << notes;
  // Independent check: pixels deprojected by librealsense's inverse model
  // (distorted -> undistorted), projected again by the fitted radtan, land
  // back on themselves.
  const double k[5] = {-0.0552862286567688, 0.0660683289170265, -0.000686826137825847, 0.000671613309532404,
                       -0.0212168209254742};
  double worst = 0;
  for (double px : {10.0, 160.0, 320.0, 480.0, 630.0})
    for (double py : {10.0, 120.0, 240.0, 360.0, 470.0}) {
      const double x = (px - c.cx) / c.fx, y = (py - c.cy) / c.fy, r2 = x * x + y * y;
      const double f = 1 + k[0] * r2 + k[1] * r2 * r2 + k[4] * r2 * r2 * r2;
      const double ux = x * f + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x);
      const double uy = y * f + 2 * k[3] * x * y + k[2] * (r2 + 2 * y * y);
      const double u2 = ux * ux + uy * uy;
      const double g = 1 + c.dist[0] * u2 + c.dist[1] * u2 * u2 + c.dist[4] * u2 * u2 * u2;
      const double dx = ux * g + 2 * c.dist[2] * ux * uy + c.dist[3] * (u2 + 2 * ux * ux);
      const double dy = uy * g + 2 * c.dist[3] * ux * uy + c.dist[2] * (u2 + 2 * uy * uy);
      worst = std::max(worst, std::hypot((dx * c.fx + c.cx) - px, (dy * c.fy + c.cy) - py));
    }
  EXPECT_LT(worst, 0.25) << "px";
  EXPECT_GT(std::abs(c.dist[0]), 0.01);  // a real fit, not zeros
}

TEST(RealSenseImport, MissingSectionsAreNamed) {
  // No IMU at all (a D435): imported, with the missing sections listed.
  std::string dump = kRealSenseD435iDump;
  dump = cut_block(dump, "Motion Intrinsic of \"Accel\"", 8);
  dump = cut_block(dump, "Motion Intrinsic of \"Gyro\"", 8);
  for (const char* from : {"Accel", "Gyro"})
    for (const char* to : {"Color", "Infrared 1"})
      dump = cut_block(dump, std::string("Extrinsic from \"") + from + "\"\t  To\t  \"" + to + "\"", 7);
  const drivers::RealSenseImport imp =
      drivers::import_realsense_text(dump, "d435.txt", drivers::RealSenseImportOptions{}, base());
  std::string missing;
  for (const std::string& m : imp.missing) missing += m + "\n";
  EXPECT_NE(missing.find("Extrinsic from \"Gyro\" To \"Color\""), std::string::npos) << missing;
  EXPECT_NE(missing.find("Motion Intrinsic of \"Accel\""), std::string::npos) << missing;
  EXPECT_NE(missing.find("Motion Intrinsic of \"Gyro\""), std::string::npos) << missing;
  EXPECT_DOUBLE_EQ(imp.rig.imu.acc_noise_density_mps2_sqrthz, 1e-2);  // kept from the base
  // What the rig cannot do without is an error naming the dump and the section.
  const std::string no_dc = cut_block(kRealSenseD435iDump, "Extrinsic from \"Depth\"\t  To\t  \"Color\"", 7);
  EXPECT_EQ(error_of(no_dc),
            "d435i.txt: no Extrinsic from Depth To Color section (needed to register depth to colour)");
  drivers::RealSenseImportOptions big;
  big.width = 1920;
  big.height = 1080;
  EXPECT_EQ(error_of(kRealSenseD435iDump, big),
            "d435i.txt: no intrinsics of \"Color\" at 1920x1080 (the dump has: 640x480, 1280x720)");
  EXPECT_NE(
      error_of("Device info:\n    Name : \tx\n").find("is this the output of `rs-enumerate-devices -c`"),
      std::string::npos);
}

TEST(RealSenseImport, BadNumbersNameLineAndField) {
  const std::string bad =
      replace(kRealSenseD435iDump, "Fx:         \t615.896179199219", "Fx:         \tfast");
  EXPECT_EQ(error_of(bad), "d435i.txt:14: Color 640x480.Fx: expected a finite number, got \"fast\"");
  const std::string neg =
      replace(kRealSenseD435iDump, "Fy:         \t616.076416015625", "Fy:         \t-616");
  EXPECT_NE(error_of(neg).find("focal lengths must be > 0"), std::string::npos);
  const std::string rot =
      replace(kRealSenseD435iDump, "   0.999982        -0.00590259", "   0.5             -0.00590259");
  EXPECT_NE(error_of(rot).find("Rotation Matrix: the rotation is not orthonormal"), std::string::npos)
      << error_of(rot);
  const std::string shortrow =
      replace(kRealSenseD435iDump, "  Coeffs:     \t0  \t0  \t0  \t0  \t0  ", "  Coeffs: 0 0");
  EXPECT_NE(error_of(shortrow).find("Color 640x480.Coeffs: expected 5 numbers"), std::string::npos);
}

}  // namespace
}  // namespace kestrel::test

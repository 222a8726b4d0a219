// Kalibr's calibration files -> a rig (drivers/rig kalibr.hpp) and the command
// `kestrel calib import-kalibr`: fields mapped, T_cam_imu inverted, noise
// densities and the time shift carried, what is missing named. The Kalibr
// files are written here in Kalibr's own layout (no copied data).
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <string>

#include "kalibr_fixtures.hpp"
#include "kestrel/drivers/kalibr.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "run_command.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

Rig base() {
  Rig b;
  b.name = "base";
  b.camera_rate_hz = 30;
  b.depth.scale_m_per_unit = 0.001;
  b.imu.gyro_range_rps = 34.9;
  b.imu.acc_bias_tau_s = 300;
  return b;
}

std::string error_of(const std::string& camchain, const std::string& imu, const std::string& cam = "cam0") {
  try {
    drivers::import_kalibr_text(camchain, "camchain.yaml", imu, "imu.yaml", cam, base());
  } catch (const std::runtime_error& e) {
    return e.what();
  }
  return "";
}

std::string replace(std::string s, const std::string& a, const std::string& b) {
  const auto at = s.find(a);
  EXPECT_NE(at, std::string::npos) << a;
  if (at != std::string::npos) s.replace(at, a.size(), b);
  return s;
}

TEST(Kalibr, FieldsMappedTransformInvertedNoiseAndShiftCarried) {
  const drivers::KalibrImport imp =
      drivers::import_kalibr_text(kCamchain, "camchain.yaml", kImuYaml, "imu.yaml", "cam0", base());
  const Rig& r = imp.rig;
  EXPECT_EQ(r.rgb.width, 640);
  EXPECT_EQ(r.rgb.height, 480);
  EXPECT_DOUBLE_EQ(r.rgb.fx, 612.31);
  EXPECT_DOUBLE_EQ(r.rgb.fy, 611.87);
  EXPECT_DOUBLE_EQ(r.rgb.cx, 321.42);
  EXPECT_DOUBLE_EQ(r.rgb.cy, 238.15);
  EXPECT_EQ(r.rgb.distortion, DistortionModel::kRadTan);
  EXPECT_DOUBLE_EQ(r.rgb.dist[0], 0.0412);
  EXPECT_DOUBLE_EQ(r.rgb.dist[3], -0.00031);
  EXPECT_DOUBLE_EQ(r.rgb.dist[4], 0.0);
  // T_BC T_cam_imu = I: the camera's origin 4 cm ahead of the IMU, 1.5 cm left, 2 cm up,
  // and the optical axis (camera z) along the body's x.
  const double T_ci[16] = {0.01745240643728351, -0.9998476951563913, 0, 0.015, 0, 0, -1, 0.02,
                           0.9998476951563913,  0.01745240643728351, 0, -0.04, 0, 0, 0,  1};
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j) {
      double p = 0;
      for (int k = 0; k < 4; ++k) p += r.T_BC[4 * i + k] * T_ci[4 * k + j];
      EXPECT_NEAR(p, i == j ? 1.0 : 0.0, 1e-12) << i << "," << j;
    }
  EXPECT_NEAR(r.T_BC[3], 0.04, 1e-3);              // x: ahead
  EXPECT_NEAR(r.T_BC[7], 0.015, 1e-3);             // y: left
  EXPECT_NEAR(r.T_BC[11], 0.02, 1e-3);             // z: up
  EXPECT_NEAR(r.T_BC[2], 1.0, 1e-3);               // camera z -> body x
  EXPECT_EQ(r.time_offset_cam_imu_ns, 5'213'100);  // same sign as Kalibr's t_imu = t_cam + shift
  EXPECT_DOUBLE_EQ(r.imu.acc_noise_density_mps2_sqrthz, 1.86e-3);
  EXPECT_DOUBLE_EQ(r.imu.acc_random_walk_mps3_sqrthz, 4.33e-4);
  EXPECT_DOUBLE_EQ(r.imu.gyro_noise_density_rad_s_sqrthz, 1.87e-4);
  EXPECT_DOUBLE_EQ(r.imu.gyro_random_walk_rad_s2_sqrthz, 2.66e-5);
  EXPECT_DOUBLE_EQ(r.imu_rate_hz, 400.0);
  // What Kalibr lacks comes from the base rig, and is named.
  EXPECT_EQ(r.name, "base");
  EXPECT_DOUBLE_EQ(r.camera_rate_hz, 30.0);
  EXPECT_DOUBLE_EQ(r.imu.gyro_range_rps, 34.9);
  std::string notes;
  for (const std::string& n : imp.notes) notes += n + "\n";
  for (const char* field : {"depth:", "camera.rate_hz", "imu.acc_bias_tau_s", "gravity_mps2"})
    EXPECT_NE(notes.find(field), std::string::npos) << field << " not named in:\n" << notes;
  // A rig that writes and reads back exactly.
  EXPECT_TRUE(drivers::rig_equal(drivers::rig_from_yaml(drivers::rig_to_yaml(r), "x"), r));
}

TEST(Kalibr, ResultsFormatEquidistantAndDefaultsNamed) {
  std::string chain = replace(kCamchain, "distortion_model: radtan", "distortion_model: equidistant");
  chain = replace(chain, "  timeshift_cam_imu: 0.0052131\n", "");
  const std::string imu_results = std::string(
      "imu0:\n  T_i_b:\n  - [1.0, 0.0, 0.0, 0.0]\n  - [0.0, 1.0, 0.0, 0.0]\n"
      "  - [0.0, 0.0, 1.0, 0.0]\n  - [0.0, 0.0, 0.0, 1.0]\n"
      "  accelerometer_noise_density: 0.002\n"
      "  accelerometer_random_walk: 0.0003\n"
      "  gyroscope_noise_density: 0.0002\n"
      "  gyroscope_random_walk: 0.00002\n"
      "  model: calibrated\n  rostopic: /imu0\n  time_offset: 0.0\n");
  const drivers::KalibrImport imp =
      drivers::import_kalibr_text(chain, "camchain.yaml", imu_results, "imu-results.yaml", "cam0", base());
  EXPECT_EQ(imp.rig.rgb.distortion, DistortionModel::kEquidistant);
  EXPECT_DOUBLE_EQ(imp.rig.imu.gyro_noise_density_rad_s_sqrthz, 0.0002);
  EXPECT_EQ(imp.rig.time_offset_cam_imu_ns, 0);
  std::string notes;
  for (const std::string& n : imp.notes) notes += n + "\n";
  EXPECT_NE(notes.find("cam0.timeshift_cam_imu: missing"), std::string::npos) << notes;
  EXPECT_NE(notes.find("imu0.update_rate: missing"), std::string::npos) << notes;
}

TEST(Kalibr, MissingAndBadFieldsAreNamed) {
  EXPECT_EQ(error_of(kCamchain, kImuYaml, "cam1"),
            "camchain.yaml: cam1: no such camera in the chain (it has: cam0)");
  const std::string no_T =
      replace(kCamchain,
              "  T_cam_imu:\n  - [0.01745240643728351, -0.9998476951563913, 0.0, 0.015]\n"
              "  - [0.0, 0.0, -1.0, 0.02]\n"
              "  - [0.9998476951563913, 0.01745240643728351, 0.0, -0.04]\n"
              "  - [0.0, 0.0, 0.0, 1.0]\n",
              "");
  EXPECT_EQ(error_of(no_T, kImuYaml).rfind("camchain.yaml: cam0.T_cam_imu: missing", 0), 0u)
      << error_of(no_T, kImuYaml);
  EXPECT_EQ(error_of(replace(kCamchain, "  intrinsics: [612.31, 611.87, 321.42, 238.15]\n", ""), kImuYaml),
            "camchain.yaml: cam0.intrinsics: missing ([fu, fv, pu, pv] in pixels)");
  EXPECT_EQ(
      error_of(replace(kCamchain, "[612.31, 611.87, 321.42, 238.15]", "[612.31, 611.87, 321.42]"), kImuYaml),
      "camchain.yaml: cam0.intrinsics: expected a list of 4 numbers");
  // fuzz_kalibr: a resolution past int was cast to int (undefined behaviour).
  EXPECT_EQ(error_of(replace(kCamchain, "resolution: [640, 480]", "resolution: [4.8e97, 480]"), kImuYaml),
            "camchain.yaml: cam0.resolution: expected two whole numbers from 1 to 32768");
  EXPECT_EQ(error_of(replace(kCamchain, "resolution: [640, 480]", "resolution: [0, 480]"), kImuYaml),
            "camchain.yaml: cam0.resolution: expected two whole numbers from 1 to 32768");
  // ... and a negative focal length was imported into a rig no rig file accepts.
  EXPECT_EQ(error_of(replace(kCamchain, "611.87", "-0.0311"), kImuYaml),
            "camchain.yaml: cam0.intrinsics: focal lengths fu, fv must be > 0");
  EXPECT_EQ(error_of(replace(kCamchain, "612.31,", "abc,"), kImuYaml),
            "camchain.yaml: cam0.intrinsics[0]: expected a finite number, got \"abc\"");
  EXPECT_EQ(error_of(replace(kCamchain, "distortion_model: radtan", "distortion_model: fov"), kImuYaml),
            "camchain.yaml: cam0.distortion_model: \"fov\": expected radtan, equidistant or none");
  EXPECT_EQ(error_of(replace(kCamchain, "camera_model: pinhole", "camera_model: omni"), kImuYaml),
            "camchain.yaml: cam0.camera_model: \"omni\": Kestrel's camera is pinhole");
  EXPECT_NE(error_of(replace(kCamchain, "- [0.0, 0.0, -1.0, 0.02]", "- [0.0, 0.0, -1.2, 0.02]"), kImuYaml)
                .find("cam0.T_cam_imu: the rotation is not orthonormal"),
            std::string::npos);
  EXPECT_EQ(error_of(kCamchain, replace(kImuYaml, "gyroscope_noise_density:     1.87e-04", "")),
            "imu.yaml: gyroscope_noise_density: missing (rad/s/sqrt(Hz), continuous time)");
  EXPECT_EQ(error_of(kCamchain, replace(kImuYaml, "1.86e-03", "-1")),
            "imu.yaml: accelerometer_noise_density: must be > 0");
  EXPECT_NE(error_of("cam0: [", kImuYaml).find("YAML syntax error"), std::string::npos);
  EXPECT_EQ(error_of("cam0: [", kImuYaml).rfind("camchain.yaml:", 0), 0u);
}

TEST(Kalibr, CommandWritesARigTheDriversLoad) {
  const std::string dir = temp_dir("kalibr_cli");
  std::ofstream(dir + "/camchain-imucam.yaml") << kCamchain;
  std::ofstream(dir + "/imu.yaml") << kImuYaml;
  const std::string base_cfg = std::string(KESTREL_SOURCE_DIR) + "/configs/realsense_v4l2_bmx055_usb.yaml";
  const CmdResult r = run_kestrel("calib import-kalibr " + dir + "/camchain-imucam.yaml " + dir +
                                  "/imu.yaml --base " + base_cfg + " --out " + dir + "/my_rig.yaml");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("time offset 5.213 ms"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("depth: not in Kalibr's files"), std::string::npos) << r.out;
  const Rig rig = drivers::load_rig_file(dir + "/my_rig.yaml");
  EXPECT_DOUBLE_EQ(rig.rgb.fx, 612.31);
  EXPECT_EQ(rig.name, "d435-bmx055-usb");  // from the base config's rig:
  EXPECT_DOUBLE_EQ(rig.depth.min_range_m, 0.2);
  // A live config naming the file (`rig: my_rig.yaml`) gets this rig.
  std::ifstream in(base_cfg);
  std::string cfg((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto a = cfg.find("\nrig:\n"), b = cfg.find("\ndrivers:\n");
  ASSERT_NE(a, std::string::npos);
  ASSERT_NE(b, std::string::npos);
  cfg = cfg.substr(0, a) + "\nrig: my_rig.yaml" + cfg.substr(b);
  std::ofstream(dir + "/live.yaml") << cfg;
  const CmdResult p = run_kestrel("run --config " + dir + "/live.yaml --print-config");
  EXPECT_EQ(p.code, 0) << p.out;
  // Usage: a missing file is an error naming it, no rig written.
  const CmdResult bad =
      run_kestrel("calib import-kalibr " + dir + "/nope.yaml " + dir + "/imu.yaml --out " + dir + "/x.yaml");
  EXPECT_EQ(bad.code, 1) << bad.out;
  EXPECT_NE(bad.out.find("nope.yaml: cannot open"), std::string::npos) << bad.out;
  EXPECT_EQ(run_kestrel("calib import-kalibr " + dir + "/camchain-imucam.yaml").code, 2);
}

}  // namespace
}  // namespace kestrel::test

// Issue 48: a two-camera chain imported from cam0 is a stereo rig; cam1's T_cam_imu gives T_BC1.
namespace kestrel::test {
namespace {

TEST(Kalibr, TwoCameraChainBecomesAStereoRigThatRoundTrips) {
  const std::string cam1 = R"(cam1:
  T_cam_imu:
  - [0.01745240643728351, -0.9998476951563913, 0.0, -0.035]
  - [0.0, 0.0, -1.0, 0.02]
  - [0.9998476951563913, 0.01745240643728351, 0.0, -0.04]
  - [0.0, 0.0, 0.0, 1.0]
  T_cn_cnm1:
  - [1.0, 0.0, 0.0, -0.05]
  - [0.0, 1.0, 0.0, 0.0]
  - [0.0, 0.0, 1.0, 0.0]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: pinhole
  distortion_coeffs: [0.01, -0.02, 0.0, 0.0]
  distortion_model: equidistant
  intrinsics: [600.5, 600.25, 320.0, 240.5]
  resolution: [640, 480]
  timeshift_cam_imu: 0.0052131
)";
  const drivers::KalibrImport imp = drivers::import_kalibr_text(
      std::string(kCamchain) + cam1, "camchain.yaml", kImuYaml, "imu.yaml", "cam0", base());
  const Rig& r = imp.rig;
  ASSERT_TRUE(r.stereo.present);
  EXPECT_DOUBLE_EQ(r.stereo.intrinsics.fx, 600.5);
  EXPECT_EQ(r.stereo.intrinsics.distortion, DistortionModel::kEquidistant);
  EXPECT_DOUBLE_EQ(r.stereo.intrinsics.dist[1], -0.02);
  // cam1 sits 5 cm further along the cameras' x, which is the body's -y here.
  EXPECT_NEAR(r.stereo.T_BC1[7] - r.T_BC[7], -0.05, 1e-3);
  EXPECT_NEAR(r.stereo.T_BC1[3], r.T_BC[3], 1e-3);
  // The rig file carries the pair unchanged.
  EXPECT_TRUE(drivers::rig_equal(drivers::rig_from_yaml(drivers::rig_to_yaml(r), "rt"), r));
  // Importing cam1 itself stays a monocular rig.
  EXPECT_FALSE(drivers::import_kalibr_text(std::string(kCamchain) + cam1, "camchain.yaml", kImuYaml,
                                           "imu.yaml", "cam1", base())
                   .rig.stereo.present);
  // A bad field of cam1 is named as cam1's.
  EXPECT_NE(error_of(std::string(kCamchain) + replace(cam1, "[640, 480]", "[640]"), kImuYaml)
                .find("cam1.resolution"),
            std::string::npos);
}

}  // namespace
}  // namespace kestrel::test

// Kalibr's camchain + imu files -> Rig. Every number goes through the text
// layer so a bad one names its file and key.
#include "kestrel/drivers/kalibr.hpp"

#include <yaml-cpp/yaml.h>

#include <cmath>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/drivers/text.hpp"

namespace kestrel::drivers {
namespace {

class Reader {
 public:
  explicit Reader(std::string where) : where_(std::move(where)) {}

  [[noreturn]] void fail(const std::string& field, const std::string& msg) const {
    throw std::runtime_error(where_ + ": " + field + ": " + msg);
  }

  YAML::Node load(const std::string& text) const {
    try {
      YAML::Node n = YAML::Load(text);
      if (!n.IsMap()) throw std::runtime_error(where_ + ": expected a YAML mapping (a Kalibr file)");
      return n;
    } catch (const YAML::ParserException& e) {
      throw std::runtime_error(where_ + ":" + std::to_string(e.mark.line + 1) +
                               ": YAML syntax error: " + e.msg);
    }
  }

  double number(const YAML::Node& n, const std::string& field) const {
    if (!n.IsScalar()) fail(field, "expected a number");
    double v = 0;
    if (!text::parse_finite_f64(n.Scalar(), v))
      fail(field, "expected a finite number, got \"" + n.Scalar() + "\"");
    return v;
  }

  std::vector<double> numbers(const YAML::Node& n, const std::string& field, std::size_t count) const {
    if (!n.IsSequence() || n.size() != count)
      fail(field, "expected a list of " + std::to_string(count) + " numbers");
    std::vector<double> v;
    for (std::size_t i = 0; i < count; ++i) v.push_back(number(n[i], field + "[" + std::to_string(i) + "]"));
    return v;
  }

  // A 4x4 as Kalibr writes it (a list of four rows), rigid (rotation checked).
  Mat4d transform(const YAML::Node& n, const std::string& field) const {
    if (!n.IsSequence() || n.size() != 4) fail(field, "expected 4 rows of 4 numbers");
    Mat4d T{};
    for (int r = 0; r < 4; ++r) {
      const std::vector<double> row = numbers(n[r], field + "[" + std::to_string(r) + "]", 4);
      for (int c = 0; c < 4; ++c) T[4 * r + c] = row[c];
    }
    if (std::abs(T[12]) + std::abs(T[13]) + std::abs(T[14]) + std::abs(T[15] - 1.0) > 1e-9)
      fail(field, "last row must be [0, 0, 0, 1]");
    double worst = 0;
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        double d = 0;
        for (int k = 0; k < 3; ++k) d += T[4 * i + k] * T[4 * j + k];
        worst = std::max(worst, std::abs(d - (i == j ? 1.0 : 0.0)));
      }
    }
    // Kalibr prints about 8 significant digits.
    if (worst > 1e-5)
      fail(field, "the rotation is not orthonormal (R R^T - I up to " + std::to_string(worst) + ")");
    return T;
  }

  const std::string& where() const { return where_; }

 private:
  std::string where_;
};

}  // namespace

KalibrImport import_kalibr_text(const std::string& camchain_yaml, const std::string& camchain_name,
                                const std::string& imu_yaml, const std::string& imu_name,
                                const std::string& camera, const Rig& base) {
  KalibrImport out;
  Rig& rig = out.rig;
  rig = base;

  // ---- camera chain ----
  const Reader cr(camchain_name);
  const YAML::Node chain = cr.load(camchain_yaml);
  const YAML::Node cam = chain[camera];
  if (!cam) {
    std::string have;
    for (const auto& kv : chain) have += std::string(have.empty() ? "" : ", ") + kv.first.Scalar();
    cr.fail(camera,
            "no such camera in the chain (it has: " + (have.empty() ? std::string("none") : have) + ")");
  }
  // One camera of the chain: its intrinsics and camera -> body.
  auto read_camera = [&](const YAML::Node& cam, const std::string& name, CameraIntrinsics& ki) {
    if (!cam.IsMap()) cr.fail(name, "expected a mapping");
    const std::string c = name + ".";
    if (cam["camera_model"] && cam["camera_model"].Scalar() != "pinhole")
      cr.fail(c + "camera_model", "\"" + cam["camera_model"].Scalar() + "\": Kestrel's camera is pinhole");
    if (!cam["intrinsics"]) cr.fail(c + "intrinsics", "missing ([fu, fv, pu, pv] in pixels)");
    const std::vector<double> k = cr.numbers(cam["intrinsics"], c + "intrinsics", 4);
    ki.fx = k[0];
    ki.fy = k[1];
    ki.cx = k[2];
    ki.cy = k[3];
    // The rig file refuses these; an import must not write what cannot be read (found by fuzz_kalibr).
    if (k[0] <= 0 || k[1] <= 0) cr.fail(c + "intrinsics", "focal lengths fu, fv must be > 0");
    if (!cam["resolution"]) cr.fail(c + "resolution", "missing ([width, height] in pixels)");
    const std::vector<double> res = cr.numbers(cam["resolution"], c + "resolution", 2);
    // Bounded before the cast to int, which is undefined past INT_MAX (found by fuzz_kalibr).
    if (res[0] < 1 || res[1] < 1 || res[0] > 32768 || res[1] > 32768 || res[0] != std::floor(res[0]) ||
        res[1] != std::floor(res[1]))
      cr.fail(c + "resolution", "expected two whole numbers from 1 to 32768");
    ki.width = static_cast<int>(res[0]);
    ki.height = static_cast<int>(res[1]);
    ki.dist = {};
    const std::string model = cam["distortion_model"] ? cam["distortion_model"].Scalar() : std::string();
    if (model.empty() || model == "none") {
      ki.distortion = DistortionModel::kNone;
      if (model.empty()) out.notes.push_back(c + "distortion_model: missing: no distortion assumed");
    } else if (model == "radtan" || model == "equidistant") {
      if (!cam["distortion_coeffs"])
        cr.fail(c + "distortion_coeffs", "missing (4 numbers for " + model + ")");
      const std::vector<double> d = cr.numbers(cam["distortion_coeffs"], c + "distortion_coeffs", 4);
      ki.distortion = model == "radtan" ? DistortionModel::kRadTan : DistortionModel::kEquidistant;
      for (int i = 0; i < 4; ++i) ki.dist[i] = d[i];  // radtan: k1 k2 p1 p2 (k3 = 0); equidistant: k1..k4
    } else {
      cr.fail(c + "distortion_model", "\"" + model + "\": expected radtan, equidistant or none");
    }
    if (!cam["T_cam_imu"]) {
      cr.fail(c + "T_cam_imu",
              "missing: this is a camera-only chain; use the camchain-imucam-*.yaml of "
              "kalibr_calibrate_imu_camera");
    }
    return rigid_inverse(cr.transform(cam["T_cam_imu"], c + "T_cam_imu"));
  };
  rig.T_BC = read_camera(cam, camera, rig.rgb);
  const std::string c = camera + ".";
  // A two-camera chain imported from cam0 is a stereo rig: cam1 is its right camera (docs/stereo.md).
  rig.stereo = StereoCamera{};
  if (camera == "cam0" && chain["cam1"]) {
    rig.stereo.T_BC1 = read_camera(chain["cam1"], "cam1", rig.stereo.intrinsics);
    rig.stereo.present = true;
    out.notes.push_back("cam1: imported as the right camera of a stereo pair (stereo:); depth from matching");
  }
  if (cam["timeshift_cam_imu"]) {
    rig.time_offset_cam_imu_ns = static_cast<int64_t>(
        std::llround(1e9 * cr.number(cam["timeshift_cam_imu"], c + "timeshift_cam_imu")));
  } else {
    rig.time_offset_cam_imu_ns = 0;
    out.notes.push_back(c +
                        "timeshift_cam_imu: missing: time_offset_cam_imu_ns = 0 (estimate it: "
                        "window.estimate_time_offset, docs/own-sensors.md)");
  }

  // ---- IMU: Kalibr's input imu.yaml (top-level keys) or its results (imu0:) ----
  const Reader ir(imu_name);
  YAML::Node imu = ir.load(imu_yaml);
  std::string ip;
  if (!imu["accelerometer_noise_density"] && imu["imu0"] && imu["imu0"].IsMap()) {
    imu = imu["imu0"];
    ip = "imu0.";
  }
  auto density = [&](const char* key, const char* what) {
    if (!imu[key]) ir.fail(ip + key, std::string("missing (") + what + ")");
    const double v = ir.number(imu[key], ip + key);
    if (!(v > 0)) ir.fail(ip + key, "must be > 0");
    return v;
  };
  rig.imu.acc_noise_density_mps2_sqrthz =
      density("accelerometer_noise_density", "m/s^2/sqrt(Hz), continuous time");
  rig.imu.acc_random_walk_mps3_sqrthz = density("accelerometer_random_walk", "m/s^3/sqrt(Hz)");
  rig.imu.gyro_noise_density_rad_s_sqrthz =
      density("gyroscope_noise_density", "rad/s/sqrt(Hz), continuous time");
  rig.imu.gyro_random_walk_rad_s2_sqrthz = density("gyroscope_random_walk", "rad/s^2/sqrt(Hz)");
  if (imu["update_rate"]) {
    rig.imu_rate_hz = ir.number(imu["update_rate"], ip + "update_rate");
    if (!(rig.imu_rate_hz > 0)) ir.fail(ip + "update_rate", "must be > 0");
  } else {
    out.notes.push_back(ip + "update_rate: missing: imu.rate_hz " + text::fmt6(rig.imu_rate_hz) +
                        " from the base rig");
  }
  if (imu["T_i_b"]) {
    const Mat4d T = ir.transform(imu["T_i_b"], ip + "T_i_b");
    for (int i = 0; i < 16; ++i) {
      if (std::abs(T[i] - kIdentity4[i]) > 1e-9) {
        ir.fail(ip + "T_i_b",
                "not identity: Kestrel's body frame is this IMU (docs/frames.md); calibrate with it "
                "as Kalibr's reference IMU");
      }
    }
  }
  rig.T_BI = kIdentity4;

  // ---- what Kalibr has no place for ----
  out.notes.push_back("camera.rate_hz: not in Kalibr's files: " + text::fmt6(rig.camera_rate_hz) +
                      " Hz from the base rig");
  out.notes.push_back(
      "depth: not in Kalibr's files (depth is registered to the colour camera): scale_m_per_unit " +
      text::fmt6(rig.depth.scale_m_per_unit) + ", range " + text::fmt6(rig.depth.min_range_m) + ".." +
      text::fmt6(rig.depth.max_range_m) + " m, sigma_coeff_per_m " + text::fmt6(rig.depth.sigma_coeff_per_m) +
      " from the base rig");
  out.notes.push_back("imu.acc_bias_tau_s, gyro_range_rps, acc_range_mps2: not in Kalibr's files: " +
                      text::fmt6(rig.imu.acc_bias_tau_s) + " s, " + text::fmt6(rig.imu.gyro_range_rps) +
                      " rad/s, " + text::fmt6(rig.imu.acc_range_mps2) + " m/s^2 from the base rig");
  out.notes.push_back("gravity_mps2: not in Kalibr's files: " + text::fmt6(rig.gravity_mps2) +
                      " from the base rig");
  if (rig.name.empty()) rig.name = "kalibr-" + camera;
  // Whatever else the rig file checks (the base rig's fields included) is
  // checked here too, so the rig written by `calib import-kalibr` always loads.
  try {
    rig_from_yaml(rig_to_yaml(rig), "the imported rig");
  } catch (const std::runtime_error& e) {
    throw std::runtime_error(camchain_name + ", " + imu_name + ": " + e.what());
  }
  return out;
}

KalibrImport import_kalibr(const std::string& camchain_path, const std::string& imu_path,
                           const std::string& camera, const Rig& base) {
  return import_kalibr_text(text::read_file(camchain_path), camchain_path, text::read_file(imu_path),
                            imu_path, camera, base);
}

}  // namespace kestrel::drivers

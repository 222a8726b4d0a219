// Rig <-> YAML. Numbers are parsed from the scalar text by the text layer so
// that every failure can name its field, and printed with %.17g so that a
// round trip is exact.
#include "kestrel/drivers/rig_yaml.hpp"

#include <cmath>
#include <fstream>
#include <initializer_list>
#include <sstream>
#include <stdexcept>

#include "kestrel/drivers/text.hpp"

namespace kestrel::drivers {
namespace {

class Parser {
 public:
  Parser(std::string where, std::string prefix) : where_(std::move(where)), prefix_(std::move(prefix)) {}

  [[noreturn]] void fail(const std::string& field, const std::string& msg) const {
    const std::string f = prefix_ + field;
    throw std::runtime_error(where_ + ": " + (f.empty() ? "" : f + ": ") + msg);
  }

  void only_keys(const YAML::Node& map, const std::string& path,
                 std::initializer_list<const char*> keys) const {
    if (!map.IsMap()) fail(path, "expected a mapping");
    for (const auto& kv : map) {
      const std::string k = kv.first.Scalar();
      bool ok = false;
      for (const char* a : keys) ok = ok || k == a;
      if (!ok) {
        std::string list;
        for (const char* a : keys) list += std::string(list.empty() ? "" : ", ") + a;
        fail((path.empty() ? "" : path + ".") + k, "unknown key (expected one of: " + list + ")");
      }
    }
  }

  double number(const YAML::Node& n, const std::string& field) const {
    if (!n.IsScalar()) fail(field, "expected a number");
    const std::string& s = n.Scalar();
    double v = 0;
    if (!text::parse_f64(s, v)) fail(field, "expected a number, got \"" + s + "\"");
    if (!text::parse_finite_f64(s, v)) fail(field, "expected a finite number, got \"" + s + "\"");
    return v;
  }

  int64_t integer(const YAML::Node& n, const std::string& field) const {
    if (!n.IsScalar()) fail(field, "expected an integer");
    const std::string& s = n.Scalar();
    int64_t v = 0;
    if (!text::parse_i64(s, v)) fail(field, "expected an integer, got \"" + s + "\"");
    return v;
  }

  // Optional keys keep the Rig{} default when absent.
  void opt_number(const YAML::Node& map, const char* key, const std::string& path, double& v) const {
    if (map[key]) v = number(map[key], path + key);
  }
  void req_number(const YAML::Node& map, const char* key, const std::string& path, double& v) const {
    if (!map[key]) fail(path + key, "missing (required)");
    v = number(map[key], path + key);
  }

  void matrix(const YAML::Node& n, const std::string& field, Mat4d& m) const {
    if (!n.IsSequence() || n.size() != 16) fail(field, "expected a list of 16 numbers (4x4 row-major)");
    for (size_t i = 0; i < 16; ++i) m[i] = number(n[i], field + "[" + std::to_string(i) + "]");
    if (m[12] != 0 || m[13] != 0 || m[14] != 0 || m[15] != 1) fail(field, "last row must be 0 0 0 1");
    for (int a = 0; a < 3; ++a) {
      for (int b = 0; b < 3; ++b) {
        double dot = 0;
        for (int k = 0; k < 3; ++k) dot += m[4 * k + a] * m[4 * k + b];
        if (std::abs(dot - (a == b ? 1.0 : 0.0)) > 1e-5)
          fail(field, "rotation part is not orthonormal (column dot products off by more than 1e-5)");
      }
    }
  }

  void non_negative(double v, const std::string& field) const {
    if (v < 0) fail(field, "must be >= 0");
  }

 private:
  std::string where_;
  std::string prefix_;
};

std::string list(const double* v, size_t n, const char* indent) {
  std::string s = "[";
  for (size_t i = 0; i < n; ++i) {
    if (i > 0) s += (n == 16 && i % 4 == 0) ? std::string(",\n") + indent : std::string(", ");
    s += text::fmt17(v[i]);
  }
  return s + "]";
}

void intrinsics(const Parser& p, const YAML::Node& cam, const std::string& path, CameraIntrinsics& k) {
  const std::pair<const char*, int*> sizes[] = {{"width_px", &k.width}, {"height_px", &k.height}};
  for (const auto& [key, dst] : sizes) {
    if (!cam[key]) p.fail(path + key, "missing (required)");
    const int64_t v = p.integer(cam[key], path + key);
    if (v <= 0 || v > 32768) p.fail(path + key, "must be in 1..32768");
    *dst = static_cast<int>(v);
  }
  p.req_number(cam, "fx_px", path, k.fx);
  p.req_number(cam, "fy_px", path, k.fy);
  p.req_number(cam, "cx_px", path, k.cx);
  p.req_number(cam, "cy_px", path, k.cy);
  if (k.fx <= 0) p.fail(path + "fx_px", "must be > 0");
  if (k.fy <= 0) p.fail(path + "fy_px", "must be > 0");
  if (cam["distortion"]) {
    const std::string d = cam["distortion"].IsScalar() ? cam["distortion"].Scalar() : "";
    if (d == "none") {
      k.distortion = DistortionModel::kNone;
    } else if (d == "radtan") {
      k.distortion = DistortionModel::kRadTan;
    } else if (d == "equidistant") {
      k.distortion = DistortionModel::kEquidistant;
    } else {
      p.fail(path + "distortion", "expected radtan, equidistant or none, got \"" + d + "\"");
    }
  }
  if (cam["dist_coeffs"]) {
    const YAML::Node dc = cam["dist_coeffs"];
    if (!dc.IsSequence() || dc.size() > 5) {
      p.fail(path + "dist_coeffs",
             "expected a list of up to 5 numbers (radtan k1 k2 p1 p2 k3, equidistant k1..k4)");
    }
    for (size_t i = 0; i < dc.size(); ++i)
      k.dist[i] = p.number(dc[i], path + "dist_coeffs[" + std::to_string(i) + "]");
  }
}

void emit_intrinsics(std::ostringstream& o, const CameraIntrinsics& k) {
  o << "  width_px: " << k.width << "\n";
  o << "  height_px: " << k.height << "\n";
  o << "  fx_px: " << text::fmt17(k.fx) << "\n";
  o << "  fy_px: " << text::fmt17(k.fy) << "\n";
  o << "  cx_px: " << text::fmt17(k.cx) << "\n";
  o << "  cy_px: " << text::fmt17(k.cy) << "\n";
  o << "  distortion: " << distortion_name(k.distortion) << "\n";
  o << "  dist_coeffs: " << list(k.dist.data(), 5, "") << "\n";
}

bool intrinsics_equal(const CameraIntrinsics& ca, const CameraIntrinsics& cb) {
  return ca.width == cb.width && ca.height == cb.height && ca.fx == cb.fx && ca.fy == cb.fy &&
         ca.cx == cb.cx && ca.cy == cb.cy && ca.distortion == cb.distortion && ca.dist == cb.dist;
}

}  // namespace

Mat4d rigid_inverse(const Mat4d& T) {
  double R[3][3];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) R[i][j] = T[static_cast<size_t>(4 * i + j)];
  for (int i = 0; i < 3; ++i) {
    for (int k = 0; k < i; ++k) {
      double dot = 0;
      for (int j = 0; j < 3; ++j) dot += R[i][j] * R[k][j];
      for (int j = 0; j < 3; ++j) R[i][j] -= dot * R[k][j];
    }
    const double n = std::sqrt(R[i][0] * R[i][0] + R[i][1] * R[i][1] + R[i][2] * R[i][2]);
    for (int j = 0; j < 3; ++j) R[i][j] /= n;
  }
  Mat4d out = kIdentity4;
  for (int i = 0; i < 3; ++i) {
    double t = 0;
    for (int j = 0; j < 3; ++j) {
      out[static_cast<size_t>(4 * i + j)] = R[j][i];
      t -= R[j][i] * T[static_cast<size_t>(4 * j + 3)];
    }
    out[static_cast<size_t>(4 * i + 3)] = t;
  }
  return out;
}

const char* distortion_name(DistortionModel m) {
  switch (m) {
    case DistortionModel::kNone:
      return "none";
    case DistortionModel::kRadTan:
      return "radtan";
    case DistortionModel::kEquidistant:
      return "equidistant";
  }
  return "none";
}

Rig rig_from_yaml_node(const YAML::Node& root, const std::string& where, const std::string& prefix) {
  Parser p(where, prefix);
  if (!root || root.IsNull()) p.fail("", "empty rig");
  // A rig file holds the rig only: the pipeline's `threads:` belong to a
  // config file (tools/config reads it; its `rig:` may name this file).
  if (prefix.empty() && root.IsMap() && root["threads"])
    p.fail("threads", "belongs in a config file beside `rig: FILE` (docs/config.md), not in a rig file");
  p.only_keys(root, "",
              {"name", "camera", "depth", "depth_camera", "stereo", "T_BC", "T_BI", "imu",
               "time_offset_cam_imu_ns", "gravity_mps2"});
  Rig rig;
  if (root["name"]) {
    if (!root["name"].IsScalar()) p.fail("name", "expected a string");
    rig.name = root["name"].Scalar();
    // Written back (the .klog header, exports) it must read the same: the
    // emitter replaces bytes that are not UTF-8 (found by fuzz_rig_yaml).
    if (!text::is_utf8(rig.name)) p.fail("name", "not valid UTF-8");
  }

  const YAML::Node cam = root["camera"];
  if (!cam) p.fail("camera", "missing (required)");
  p.only_keys(
      cam, "camera",
      {"width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "distortion", "dist_coeffs", "rate_hz"});
  intrinsics(p, cam, "camera.", rig.rgb);
  p.opt_number(cam, "rate_hz", "camera.", rig.camera_rate_hz);
  p.non_negative(rig.camera_rate_hz, "camera.rate_hz");

  if (const YAML::Node dc = root["depth_camera"]) {
    p.only_keys(
        dc, "depth_camera",
        {"width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "distortion", "dist_coeffs", "T_CD"});
    intrinsics(p, dc, "depth_camera.", rig.depth_camera.intrinsics);
    if (!dc["T_CD"])
      p.fail("depth_camera.T_CD", "missing (required: depth camera -> colour camera, 4x4 row-major)");
    p.matrix(dc["T_CD"], "depth_camera.T_CD", rig.depth_camera.T_CD);
    rig.depth_camera.present = true;
  }

  if (const YAML::Node sc = root["stereo"]) {
    p.only_keys(
        sc, "stereo",
        {"width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "distortion", "dist_coeffs", "T_BC1"});
    intrinsics(p, sc, "stereo.", rig.stereo.intrinsics);
    if (!sc["T_BC1"]) p.fail("stereo.T_BC1", "missing (required: right camera -> body, 4x4 row-major)");
    p.matrix(sc["T_BC1"], "stereo.T_BC1", rig.stereo.T_BC1);
    rig.stereo.present = true;
  }

  if (const YAML::Node d = root["depth"]) {
    p.only_keys(d, "depth", {"scale_m_per_unit", "min_range_m", "max_range_m", "sigma_coeff_per_m"});
    p.opt_number(d, "scale_m_per_unit", "depth.", rig.depth.scale_m_per_unit);
    p.opt_number(d, "min_range_m", "depth.", rig.depth.min_range_m);
    p.opt_number(d, "max_range_m", "depth.", rig.depth.max_range_m);
    p.opt_number(d, "sigma_coeff_per_m", "depth.", rig.depth.sigma_coeff_per_m);
    if (rig.depth.scale_m_per_unit <= 0) p.fail("depth.scale_m_per_unit", "must be > 0");
    p.non_negative(rig.depth.min_range_m, "depth.min_range_m");
    if (rig.depth.max_range_m <= rig.depth.min_range_m)
      p.fail("depth.max_range_m", "must be > depth.min_range_m");
    p.non_negative(rig.depth.sigma_coeff_per_m, "depth.sigma_coeff_per_m");
  }
  if (root["T_BC"]) p.matrix(root["T_BC"], "T_BC", rig.T_BC);
  if (root["T_BI"]) p.matrix(root["T_BI"], "T_BI", rig.T_BI);

  if (const YAML::Node imu = root["imu"]) {
    p.only_keys(imu, "imu",
                {"rate_hz", "gyro_noise_density_rad_s_sqrthz", "gyro_random_walk_rad_s2_sqrthz",
                 "acc_noise_density_mps2_sqrthz", "acc_random_walk_mps3_sqrthz", "acc_bias_tau_s",
                 "gyro_range_rps", "acc_range_mps2"});
    ImuNoise& n = rig.imu;
    const std::pair<const char*, double*> fields[] = {
        {"rate_hz", &rig.imu_rate_hz},
        {"gyro_noise_density_rad_s_sqrthz", &n.gyro_noise_density_rad_s_sqrthz},
        {"gyro_random_walk_rad_s2_sqrthz", &n.gyro_random_walk_rad_s2_sqrthz},
        {"acc_noise_density_mps2_sqrthz", &n.acc_noise_density_mps2_sqrthz},
        {"acc_random_walk_mps3_sqrthz", &n.acc_random_walk_mps3_sqrthz},
        {"acc_bias_tau_s", &n.acc_bias_tau_s},
        {"gyro_range_rps", &n.gyro_range_rps},
        {"acc_range_mps2", &n.acc_range_mps2}};
    for (const auto& [key, dst] : fields) {
      p.opt_number(imu, key, "imu.", *dst);
      // tau <= 0 is meaningful (plain random walk); everything else is a magnitude.
      if (std::string(key) != "acc_bias_tau_s") p.non_negative(*dst, std::string("imu.") + key);
    }
  }
  if (root["time_offset_cam_imu_ns"])
    rig.time_offset_cam_imu_ns = p.integer(root["time_offset_cam_imu_ns"], "time_offset_cam_imu_ns");
  p.opt_number(root, "gravity_mps2", "", rig.gravity_mps2);
  if (rig.gravity_mps2 <= 0) p.fail("gravity_mps2", "must be > 0");
  return rig;
}

Rig rig_from_yaml(const std::string& yaml_text, const std::string& where) {
  YAML::Node root;
  try {
    root = YAML::Load(yaml_text);
  } catch (const YAML::ParserException& e) {
    throw std::runtime_error(where + ":" + std::to_string(e.mark.line + 1) + ":" +
                             std::to_string(e.mark.column + 1) + ": YAML syntax error: " + e.msg);
  }
  try {
    return rig_from_yaml_node(root, where, "");
  } catch (const YAML::Exception& e) {
    // Structural surprises yaml-cpp catches before we do (e.g. indexing a scalar).
    throw std::runtime_error(where + ": " + e.what());
  }
}

std::string rig_to_yaml(const Rig& r) {
  YAML::Emitter name;
  name << YAML::DoubleQuoted << r.name;
  std::ostringstream o;
  o << "# Kestrel rig. Units are in the key names (docs/log-format.md).\n";
  o << "name: " << name.c_str() << "\n";
  o << "camera:\n";
  emit_intrinsics(o, r.rgb);
  o << "  rate_hz: " << text::fmt17(r.camera_rate_hz) << "\n";
  o << "depth:\n";
  o << "  scale_m_per_unit: " << text::fmt17(r.depth.scale_m_per_unit) << "\n";
  o << "  min_range_m: " << text::fmt17(r.depth.min_range_m) << "\n";
  o << "  max_range_m: " << text::fmt17(r.depth.max_range_m) << "\n";
  o << "  sigma_coeff_per_m: " << text::fmt17(r.depth.sigma_coeff_per_m) << "\n";
  if (r.depth_camera.present) {
    o << "# the depth sensor when it is not the colour camera; its depth is registered to the colour "
         "camera\n";
    o << "depth_camera:\n";
    emit_intrinsics(o, r.depth_camera.intrinsics);
    o << "  # depth camera -> colour camera, 4x4 row-major\n";
    o << "  T_CD: " << list(r.depth_camera.T_CD.data(), 16, "        ") << "\n";
  }
  if (r.stereo.present) {
    // A rectified rig is the estimator's view of the pair, derived at start-up; files keep the calibration.
    o << "# the right camera of a stereo pair (camera: is the left one); depth from matching "
         "(docs/stereo.md)\n";
    o << "stereo:\n";
    emit_intrinsics(o, r.stereo.intrinsics);
    o << "  # right camera -> body, 4x4 row-major\n";
    o << "  T_BC1: " << list(r.stereo.T_BC1.data(), 16, "        ") << "\n";
  }
  o << "# camera -> body (body = IMU frame), 4x4 row-major\n";
  o << "T_BC: " << list(r.T_BC.data(), 16, "       ") << "\n";
  o << "# IMU -> body, 4x4 row-major\n";
  o << "T_BI: " << list(r.T_BI.data(), 16, "       ") << "\n";
  o << "imu:\n";
  o << "  rate_hz: " << text::fmt17(r.imu_rate_hz) << "\n";
  o << "  gyro_noise_density_rad_s_sqrthz: " << text::fmt17(r.imu.gyro_noise_density_rad_s_sqrthz) << "\n";
  o << "  gyro_random_walk_rad_s2_sqrthz: " << text::fmt17(r.imu.gyro_random_walk_rad_s2_sqrthz) << "\n";
  o << "  acc_noise_density_mps2_sqrthz: " << text::fmt17(r.imu.acc_noise_density_mps2_sqrthz) << "\n";
  o << "  acc_random_walk_mps3_sqrthz: " << text::fmt17(r.imu.acc_random_walk_mps3_sqrthz) << "\n";
  o << "  acc_bias_tau_s: " << text::fmt17(r.imu.acc_bias_tau_s) << "\n";
  o << "  gyro_range_rps: " << text::fmt17(r.imu.gyro_range_rps) << "\n";
  o << "  acc_range_mps2: " << text::fmt17(r.imu.acc_range_mps2) << "\n";
  o << "# t_imu = t_cam + offset\n";
  o << "time_offset_cam_imu_ns: " << r.time_offset_cam_imu_ns << "\n";
  o << "gravity_mps2: " << text::fmt17(r.gravity_mps2) << "\n";
  return o.str();
}

Rig load_rig_file(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error(path + ": cannot open rig file");
  std::ostringstream s;
  s << f.rdbuf();
  return rig_from_yaml(s.str(), path);
}

bool rig_equal(const Rig& a, const Rig& b) {
  const bool depth_camera_equal =
      a.depth_camera.present == b.depth_camera.present &&
      (!a.depth_camera.present || (intrinsics_equal(a.depth_camera.intrinsics, b.depth_camera.intrinsics) &&
                                   a.depth_camera.T_CD == b.depth_camera.T_CD));
  const bool stereo_equal =
      a.stereo.present == b.stereo.present &&
      (!a.stereo.present ||
       (intrinsics_equal(a.stereo.intrinsics, b.stereo.intrinsics) && a.stereo.T_BC1 == b.stereo.T_BC1));
  return a.name == b.name && intrinsics_equal(a.rgb, b.rgb) && depth_camera_equal && stereo_equal &&
         a.depth.scale_m_per_unit == b.depth.scale_m_per_unit && a.depth.min_range_m == b.depth.min_range_m &&
         a.depth.max_range_m == b.depth.max_range_m &&
         a.depth.sigma_coeff_per_m == b.depth.sigma_coeff_per_m && a.T_BC == b.T_BC && a.T_BI == b.T_BI &&
         a.imu.gyro_noise_density_rad_s_sqrthz == b.imu.gyro_noise_density_rad_s_sqrthz &&
         a.imu.gyro_random_walk_rad_s2_sqrthz == b.imu.gyro_random_walk_rad_s2_sqrthz &&
         a.imu.acc_noise_density_mps2_sqrthz == b.imu.acc_noise_density_mps2_sqrthz &&
         a.imu.acc_random_walk_mps3_sqrthz == b.imu.acc_random_walk_mps3_sqrthz &&
         a.imu.acc_bias_tau_s == b.imu.acc_bias_tau_s && a.imu.gyro_range_rps == b.imu.gyro_range_rps &&
         a.imu.acc_range_mps2 == b.imu.acc_range_mps2 && a.imu_rate_hz == b.imu_rate_hz &&
         a.camera_rate_hz == b.camera_rate_hz && a.time_offset_cam_imu_ns == b.time_offset_cam_imu_ns &&
         a.gravity_mps2 == b.gravity_mps2;
}

}  // namespace kestrel::drivers

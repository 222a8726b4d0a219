// `rs-enumerate-devices -c` text -> Rig. A line-oriented reader: each block
// starts with a header line the tool prints verbatim, its fields follow on
// the next lines; every number goes through the text layer so a bad one
// names its line and field.
#include "kestrel/drivers/realsense_import.hpp"

#include <cmath>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/drivers/text.hpp"

namespace kestrel::drivers {
namespace {

class Lines {
 public:
  Lines(const std::string& text, std::string name) : name_(std::move(name)) {
    std::istringstream in(text);
    std::string l;
    while (std::getline(in, l)) {
      if (!l.empty() && l.back() == '\r') l.pop_back();
      lines_.push_back(l);
    }
  }
  bool done() const { return at_ >= lines_.size(); }
  const std::string& peek() const { return lines_[at_]; }
  std::string next() { return lines_[at_++]; }
  int line() const { return static_cast<int>(at_); }  // 1-based number of the line last taken
  // The next line that is not blank (or "" at the end).
  std::string next_nonblank() {
    while (!done() && text::trim(peek()).empty()) ++at_;
    return done() ? std::string() : next();
  }
  [[noreturn]] void fail(const std::string& field, const std::string& msg) const {
    throw std::runtime_error(name_ + ":" + std::to_string(line()) + ": " + field + ": " + msg);
  }
  double number(const std::string& s, const std::string& field) const {
    double v = 0;
    if (!text::parse_finite_f64(s, v)) fail(field, "expected a finite number, got \"" + s + "\"");
    return v;
  }
  std::vector<double> numbers(const std::string& s, const std::string& field, size_t count) const {
    const std::vector<std::string> f = text::split_ws(s);
    if (f.size() != count)
      fail(field, "expected " + std::to_string(count) + " numbers, got \"" + text::trim(s) + "\"");
    std::vector<double> v;
    for (size_t i = 0; i < count; ++i) v.push_back(number(f[i], field + "[" + std::to_string(i) + "]"));
    return v;
  }
  // "  Key:  \tvalue" -> value, after checking the key.
  std::string field(const std::string& key) {
    const std::string l = next_nonblank();
    const size_t colon = l.find(':');
    if (colon == std::string::npos || text::trim(l.substr(0, colon)) != key)
      fail(key, "expected \"" + key + ":\", got \"" + text::trim(l) + "\"");
    return text::trim(l.substr(colon + 1));
  }
  const std::string& name() const { return name_; }

 private:
  std::string name_;
  std::vector<std::string> lines_;
  size_t at_ = 0;
};

[[noreturn]] void throw_named(const std::string& name, const std::string& what) {
  throw std::runtime_error(name + ": " + what);
}

bool starts_with(const std::string& s, const std::string& p) { return s.compare(0, p.size(), p) == 0; }

// The quoted names of a header line, in order.
std::vector<std::string> quoted(const std::string& l) {
  std::vector<std::string> out;
  size_t at = 0;
  while (true) {
    const size_t a = l.find('"', at);
    if (a == std::string::npos) break;
    const size_t b = l.find('"', a + 1);
    if (b == std::string::npos) break;
    out.push_back(l.substr(a + 1, b - a - 1));
    at = b + 1;
  }
  return out;
}

void check_rotation(Lines& in, const Mat4d& T, const std::string& field) {
  double worst = 0;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      double d = 0;
      for (int k = 0; k < 3; ++k) d += T[4 * i + k] * T[4 * j + k];
      worst = std::max(worst, std::abs(d - (i == j ? 1.0 : 0.0)));
    }
  }
  // rs-enumerate-devices prints floats with 6 significant digits.
  if (worst > 1e-4)
    in.fail(field, "the rotation is not orthonormal (R R^T - I up to " + text::fmt6(worst) + ")");
}

void parse_intrinsics(Lines& in, const std::string& header, RealSenseDump& d) {
  RsIntrinsics r;
  r.line = in.line();
  const std::vector<std::string> q = quoted(header);
  if (q.size() != 1) in.fail("Intrinsic of", "expected one quoted stream name");
  r.stream = q[0];
  // ' / 848x480 / {Z16}' (the formats hold '/' too: "{RGB8/Y16/YUYV}").
  const std::string tail = header.substr(header.rfind('"') + 1);
  const size_t s1 = tail.find('/');
  const size_t s2 = s1 == std::string::npos ? std::string::npos : tail.find('/', s1 + 1);
  if (s1 == std::string::npos)
    in.fail("Intrinsic of \"" + r.stream + "\"", "expected \"/ WIDTHxHEIGHT / {FORMATS}\"");
  const std::string size =
      text::trim(tail.substr(s1 + 1, s2 == std::string::npos ? std::string::npos : s2 - s1 - 1));
  const size_t x = size.find('x');
  double w = 0, h = 0;
  if (x == std::string::npos || !text::parse_finite_f64(size.substr(0, x), w) ||
      !text::parse_finite_f64(size.substr(x + 1), h) || w < 1 || h < 1 || w > 32768 || h > 32768 ||
      w != std::floor(w) || h != std::floor(h))
    in.fail("Intrinsic of \"" + r.stream + "\"", "expected a size WIDTHxHEIGHT, got \"" + size + "\"");
  r.width = static_cast<int>(w);
  r.height = static_cast<int>(h);
  if (s2 != std::string::npos) r.formats = text::trim(tail.substr(s2 + 1));
  const std::string s = r.stream + " " + std::to_string(r.width) + "x" + std::to_string(r.height) + ".";
  if (!in.done() && text::trim(in.peek()).rfind("Intrinsic NOT available", 0) == 0) {
    in.next();
    d.intrinsics.push_back(r);
    return;
  }
  const double fw = in.number(in.field("Width"), s + "Width");
  const double fh = in.number(in.field("Height"), s + "Height");
  if (fw != r.width || fh != r.height) in.fail(s + "Width", "does not match the block's size");
  r.ppx = in.number(in.field("PPX"), s + "PPX");
  r.ppy = in.number(in.field("PPY"), s + "PPY");
  r.fx = in.number(in.field("Fx"), s + "Fx");
  r.fy = in.number(in.field("Fy"), s + "Fy");
  if (r.fx <= 0 || r.fy <= 0) in.fail(s + "Fx", "focal lengths must be > 0");
  r.model = in.field("Distortion");
  const std::vector<double> c = in.numbers(in.field("Coeffs"), s + "Coeffs", 5);
  for (int i = 0; i < 5; ++i) r.coeffs[static_cast<size_t>(i)] = c[static_cast<size_t>(i)];
  r.available = true;
  d.intrinsics.push_back(r);
}

void parse_motion(Lines& in, const std::string& header, RealSenseDump& d) {
  RsMotionIntrinsics m;
  m.line = in.line();
  const std::vector<std::string> q = quoted(header);
  if (q.size() != 1) in.fail("Motion Intrinsic of", "expected one quoted stream name");
  m.stream = q[0];
  const std::string s = m.stream + ".";
  if (!in.done() && text::trim(in.peek()).rfind("Intrinsic NOT available", 0) == 0) {
    in.next();
    d.motion.push_back(m);
    return;
  }
  const std::vector<double> b = in.numbers(in.field("Bias Variances"), s + "Bias Variances", 3);
  const std::vector<double> n = in.numbers(in.field("Noise Variances"), s + "Noise Variances", 3);
  for (size_t i = 0; i < 3; ++i) {
    if (b[i] < 0 || n[i] < 0) in.fail(s + "Variances", "must be >= 0");
    m.bias_variances[i] = b[i];
    m.noise_variances[i] = n[i];
  }
  // Older librealsense prints no sensitivity.
  if (!in.done()) {
    std::string l = in.peek();
    size_t skip = 0;
    while (text::trim(l).empty() && !in.done()) {
      in.next();
      ++skip;
      if (in.done()) break;
      l = in.peek();
    }
    if (!in.done() && starts_with(text::trim(l), "Sensitivity")) {
      in.next();
      for (size_t r = 0; r < 3; ++r) {
        const std::vector<double> row =
            in.numbers(in.next_nonblank(), s + "Sensitivity[" + std::to_string(r) + "]", 4);
        for (size_t c = 0; c < 4; ++c) m.sensitivity[4 * r + c] = row[c];
      }
      m.has_sensitivity = true;
    }
    (void)skip;
  }
  m.available = true;
  d.motion.push_back(m);
}

void parse_extrinsics(Lines& in, const std::string& header, RealSenseDump& d) {
  RsExtrinsics e;
  e.line = in.line();
  const std::vector<std::string> q = quoted(header);
  if (q.size() != 2) in.fail("Extrinsic from", "expected \"FROM\" To \"TO\"");
  e.from = q[0];
  e.to = q[1];
  const std::string s = e.from + "->" + e.to + ".";
  const std::string first = text::trim(in.next_nonblank());
  if (first == "N/A") {
    d.extrinsics.push_back(e);
    return;
  }
  if (first != "Rotation Matrix:")
    in.fail(s + "Rotation Matrix", "expected \"Rotation Matrix:\", got \"" + first + "\"");
  for (int r = 0; r < 3; ++r) {
    const std::vector<double> row =
        in.numbers(in.next_nonblank(), s + "Rotation Matrix[" + std::to_string(r) + "]", 3);
    for (int c = 0; c < 3; ++c) e.T_to_from[static_cast<size_t>(4 * r + c)] = row[static_cast<size_t>(c)];
  }
  const std::string t = in.field("Translation Vector");
  const std::vector<double> tv = in.numbers(t, s + "Translation Vector", 3);
  for (int r = 0; r < 3; ++r) e.T_to_from[static_cast<size_t>(4 * r + 3)] = tv[static_cast<size_t>(r)];
  check_rotation(in, e.T_to_from, s + "Rotation Matrix");
  e.available = true;
  d.extrinsics.push_back(e);
}

// Orthonormalised copy (the rig file checks rotations tightly).
Mat4d rigid(const Mat4d& T) { return rigid_inverse(rigid_inverse(T)); }

// Solves the 5x5 system A x = b (partial pivoting); false when singular.
bool solve5(std::array<std::array<double, 6>, 5> m, std::array<double, 5>& x) {
  for (int c = 0; c < 5; ++c) {
    int p = c;
    for (int r = c + 1; r < 5; ++r) {
      if (std::abs(m[static_cast<size_t>(r)][static_cast<size_t>(c)]) >
          std::abs(m[static_cast<size_t>(p)][static_cast<size_t>(c)]))
        p = r;
    }
    if (std::abs(m[static_cast<size_t>(p)][static_cast<size_t>(c)]) < 1e-300) return false;
    std::swap(m[static_cast<size_t>(c)], m[static_cast<size_t>(p)]);
    for (int r = 0; r < 5; ++r) {
      if (r == c) continue;
      const double f = m[static_cast<size_t>(r)][static_cast<size_t>(c)] /
                       m[static_cast<size_t>(c)][static_cast<size_t>(c)];
      for (int k = c; k < 6; ++k) {
        m[static_cast<size_t>(r)][static_cast<size_t>(k)] -=
            f * m[static_cast<size_t>(c)][static_cast<size_t>(k)];
      }
    }
  }
  for (int c = 0; c < 5; ++c) {
    x[static_cast<size_t>(c)] =
        m[static_cast<size_t>(c)][5] / m[static_cast<size_t>(c)][static_cast<size_t>(c)];
  }
  return true;
}

void radtan(const std::array<double, 5>& k, double ux, double uy, double& dx, double& dy) {
  const double r2 = ux * ux + uy * uy;
  const double f = 1 + k[0] * r2 + k[1] * r2 * r2 + k[4] * r2 * r2 * r2;
  dx = ux * f + 2 * k[2] * ux * uy + k[3] * (r2 + 2 * ux * ux);
  dy = uy * f + 2 * k[3] * ux * uy + k[2] * (r2 + 2 * uy * uy);
}

}  // namespace

const RsIntrinsics* RealSenseDump::find(const std::string& stream, int width, int height) const {
  for (const RsIntrinsics& r : intrinsics)
    if (r.stream == stream && r.width == width && r.height == height) return &r;
  return nullptr;
}
const RsExtrinsics* RealSenseDump::find_extrinsics(const std::string& from, const std::string& to) const {
  for (const RsExtrinsics& e : extrinsics)
    if (e.from == from && e.to == to) return &e;
  return nullptr;
}
const RsMotionIntrinsics* RealSenseDump::find_motion(const std::string& stream) const {
  for (const RsMotionIntrinsics& m : motion)
    if (m.stream == stream) return &m;
  return nullptr;
}
std::string RealSenseDump::sizes_of(const std::string& stream) const {
  std::string s;
  for (const RsIntrinsics& r : intrinsics) {
    if (r.stream == stream)
      s += (s.empty() ? "" : ", ") + std::to_string(r.width) + "x" + std::to_string(r.height);
  }
  return s.empty() ? "none" : s;
}

RealSenseDump parse_realsense_dump(const std::string& text, const std::string& name) {
  Lines in(text, name);
  RealSenseDump d;
  while (!in.done()) {
    const std::string raw = in.next();
    const std::string l = text::trim(raw);
    if (starts_with(l, "Intrinsic of \"")) {
      parse_intrinsics(in, l, d);
    } else if (starts_with(l, "Motion Intrinsic of \"")) {
      parse_motion(in, l, d);
    } else if (starts_with(l, "Extrinsic from \"")) {
      parse_extrinsics(in, l, d);
    } else {
      // Device info: "    Name                          : \tIntel RealSense D435I".
      const size_t colon = l.find(':');
      if (colon == std::string::npos) continue;
      const std::string key = text::trim(l.substr(0, colon));
      const std::string value = text::trim(l.substr(colon + 1));
      if (key == "Name" && d.device_name.empty()) d.device_name = value;
      if (key == "Serial Number" && d.serial.empty()) d.serial = value;
      if (key == "Firmware Version" && d.firmware.empty()) d.firmware = value;
    }
  }
  return d;
}

bool fit_radtan(const RsIntrinsics& in, std::array<double, 5>& k, double& rms_px) {
  const std::array<double, 5>& c = in.coeffs;
  const bool inverse = in.model == "Inverse Brown Conrady";
  const bool modified = in.model == "Modified Brown Conrady";
  if (!inverse && !modified && in.model != "Brown Conrady") return false;
  // Pairs (undistorted u, distorted d) over a grid of the image, in normalised coordinates.
  std::vector<std::array<double, 4>> pairs;
  constexpr int kN = 24;
  for (int gy = 0; gy <= kN; ++gy) {
    for (int gx = 0; gx <= kN; ++gx) {
      const double px = in.width * gx / static_cast<double>(kN),
                   py = in.height * gy / static_cast<double>(kN);
      const double x = (px - in.ppx) / in.fx, y = (py - in.ppy) / in.fy;
      const double r2 = x * x + y * y;
      const double f = 1 + c[0] * r2 + c[1] * r2 * r2 + c[4] * r2 * r2 * r2;
      if (inverse) {  // pixel (distorted) -> undistorted: librealsense's deprojection
        pairs.push_back({x * f + 2 * c[2] * x * y + c[3] * (r2 + 2 * x * x),
                         y * f + 2 * c[3] * x * y + c[2] * (r2 + 2 * y * y), x, y});
      } else if (modified) {  // undistorted -> distorted, tangential terms on the radially scaled point
        const double xs = x * f, ys = y * f;
        pairs.push_back({x, y, xs + 2 * c[2] * xs * ys + c[3] * (r2 + 2 * xs * xs),
                         ys + 2 * c[3] * xs * ys + c[2] * (r2 + 2 * ys * ys)});
      } else {
        double dx = 0, dy = 0;
        radtan(c, x, y, dx, dy);
        pairs.push_back({x, y, dx, dy});
      }
    }
  }
  std::array<std::array<double, 6>, 5> n{};
  for (const auto& p : pairs) {
    const double ux = p[0], uy = p[1], r2 = ux * ux + uy * uy;
    const double rows[2][6] = {
        {ux * r2, ux * r2 * r2, 2 * ux * uy, r2 + 2 * ux * ux, ux * r2 * r2 * r2, p[2] - ux},
        {uy * r2, uy * r2 * r2, r2 + 2 * uy * uy, 2 * ux * uy, uy * r2 * r2 * r2, p[3] - uy}};
    for (const auto& row : rows) {
      for (size_t i = 0; i < 5; ++i)
        for (size_t j = 0; j < 6; ++j) n[i][j] += row[i] * row[j];
    }
  }
  // A tiny ridge keeps an all-zero model (every row zero) solvable: the answer is zero.
  for (size_t i = 0; i < 5; ++i) n[i][i] += 1e-12;
  if (!solve5(n, k)) return false;
  double sum = 0;
  for (const auto& p : pairs) {
    double dx = 0, dy = 0;
    radtan(k, p[0], p[1], dx, dy);
    sum += std::pow((dx - p[2]) * in.fx, 2) + std::pow((dy - p[3]) * in.fy, 2);
  }
  rms_px = std::sqrt(sum / static_cast<double>(pairs.size()));
  return std::isfinite(rms_px);
}

RealSenseImport import_realsense_text(const std::string& text, const std::string& name,
                                      const RealSenseImportOptions& o, const Rig& base) {
  const RealSenseDump d = parse_realsense_dump(text, name);
  RealSenseImport out;
  Rig& rig = out.rig;
  rig = base;
  auto fail = [&](const std::string& what) { throw_named(name, what); };
  if (o.camera != "Color" && o.camera != "Infrared 1")
    fail("camera \"" + o.camera + "\": expected \"Color\" or \"Infrared 1\"");
  if (!(o.accel_rate_hz > 0) || !(o.gyro_rate_hz > 0)) fail("the accel and gyro rates must be > 0");
  const int w = o.width > 0 ? o.width : (base.rgb.width > 0 ? base.rgb.width : 640);
  const int h = o.height > 0 ? o.height : (base.rgb.height > 0 ? base.rgb.height : 480);
  if (d.intrinsics.empty() && d.extrinsics.empty()) {
    fail(
        "no \"Intrinsic of\" or \"Extrinsic from\" sections: is this the output of `rs-enumerate-devices "
        "-c`?");
  }

  // ---- the camera ----
  auto intrinsics = [&](const RsIntrinsics& r, CameraIntrinsics& ci, const std::string& what) {
    ci.width = r.width;
    ci.height = r.height;
    ci.fx = r.fx;
    ci.fy = r.fy;
    ci.cx = r.ppx;
    ci.cy = r.ppy;
    ci.dist = {};
    const bool zero = r.coeffs == std::array<double, 5>{};
    if (r.model == "None" || (zero && r.model != "Kannala Brandt4" && r.model != "Ftheta")) {
      ci.distortion = DistortionModel::kNone;
    } else if (r.model == "Kannala Brandt4") {
      ci.distortion = DistortionModel::kEquidistant;
      for (size_t i = 0; i < 4; ++i) ci.dist[i] = r.coeffs[i];
    } else if (r.model == "Brown Conrady") {
      ci.distortion = DistortionModel::kRadTan;
      ci.dist = r.coeffs;  // k1 k2 p1 p2 k3, the same equations
    } else {
      std::array<double, 5> k{};
      double rms = 0;
      if (!fit_radtan(r, k, rms))
        fail(what + ": distortion \"" + r.model + "\" has no Kestrel equivalent (none, radtan, equidistant)");
      ci.distortion = DistortionModel::kRadTan;
      ci.dist = k;
      out.notes.push_back(what + ": \"" + r.model + "\" fitted as radtan over the image, residual " +
                          text::fmt6(rms) + " px rms" +
                          (rms > 0.1 ? " (LARGE: check the undistortion)" : ""));
    }
  };
  const RsIntrinsics* cam = d.find(o.camera, w, h);
  if (cam == nullptr) {
    throw_named(name, "no intrinsics of \"" + o.camera + "\" at " + std::to_string(w) + "x" +
                          std::to_string(h) + " (the dump has: " + d.sizes_of(o.camera) + ")");
  }
  if (!cam->available) fail("Intrinsic of " + o.camera + ": \"Intrinsic NOT available!\" in the dump");
  intrinsics(*cam, rig.rgb, o.camera);

  // ---- depth ----
  const int dw = o.depth_width > 0 ? o.depth_width : w, dh = o.depth_height > 0 ? o.depth_height : h;
  if (o.camera == "Color") {
    const RsIntrinsics* dep = d.find("Depth", dw, dh);
    if (dep == nullptr || !dep->available) {
      throw_named(name, "no intrinsics of \"Depth\" at " + std::to_string(dw) + "x" + std::to_string(dh) +
                            " (the dump has: " + d.sizes_of("Depth") +
                            "); depth must be registered to Color");
    }
    const RsExtrinsics* e = d.find_extrinsics("Depth", "Color");
    if (e == nullptr || !e->available)
      throw_named(name, "no Extrinsic from Depth To Color section (needed to register depth to colour)");
    rig.depth_camera.present = true;
    intrinsics(*dep, rig.depth_camera.intrinsics, "Depth");
    rig.depth_camera.T_CD = rigid(e->T_to_from);
  } else {
    // The D4xx computes depth in the left imager's frame: no registration.
    rig.depth_camera = DepthCamera{};
    if (dw != w || dh != h) fail("with \"Infrared 1\" as the camera the depth size must be the camera's");
    const RsExtrinsics* e = d.find_extrinsics("Depth", "Infrared 1");
    if (e != nullptr && e->available) {
      double off = 0;
      for (size_t i = 0; i < 16; ++i) off = std::max(off, std::abs(e->T_to_from[i] - kIdentity4[i]));
      if (off > 1e-4) {
        out.notes.push_back("Depth -> Infrared 1 is not identity (" + text::fmt6(off) +
                            "): unexpected on a D4xx");
      }
    }
  }

  if (o.camera == "Color" && d.find("Infrared 1", w, h) != nullptr) {
    out.notes.push_back(
        "Infrared 1 and 2 intrinsics: read, not used (the rig's camera is Color; "
        "--camera infrared1 makes the left imager the camera)");
  }

  // ---- the IMU: extrinsics ----
  const RsExtrinsics* g = d.find_extrinsics("Gyro", o.camera);
  const RsExtrinsics* a = d.find_extrinsics("Accel", o.camera);
  if (g != nullptr && g->available) {
    rig.T_BC = rigid_inverse(g->T_to_from);
    if (a != nullptr && a->available) {
      double off = 0;
      for (size_t i = 0; i < 12; ++i) off = std::max(off, std::abs(a->T_to_from[i] - g->T_to_from[i]));
      if (off > 1e-3) {
        out.notes.push_back("Accel -> " + o.camera + " differs from Gyro -> " + o.camera + " by " +
                            text::fmt6(off) + ": the body frame is the gyro's");
      }
    }
  } else if (a != nullptr && a->available) {
    rig.T_BC = rigid_inverse(a->T_to_from);
    out.notes.push_back("T_BC from Accel -> " + o.camera + " (no Gyro extrinsics in the dump)");
  } else {
    out.missing.push_back("Extrinsic from \"Gyro\" To \"" + o.camera +
                          "\" (no IMU: a D435/D415?): T_BC kept from the base rig, NOT calibrated");
  }
  rig.T_BI = kIdentity4;

  // ---- the IMU: noise ----
  auto noise = [&](const char* stream, double rate_hz, double& density, const char* unit) {
    const RsMotionIntrinsics* m = d.find_motion(stream);
    if (m == nullptr || !m->available) {
      out.missing.push_back(std::string("Motion Intrinsic of \"") + stream + "\": noise density " +
                            text::fmt6(density) + " " + unit + " kept from the base rig");
      return;
    }
    const double var = (m->noise_variances[0] + m->noise_variances[1] + m->noise_variances[2]) / 3.0;
    if (!(var > 0)) {
      out.missing.push_back(
          std::string("Motion Intrinsic of \"") + stream +
          "\": noise variances are zero (IMU not calibrated, rs-imu-calibration): noise density " +
          text::fmt6(density) + " " + unit + " kept from the base rig");
      return;
    }
    // A discrete variance per sample at rate f is sigma_c^2 * f: density = sqrt(var / f).
    density = std::sqrt(var / rate_hz);
    out.notes.push_back(std::string(stream) + ": noise density " + text::fmt6(density) + " " + unit +
                        " from the mean noise variance " + text::fmt6(var) + " at " + text::fmt6(rate_hz) +
                        " Hz");
    if (m->has_sensitivity) {
      double off = 0;
      for (size_t r = 0; r < 3; ++r) {
        for (size_t c = 0; c < 4; ++c)
          off = std::max(off, std::abs(m->sensitivity[4 * r + c] - (r == c ? 1.0 : 0.0)));
      }
      if (off > 1e-6) {
        out.notes.push_back(
            std::string(stream) + ": sensitivity/bias matrix is not identity (" + text::fmt6(off) +
            "): Kestrel does not apply it; write it to the device (rs-imu-calibration) so the "
            "firmware does");
      }
    }
  };
  noise("Accel", o.accel_rate_hz, rig.imu.acc_noise_density_mps2_sqrthz, "m/s^2/sqrt(Hz)");
  noise("Gyro", o.gyro_rate_hz, rig.imu.gyro_noise_density_rad_s_sqrthz, "rad/s/sqrt(Hz)");
  rig.imu_rate_hz = o.gyro_rate_hz;

  // ---- what the dump has no place for ----
  out.notes.push_back("imu.rate_hz: " + text::fmt6(rig.imu_rate_hz) +
                      " (the gyro's; the accelerometer is interpolated onto it)");
  out.notes.push_back(
      "imu random walks: not in the dump: acc " + text::fmt6(rig.imu.acc_random_walk_mps3_sqrthz) +
      " m/s^3/sqrt(Hz), gyro " + text::fmt6(rig.imu.gyro_random_walk_rad_s2_sqrthz) +
      " rad/s^2/sqrt(Hz) from the base rig (the dump's bias variances are a static uncertainty)");
  out.notes.push_back("depth unit and range: not in `-c` output: scale_m_per_unit " +
                      text::fmt6(rig.depth.scale_m_per_unit) + ", " + text::fmt6(rig.depth.min_range_m) +
                      ".." + text::fmt6(rig.depth.max_range_m) + " m from the base rig");
  out.notes.push_back("time_offset_cam_imu_ns: " + std::to_string(rig.time_offset_cam_imu_ns) +
                      " from the base rig (frames and IMU share the D4xx clock; docs/realsense.md)");
  out.notes.push_back("camera.rate_hz " + text::fmt6(rig.camera_rate_hz) + ", gravity " +
                      text::fmt6(rig.gravity_mps2) + " m/s^2, IMU ranges, acc_bias_tau_s: from the base rig");
  if (rig.name.empty() || rig.name == base.name) {
    rig.name = (d.device_name.empty() ? std::string("realsense") : d.device_name) +
               (d.serial.empty() ? std::string() : " " + d.serial);
    // The name is the dump's text: only printable ASCII survives the rig
    // YAML's round trip as it is (found by fuzz_realsense_dump).
    for (char& c : rig.name)
      if (static_cast<unsigned char>(c) < 0x20 || static_cast<unsigned char>(c) > 0x7e) c = '?';
  }
  try {
    rig_from_yaml(rig_to_yaml(rig), "the imported rig");
  } catch (const std::runtime_error& e) {
    throw std::runtime_error(name + ": " + e.what());
  }
  return out;
}

RealSenseImport import_realsense(const std::string& path, const RealSenseImportOptions& o, const Rig& base) {
  return import_realsense_text(
      text::read_file(path, " (the output of `rs-enumerate-devices -c > " + path + "`)"), path, o, base);
}

}  // namespace kestrel::drivers

// Built-in scenarios: sums of sinusoids and quintic steps with analytic
// derivatives, switched on by C2 ramps so every flight starts at rest with
// zero acceleration (a clean static initialisation).
#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/tools/sim_trajectory.hpp"

namespace kestrel::tools {
namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kTwoPi = 2.0 * kPi;
constexpr double deg(double d) { return d * kPi / 180.0; }

// A scalar signal and its first two time derivatives.
struct Jet {
  double v = 0.0, d1 = 0.0, d2 = 0.0;
};

Jet operator+(const Jet& a, const Jet& b) { return {a.v + b.v, a.d1 + b.d1, a.d2 + b.d2}; }
Jet operator*(const Jet& a, const Jet& b) {
  return {a.v * b.v, a.d1 * b.v + a.v * b.d1, a.d2 * b.v + 2.0 * a.d1 * b.d1 + a.v * b.d2};
}

// Quintic smoothstep 10x^3 - 15x^4 + 6x^5 from t0 over len: value, slope and
// curvature all vanish at both ends, so anything multiplied by it is C2.
Jet smoothstep5(double t, double t0, double len) {
  const double x = (t - t0) / len;
  if (x <= 0.0) return {0.0, 0.0, 0.0};
  if (x >= 1.0) return {1.0, 0.0, 0.0};
  const double omx = 1.0 - x;
  return {x * x * x * (10.0 - 15.0 * x + 6.0 * x * x), 30.0 * x * x * omx * omx / len,
          60.0 * x * omx * (1.0 - 2.0 * x) / (len * len)};
}

// Integral of smoothstep5 from t0: a time warp whose rate ramps smoothly
// from 0 to 1, for paths that must be traced at a steady speed after a start
// from rest.
Jet smooth_time(double t, double t0, double len) {
  const double x = (t - t0) / len;
  if (x <= 0.0) return {0.0, 0.0, 0.0};
  if (x >= 1.0) return {t - t0 - 0.5 * len, 1.0, 0.0};
  const double x4 = x * x * x * x;
  const Jet s = smoothstep5(t, t0, len);
  return {len * (2.5 * x4 - 3.0 * x4 * x + x4 * x * x), s.v, s.d1};
}

struct Sine {
  double amp = 0.0, freq_hz = 0.0, phase = 0.0;
};

struct Step {
  double t0 = 0.0, len = 1.0, delta = 0.0;
};

// base + ramp(t) * sum(sines) + sum(steps).
struct Channel {
  double base = 0.0;
  double ramp_start_s = 0.0;
  double ramp_len_s = 4.0;
  std::vector<Sine> sines;
  std::vector<Step> steps;

  Jet eval(double t) const {
    Jet g;
    for (const Sine& s : sines) {
      const double w = kTwoPi * s.freq_hz;
      const double a = w * (t - ramp_start_s) + s.phase;
      g = g + Jet{s.amp * std::sin(a), s.amp * w * std::cos(a), -s.amp * w * w * std::sin(a)};
    }
    Jet out = smoothstep5(t, ramp_start_s, ramp_len_s) * g;
    out.v += base;
    for (const Step& st : steps) out = out + Jet{st.delta, 0.0, 0.0} * smoothstep5(t, st.t0, st.len);
    return out;
  }
};

// Position channels (x, y, z in W) and ZYX Euler angles (roll, pitch, yaw;
// R_WB = Rz(yaw) Ry(pitch) Rx(roll)). Euler angles are only a convenient way
// to write attitude signals; the outputs are the quaternion and body rate.
class AnalyticTrajectory : public MotionModel {
 public:
  AnalyticTrajectory(std::string name, double duration_s) : name_(std::move(name)), duration_s_(duration_s) {}
  double duration_s() const override { return duration_s_; }
  int64_t t0_ns() const override { return kT0Ns; }
  std::string description() const override { return "scenario " + name_; }

  TrajectoryState state(double t) const override {
    Jet pos[3], eul[3];
    eval(t, pos, eul);
    TrajectoryState s;
    s.t_s = t;
    s.p_WB = {pos[0].v, pos[1].v, pos[2].v};
    s.v_WB = {pos[0].d1, pos[1].d1, pos[2].d1};
    s.a_WB = {pos[0].d2, pos[1].d2, pos[2].d2};
    const double r = eul[0].v, p = eul[1].v, y = eul[2].v;
    s.q_WB = Eigen::AngleAxisd(y, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(p, Eigen::Vector3d::UnitY()) *
             Eigen::AngleAxisd(r, Eigen::Vector3d::UnitX());
    s.q_WB.normalize();
    const double dr = eul[0].d1, dp = eul[1].d1, dy = eul[2].d1;
    const double sr = std::sin(r), cr = std::cos(r), sp = std::sin(p), cp = std::cos(p);
    s.w_B = {dr - dy * sp, dp * cr + dy * sr * cp, -dp * sr + dy * cr * cp};
    return s;
  }

  // Log time of t = 0: one second, so stamps shifted by a negative camera
  // offset stay positive.
  static constexpr int64_t kT0Ns = 1'000'000'000;

 protected:
  // Only v and d1 of the Euler angles are used.
  virtual void eval(double t, Jet pos[3], Jet eul[3]) const = 0;

 private:
  std::string name_;
  double duration_s_;
};

class ChannelTrajectory final : public AnalyticTrajectory {
 public:
  ChannelTrajectory(std::string name, double duration_s) : AnalyticTrajectory(std::move(name), duration_s) {}
  Channel ch[6];  // x y z roll pitch yaw

 protected:
  void eval(double t, Jet pos[3], Jet eul[3]) const override {
    for (int i = 0; i < 3; ++i) pos[i] = ch[i].eval(t);
    for (int i = 0; i < 3; ++i) eul[i] = ch[3 + i].eval(t);
  }
};

// Lissajous figure eight x = A sin u, y = B sin 2u traced with u = w * warp(t).
class Figure8Trajectory final : public AnalyticTrajectory {
 public:
  Figure8Trajectory(double duration_s, bool yaw_follows)
      : AnalyticTrajectory("figure8", duration_s), yaw_follows_(yaw_follows) {
    z_.base = 1.2;
    z_.ramp_len_s = 4.0;
    z_.sines = {{0.10, 0.07, 0.3}, {0.02, 0.4, 1.0}};
    roll_.sines = {{deg(3.0), 0.11, 0.0}, {deg(0.7), 0.9, 1.3}};
    pitch_.sines = {{deg(3.0), 0.09, 1.0}, {deg(0.7), 1.1, 0.4}};
    yaw_.sines = {{deg(10.0), 0.05, 0.0}};
  }

 protected:
  void eval(double t, Jet pos[3], Jet eul[3]) const override {
    const Jet warp = smooth_time(t, 0.0, kRampS);
    const double u = kOmega * warp.v, du = kOmega * warp.d1, ddu = kOmega * warp.d2;
    const double su = std::sin(u), cu = std::cos(u), s2 = std::sin(2.0 * u), c2 = std::cos(2.0 * u);
    pos[0] = {kA * su, kA * cu * du, -kA * su * du * du + kA * cu * ddu};
    pos[1] = {kB * s2, 2.0 * kB * c2 * du, -4.0 * kB * s2 * du * du + 2.0 * kB * c2 * ddu};
    pos[2] = z_.eval(t);
    eul[0] = roll_.eval(t);
    eul[1] = pitch_.eval(t);
    if (yaw_follows_) {
      // Heading of the path tangent in u, which never vanishes (cos u and
      // cos 2u are never zero together), so the heading is defined even at rest.
      const double xu = kA * cu, yu = 2.0 * kB * c2, xuu = -kA * su, yuu = -4.0 * kB * s2;
      const double dpsi_du = (xu * yuu - yu * xuu) / (xu * xu + yu * yu);
      eul[2] = {std::atan2(yu, xu), dpsi_du * du, 0.0};
    } else {
      eul[2] = yaw_.eval(t);
    }
  }

 private:
  static constexpr double kA = 1.5;       // m: 3 m long
  static constexpr double kB = 1.0;       // m: 2 m wide
  static constexpr double kOmega = 0.55;  // rad/s of u: ~1 m/s mean speed along the path
  static constexpr double kRampS = 3.0;
  bool yaw_follows_;
  Channel z_, roll_, pitch_, yaw_;
};

std::unique_ptr<MotionModel> make_hover(double T) {
  // Paper 000's 189 s hover: slow drifts of a few cm and a few degrees, small
  // fast corrections on top.
  auto tr = std::make_unique<ChannelTrajectory>("hover", T);
  auto& c = tr->ch;
  c[2].base = 1.2;
  c[0].sines = {{0.04, 0.013, 0.3}, {0.02, 0.061, 1.1}, {0.006, 0.37, 2.0}, {0.002, 1.3, 0.5}};
  c[1].sines = {{0.035, 0.017, 2.1}, {0.018, 0.07, 0.4}, {0.005, 0.41, 1.3}, {0.002, 1.1, 2.5}};
  c[2].sines = {{0.03, 0.021, 0.7}, {0.01, 0.11, 2.9}, {0.003, 0.53, 0.2}};
  c[3].sines = {{deg(1.5), 0.09, 0.0}, {deg(0.6), 0.45, 1.0}, {deg(0.2), 1.7, 2.0}};
  c[4].sines = {{deg(1.5), 0.08, 0.5}, {deg(0.6), 0.5, 2.0}, {deg(0.2), 1.9, 0.3}};
  c[5].sines = {{deg(3.0), 0.011, 0.2}, {deg(1.0), 0.05, 1.5}, {deg(0.3), 0.3, 0.9}};
  return tr;
}

std::unique_ptr<MotionModel> make_aggressive(double T) {
  auto tr = std::make_unique<ChannelTrajectory>("aggressive", T);
  auto& c = tr->ch;
  for (auto& ch : c) ch.ramp_len_s = 3.0;
  c[2].base = 1.3;
  c[0].sines = {{0.8, 0.23, 0.0}, {0.3, 0.71, 1.0}};
  c[1].sines = {{0.7, 0.19, 2.0}, {0.25, 0.83, 0.5}};
  c[2].sines = {{0.3, 0.31, 1.0}, {0.1, 1.1, 0.0}};
  c[3].sines = {{deg(20.0), 0.5, 0.0}, {deg(8.0), 1.3, 1.0}};
  c[4].sines = {{deg(20.0), 0.45, 1.0}, {deg(8.0), 1.1, 2.0}};
  // Yaw bursts whose peak rate is 300 deg/s: a quintic step of size D over
  // len peaks at 15/8 * D / len.
  const double peak = deg(300.0);
  const double sizes_deg[] = {120.0, -180.0, 90.0, 150.0, -120.0, -90.0, 180.0, -150.0};
  int k = 0;
  for (double t0 = 4.0; t0 + 1.5 < T; t0 += 5.0, ++k) {
    const double d = deg(sizes_deg[k % 8]);
    c[5].steps.push_back({t0, 15.0 / 8.0 * std::abs(d) / peak, d});
  }
  return tr;
}

std::unique_ptr<MotionModel> make_static(double T) {
  // Still on the floor (body 0.25 m up, level) for min(30 s, T/2), then a
  // smooth take-off to 1.2 m and gentle motion.
  const double still = std::min(30.0, 0.5 * T);
  auto tr = std::make_unique<ChannelTrajectory>("static", T);
  auto& c = tr->ch;
  for (auto& ch : c) {
    ch.ramp_start_s = still + 1.0;
    ch.ramp_len_s = 3.0;
  }
  c[2].base = 0.25;
  c[2].steps = {{still, 3.0, 0.95}};
  c[0].sines = {{0.5, 0.1, 0.0}, {0.05, 0.6, 1.0}};
  c[1].sines = {{0.4, 0.13, 0.0}, {0.05, 0.5, 2.0}};
  c[2].sines = {{0.1, 0.2, 0.0}};
  c[3].sines = {{deg(5.0), 0.3, 0.0}, {deg(1.0), 1.2, 0.5}};
  c[4].sines = {{deg(5.0), 0.25, 0.0}, {deg(1.0), 1.0, 1.5}};
  c[5].sines = {{deg(30.0), 0.08, 0.0}, {deg(3.0), 0.7, 0.2}};
  return tr;
}

}  // namespace

namespace {

// Built to make backends lose the truth (issue 17): wide sweeps through a
// hall whose walls are beyond the depth range, faster yaw bursts than
// `aggressive`, and passes that face the bare wall; the simulator adds the
// exposure steps and motion blur (simulator.cpp).
std::unique_ptr<MotionModel> make_hard(double T) {
  auto tr = std::make_unique<ChannelTrajectory>("hard", T);
  auto& c = tr->ch;
  for (auto& ch : c) ch.ramp_len_s = 3.0;
  c[2].base = 1.5;
  c[0].sines = {{3.0, 0.07, 0.0}, {0.6, 0.41, 1.0}};
  c[1].sines = {{2.5, 0.09, 2.0}, {0.4, 0.53, 0.5}};
  c[2].sines = {{0.6, 0.13, 1.0}, {0.1, 0.9, 0.0}};
  c[3].sines = {{deg(15.0), 0.4, 0.0}, {deg(6.0), 1.1, 1.0}};
  c[4].sines = {{deg(15.0), 0.35, 1.0}, {deg(6.0), 1.3, 2.0}};
  c[5].sines = {{deg(40.0), 0.05, 0.0}};
  // Yaw bursts peaking at 400 deg/s, every 4 s.
  const double peak = deg(400.0);
  const double sizes_deg[] = {150.0, -210.0, 120.0, 180.0, -150.0, -120.0, 210.0, -180.0};
  int k = 0;
  for (double t0 = 3.5; t0 + 1.5 < T; t0 += 4.0, ++k) {
    const double d = deg(sizes_deg[k % 8]);
    c[5].steps.push_back({t0, 15.0 / 8.0 * std::abs(d) / peak, d});
  }
  return tr;
}

}  // namespace

std::vector<std::string> scenario_names() { return {"hover", "figure8", "aggressive", "static", "hard"}; }

double default_scenario_duration_s(const std::string& name) {
  if (name == "hover") return 189.0;
  if (name == "figure8" || name == "aggressive" || name == "static" || name == "hard") return 60.0;
  throw std::invalid_argument("unknown scenario '" + name +
                              "' (known: hover, figure8, aggressive, static, hard)");
}

std::unique_ptr<MotionModel> make_scenario(const std::string& name, double duration_s,
                                           const ScenarioOptions& options) {
  const double T = duration_s > 0.0 ? duration_s : default_scenario_duration_s(name);
  if (name == "hover") return make_hover(T);
  if (name == "figure8") return std::make_unique<Figure8Trajectory>(T, options.yaw_follows_path);
  if (name == "aggressive") return make_aggressive(T);
  if (name == "static") return make_static(T);
  if (name == "hard") return make_hard(T);
  throw std::invalid_argument("unknown scenario '" + name +
                              "' (known: hover, figure8, aggressive, static, hard)");
}

Eigen::Quaterniond so3_exp(const Eigen::Vector3d& phi) {
  const double th = phi.norm();
  if (th < 1e-8) {
    Eigen::Quaterniond q(1.0, 0.5 * phi.x(), 0.5 * phi.y(), 0.5 * phi.z());
    return q.normalized();
  }
  const double s = std::sin(0.5 * th) / th;
  return Eigen::Quaterniond(std::cos(0.5 * th), s * phi.x(), s * phi.y(), s * phi.z());
}

Eigen::Vector3d so3_log(const Eigen::Quaterniond& q_in) {
  Eigen::Quaterniond q = q_in.normalized();
  if (q.w() < 0.0) q.coeffs() = -q.coeffs();
  const Eigen::Vector3d v = q.vec();
  const double n = v.norm();
  if (n < 1e-10) return 2.0 * v / q.w();
  return (2.0 * std::atan2(n, q.w()) / n) * v;
}

}  // namespace kestrel::tools

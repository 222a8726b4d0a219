// Smooth body trajectories for the simulator: built-in scenarios with
// analytic derivatives, and splines fitted to ground-truth files.
//
// Frames (docs/frames.md): W world, z up, gravity along -z; B body = IMU.
// Time inside a MotionModel is double seconds since t0_ns(); logs get
// t0_ns() + round(t_s * 1e9).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

namespace kestrel::tools {

// Everything an IMU or a camera needs at one instant. Derivatives are exact
// (analytic for scenarios, the spline's own for fitted trajectories), so a
// synthetic IMU integrates back onto the trajectory.
struct TrajectoryState {
  double t_s = 0.0;
  Eigen::Vector3d p_WB = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_WB = Eigen::Quaterniond::Identity();
  Eigen::Vector3d v_WB = Eigen::Vector3d::Zero();  // m/s, in W
  Eigen::Vector3d a_WB = Eigen::Vector3d::Zero();  // m/s^2, in W (kinematic, gravity not included)
  Eigen::Vector3d w_B = Eigen::Vector3d::Zero();   // rad/s, angular velocity of B w.r.t. W, in B
};

class MotionModel {
 public:
  virtual ~MotionModel() = default;
  // Valid for t_s in [0, duration_s()].
  virtual double duration_s() const = 0;
  virtual TrajectoryState state(double t_s) const = 0;
  // Log time of t_s = 0.
  virtual int64_t t0_ns() const = 0;
  virtual std::string description() const = 0;
  // Times (s since t0) of the samples a fitted trajectory came from; camera
  // frames are placed there by default. Empty for analytic scenarios.
  virtual std::vector<double> sample_times_s() const { return {}; }
};

// ---- built-in scenarios ------------------------------------------------------

struct ScenarioOptions {
  // figure8: heading along the path (true) or constant (false).
  bool yaw_follows_path = true;
};

// "hover", "figure8", "aggressive", "static".
std::vector<std::string> scenario_names();
// Default length of a scenario in seconds (hover: 189 s, paper 000's flight).
double default_scenario_duration_s(const std::string& name);
// duration_s <= 0 takes the default. Throws std::invalid_argument for an
// unknown name. The motion depends on name, duration and options only, never
// on the seed: the same flight with different noise is one seed away.
std::unique_ptr<MotionModel> make_scenario(const std::string& name, double duration_s = -1.0,
                                           const ScenarioOptions& options = {});

// ---- ground-truth files and splines -----------------------------------------

struct GtSample {
  int64_t t_ns = 0;
  Eigen::Vector3d p_WB = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_WB = Eigen::Quaterniond::Identity();
};

// Reads an EuRoC-style CSV (`t_ns,px,py,pz,qw,qx,qy,qz[,...]`, e.g.
// gt_body_20hz.csv or state_groundtruth_estimate0) or a TUM trajectory
// (`t_s x y z qx qy qz qw`, space separated), told apart by the first data
// line. Lines starting with '#' are comments. Throws std::runtime_error
// naming "file:line" for a malformed line, a non-unit quaternion or time that
// does not increase; throws when the file cannot be read or has < 4 samples.
std::vector<GtSample> load_gt_file(const std::string& path);

struct SplineFitOptions {
  // Knot spacing in seconds; <= 0 takes the median sample interval, which
  // makes the spline (nearly) interpolate the samples.
  double knot_spacing_s = 0.0;
  // Weight of the squared second differences of the position control
  // points, relative to the sample residuals (0: interpolate).
  double position_smoothing = 0.0;
  // Gauss-Newton passes for the rotation control points.
  int rotation_iterations = 8;
};

// A uniform cubic B-spline on positions and a cumulative cubic B-spline on
// SO(3) (Lovegrove et al. BMVC 2013; derivatives after Sommer et al. CVPR
// 2020). Positions are C2 and rotations C2, so acceleration and body rate are
// continuous and consistent with the pose.
class SplineTrajectory final : public MotionModel {
 public:
  using FitOptions = SplineFitOptions;

  // Least-squares fit to the samples (at least 4, increasing times).
  static SplineTrajectory fit(const std::vector<GtSample>& samples,
                              const SplineFitOptions& options = SplineFitOptions{});
  // load_gt_file, then keep [first + start_s, first + start_s + duration_s]
  // (duration_s <= 0: to the end) and fit. Throws std::invalid_argument when
  // the span holds fewer than 4 samples.
  static SplineTrajectory from_file(const std::string& path, double start_s = 0.0, double duration_s = -1.0,
                                    const SplineFitOptions& options = SplineFitOptions{});

  double duration_s() const override { return duration_s_; }
  TrajectoryState state(double t_s) const override;
  int64_t t0_ns() const override { return t0_ns_; }
  std::string description() const override { return description_; }
  std::vector<double> sample_times_s() const override { return sample_times_s_; }

  double knot_spacing_s() const { return dt_; }
  size_t num_control_points() const { return ctrl_p_.size(); }
  // Largest position / rotation distance between the spline and the samples it was fitted to.
  double max_position_residual_m() const { return max_pos_residual_m_; }
  double max_rotation_residual_rad() const { return max_rot_residual_rad_; }
  void set_description(std::string d) { description_ = std::move(d); }

 private:
  SplineTrajectory() = default;
  int64_t t0_ns_ = 0;
  double duration_s_ = 0.0;
  double dt_ = 0.05;
  std::vector<Eigen::Vector3d> ctrl_p_;
  std::vector<Eigen::Quaterniond> ctrl_q_;
  std::vector<double> sample_times_s_;
  double max_pos_residual_m_ = 0.0;
  double max_rot_residual_rad_ = 0.0;
  std::string description_;
};

// SO(3) helpers shared by the spline, the IMU tests and the scene.
Eigen::Quaterniond so3_exp(const Eigen::Vector3d& phi);
Eigen::Vector3d so3_log(const Eigen::Quaterniond& q);

}  // namespace kestrel::tools

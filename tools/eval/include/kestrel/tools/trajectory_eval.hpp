// Trajectory evaluation: loading, time association, alignment, ATE / RPE
// metrics, and their text / JSON / SVG output. Used by `kestrel eval` and by
// the replay and bench tools. Definitions and formulas: docs/evaluation.md.
//
// Frames: every pose is T_WB (body B in world W, W with gravity along -z);
// positions in metres, times in int64 nanoseconds.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <vector>

namespace kestrel::tools {

struct TimedPose {
  int64_t t_ns = 0;
  Eigen::Vector3d p = Eigen::Vector3d::Zero();            // p_WB [m]
  Eigen::Quaterniond q = Eigen::Quaterniond::Identity();  // q_WB, unit norm
};
using Trajectory = std::vector<TimedPose>;

// Reads a trajectory, whatever it is stored in (detected by content/extension):
//   - TUM text: `t[s] x y z qx qy qz qw`, whitespace separated, '#' comments;
//   - EuRoC CSV: `t[ns],px,py,pz,qw,qx,qy,qz[,more columns ignored]` (gt_body_20hz.csv,
//     state_groundtruth_estimate0/data.csv);
//   - anything kestrel::drivers::open_log reads (.klog file, EuRoC or TUM RGB-D folder):
//     its kGroundTruth records.
// The result is sorted by time with exact duplicates dropped. Every line that is
// skipped (malformed, non-finite, zero quaternion, conflicting duplicate time) and
// every repair (unsorted input, duplicates) is reported in `warnings` as
// "file:line: ..." naming the field. With `warnings == nullptr` the first such
// problem throws std::runtime_error instead, so nothing is ever dropped silently.
// Throws std::runtime_error naming the path when it cannot be read or holds no pose.
Trajectory load_trajectory(const std::string& path, std::vector<std::string>* warnings);

// Writes TUM text (`t[s] x y z qx qy qz qw`, times printed exactly from t_ns).
// Throws std::runtime_error naming the path when it cannot be written.
void write_tum(const std::string& path, const Trajectory& trajectory);

enum class Alignment {
  kNone,    // compare as given
  kSe3,     // rotation + translation (Umeyama without scale)
  kSim3,    // rotation + translation + scale (monocular)
  kPosYaw,  // translation + rotation about world z: the 4 unobservable DoF of VIO
};
// "none" | "se3" | "sim3" | "posyaw"; std::nullopt for anything else.
std::optional<Alignment> parse_alignment(const std::string& name);
const char* alignment_name(Alignment alignment);

// x_W = scale * R * x_E + t: maps estimate-world coordinates into ground-truth world.
struct Sim3 {
  double scale = 1.0;
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
};

// Least-squares alignment of corresponding positions (est[i] <-> gt[i]).
// Needs >= 3 pairs for se3/sim3, >= 2 for posyaw; throws std::invalid_argument otherwise.
Sim3 align_positions(const std::vector<Eigen::Vector3d>& est, const std::vector<Eigen::Vector3d>& gt,
                     Alignment alignment);

// The pose of `trajectory` (sorted) at t_ns: linear position / slerp rotation
// between the two neighbours when both lie within max_gap_ns of t_ns, else the
// nearest neighbour within max_gap_ns, else nullopt. `interpolated` (optional)
// tells which happened.
std::optional<TimedPose> pose_at(const Trajectory& trajectory, int64_t t_ns, int64_t max_gap_ns,
                                 bool* interpolated = nullptr);

// A keyframe as the map holds it at the end of a flight: its body pose in the
// map frame M (after every bundle adjustment and loop correction) and the
// odometry pose T_WB it was taken at.
struct KeyframeAnchor {
  int64_t t_ns = 0;
  Eigen::Isometry3d T_MB = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();
};

// The odometry re-expressed through the map's final keyframes: what a SLAM
// system reports once the flight is over (ORB-SLAM's saved trajectory), not
// what a flight controller could have had at the time. Each keyframe k
// defines a correction C_k = T_MB_k * T_WB(t_k)^-1 (T_WB(t_k): the odometry's
// own pose at the keyframe's stamp when it has one, else the keyframe's), and a
// pose between two keyframes takes the correction interpolated between theirs,
// so every keyframe lands exactly on its map pose and the poses in between
// keep their odometry motion relative to it. The difference of two
// neighbouring corrections is taken and interpolated at each pose's body
// (T^-1 C_a^-1 C_b T), so it does not grow with the distance to W's origin;
// one larger than max_step_m / max_step_rad there is not drift (a reset or a
// relocalisation between them): such poses take the earlier keyframe's alone.
// `keyframes` sorted by time; empty: the odometry unchanged.
Trajectory anchor_to_keyframes(const Trajectory& odometry, const std::vector<KeyframeAnchor>& keyframes,
                               double max_step_m = 0.2, double max_step_rad = 0.1);

struct EvalOptions {
  Alignment align = Alignment::kPosYaw;
  double max_gap_ms = 20.0;                              // association tolerance
  double rpe_delta_s = 1.0;                              // RPE time step
  std::vector<double> segment_lengths_m{1.0, 2.0, 5.0};  // KITTI-style RPE over distance
  // Estimate gaps longer than this do not count towards coverage.
  double coverage_gap_s = 0.5;
};

struct SegmentError {
  double length_m = 0;
  int count = 0;             // segments evaluated (0: trajectory too short)
  double trans_pct = 0;      // mean |translation error| / length * 100
  double rot_deg_per_m = 0;  // mean rotation error angle / length
};

struct Stats {
  double rmse = 0, mean = 0, median = 0, std = 0, min = 0, max = 0;
  int count = 0;
};

struct EvalResult {
  // Inputs, as evaluated.
  Alignment align = Alignment::kPosYaw;
  std::string gt_file, est_file;  // informative only; set by the caller
  int gt_poses = 0;
  int est_poses = 0;
  int matched = 0;
  int interpolated = 0;  // matched through interpolation (the rest: nearest)
  int unmatched = 0;
  double gt_duration_s = 0;
  double gt_length_m = 0;  // path length of the matched ground truth
  double coverage = 0;     // [0, 1] share of the GT time span covered by matched estimates

  Sim3 T_align;  // est world -> gt world

  Stats ate_m;        // position error after alignment [m]
  Stats ate_rot_deg;  // angle of R_gt^T * R_est_aligned [deg]
  // Rotation gain per body axis: the least-squares slope of the estimate's
  // rotation vector against the ground truth's, both taken relative to the
  // first associated pose in that pose's body frame. 1 = no rotation-scale
  // error; tracking noise and drift scatter around 1, a camera model that is
  // off (focal length, distortion, registration) pulls it away on a whole
  // axis. NaN on an axis the ground truth turns less than 2 degrees about.
  Eigen::Vector3d rot_gain = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());

  double rpe_delta_s = 0;
  int rpe_pairs = 0;
  double rpe_trans_rmse_m = 0, rpe_trans_mean_m = 0;
  double rpe_trans_m_per_s = 0;  // RMSE of |translation error| / pair duration
  double rpe_rot_rmse_deg = 0, rpe_rot_mean_deg = 0;

  std::vector<SegmentError> segments;

  // Per associated pose, in time order (for plots and further analysis).
  std::vector<TimedPose> gt_matched;   // ground truth at the estimate times
  std::vector<TimedPose> est_aligned;  // T_align * estimate
  std::vector<double> pos_err_m;
  std::vector<double> rot_err_deg;

  std::vector<std::string> warnings;  // unmatched poses, degenerate inputs...
};

// Associates, aligns and computes all metrics. Throws std::runtime_error when too
// few poses associate for the requested alignment (the message says how many did),
// std::invalid_argument for nonsensical options.
EvalResult evaluate(const Trajectory& gt, const Trajectory& est, const EvalOptions& options);

// RPE over a fixed time step on what evaluate() associated and aligned
// (r.gt_matched, r.est_aligned): evaluate() reports it for
// EvalOptions::rpe_delta_s; a report calls it for several deltas. pairs == 0
// (and NaN statistics) when no pose has another delta_s later. Throws
// std::invalid_argument for delta_s <= 0.
struct RpeStats {
  double delta_s = 0;
  int pairs = 0;
  double trans_rmse_m = 0, trans_mean_m = 0;
  double trans_m_per_s = 0;  // RMSE of |translation error| / pair duration
  double rot_rmse_deg = 0, rot_mean_deg = 0;
};
RpeStats relative_pose_error(const EvalResult& r, double delta_s, double max_gap_ms);

// `key: value` lines; the first line is always `ate_rmse_m: <value>`.
std::string to_text(const EvalResult& result);
// One JSON object with the same keys as to_text (non-finite numbers as null).
std::string to_json(const EvalResult& result);

// Self-contained SVG: left, top view (x-y) of the ground truth and the aligned
// estimate; right, position error over time. Throws std::runtime_error naming
// the path when it cannot be written.
void write_svg_plot(const std::string& path, const Trajectory& gt, const EvalResult& result,
                    const std::string& title = "");

// One latency distribution of a replay, as `kestrel replay --metrics-out`
// exports it: percentiles and the histogram's non-empty bins.
struct LatencyDistribution {
  struct Bin {
    int64_t lower_ns = 0, width_ns = 0;
    uint64_t count = 0;
  };
  std::string name;  // imu_to_output, tracking, estimator_imu, optimizer
  uint64_t count = 0;
  double p50_ms = 0, p90_ms = 0, p99_ms = 0, max_ms = 0;
  std::vector<Bin> bins;
};
// The non-empty histograms of a replay metrics file. Throws std::runtime_error
// naming the file and the field ("m.json: latency.tracking.bins[3]: expected
// [lower_ns, width_ns, count]").
std::vector<LatencyDistribution> read_replay_latencies(const std::string& metrics_json_path);

struct HtmlReportOptions {
  std::string title;
  // RPE is shown for each of these that fits in the associated estimate.
  std::vector<double> rpe_deltas_s{0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100};
  double max_gap_ms = 20.0;                    // as evaluated (RPE pairing tolerance)
  std::vector<LatencyDistribution> latencies;  // empty: no latency section
  std::string metrics_file;                    // where they came from, for the page
};
// One self-contained HTML page (inline CSS and SVG, no script, nothing
// fetched): summary, top and side views after alignment, position / rotation
// / per-axis error over time, RPE over several time steps, and the run's
// latency histograms when given. Throws std::runtime_error naming the path
// when it cannot be written.
void write_html_report(const std::string& path, const Trajectory& gt, const EvalResult& result,
                       const HtmlReportOptions& options);

}  // namespace kestrel::tools

// `kestrel sim` as a library: a textured room rendered into colour +
// registered depth along a trajectory, a synthetic (or real) IMU, and ground
// truth, written as one .klog. docs/simulator.md describes the models.
//
// Pieces usable on their own (tests, bench): MotionModel / make_scenario /
// SplineTrajectory (sim_trajectory.hpp), ImuModel / ImuSynth (sim_imu.hpp),
// Scene / Renderer (sim_render.hpp).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/drivers/klog_image_codec.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/msgs.hpp"
#include "kestrel/tools/sim_imu.hpp"
#include "kestrel/tools/sim_render.hpp"
#include "kestrel/tools/sim_trajectory.hpp"

namespace kestrel::tools {

// A bad option value or a missing input file: the caller's mistake (the CLI
// turns it into a usage error). Malformed file contents are std::runtime_error.
struct SimOptionError : std::invalid_argument {
  using std::invalid_argument::invalid_argument;
};

struct SimOptions {
  // Motion: a built-in scenario, or a ground-truth file (EuRoC csv / TUM txt).
  std::string scenario = "hover";
  std::string trajectory_path;
  // Hybrid mode: the real IMU (EuRoC imu0.csv) is written as is, the camera
  // is rendered along the spline of trajectory_path.
  std::string imu_path;
  // Real images (`--images`): a recording with ground truth and no IMU, read
  // by any reader (images_format, `auto` detects it; rig_path and fps go to
  // the reader). Its images and ground truth are written as they are, with
  // an IMU synthesised along a smoothing spline through the ground truth
  // (knot_spacing_s, default 0.1 s, and position_smoothing).
  std::string images_path;
  std::string images_format = "auto";
  double position_smoothing = 0.0;  // --images: second-difference weight of the position spline
  std::string out_path;             // .klog (run_simulation(options) only)
  drivers::klog::ImageCompression image_compression{};  // of the .klog's images (--image-codec)

  double duration_s = -1.0;  // <= 0: scenario default / whole file
  double start_s = 0.0;      // into the ground-truth file
  uint64_t seed = 1;

  // Unset: from the rig file, else the built-in rig (640x480, 30 Hz, 400 Hz).
  // With a GT file and no fps, frames are at the file's sample times when
  // those come at <= 60 Hz.
  std::optional<int> width;
  std::optional<int> height;
  std::optional<double> fps;
  std::optional<double> imu_rate_hz;
  std::string rig_path;  // optional rig YAML (drivers/rig_yaml.hpp schema)

  double time_offset_ms = 0.0;  // frame stamps = true time - offset (t_imu = t_cam + offset)
  // What the log's rig says the offset is (unset: time_offset_ms). A value
  // other than the true one makes a miscalibrated log (kestrel replay with
  // window.estimate_time_offset finds the difference).
  std::optional<double> rig_time_offset_ms;
  double timestamp_jitter_us = 0.0;  // std of frame stamp noise
  double frame_drop_rate = 0.0;      // probability a frame is lost (not written)

  bool noise = true;  // false: ideal IMU, exact depth, clean images, no dropouts
  // Stereo (`--stereo`): a right camera like the left one, baseline_m along
  // the left camera's x; the log holds stereo pairs instead of depth images.
  bool stereo = false;
  double stereo_baseline_m = 0.11;  // EuRoC's VI-Sensor
  double depth_dropout = 0.003;     // share of depth pixels lost in small blobs
  double image_noise_sigma = 1.0;   // 8-bit DN
  double acc_bias_tau_s = 300.0;    // paper 000 eq. 6
  std::string texture_path;         // optional image for walls, floor and ceiling
  // Conditions that make tracking hard (the `hard` scenario turns them all on, docs/simulator.md):
  double room_m = 0.0;           // > 0: a hall at least this long on each side, walls up to this far
                                 // from the path (beyond the depth range)
  double exposure_change = 0.0;  // image gain swings by up to +- this share (drift and sudden steps)
  double motion_blur_ms = 0.0;   // exposure time, rendered as sub-frames averaged
  bool bare_wall = false;        // the +x wall is bare paint (low texture)
  // A lens covered (a kidnap: the camera sees nothing while the vehicle
  // moves on): frames in [cover_at_s, cover_at_s + cover_s) are near-black
  // sensor noise with no depth. cover_s <= 0: never.
  double cover_at_s = 0.0;
  double cover_s = 0.0;
  bool yaw_follows_path = true;  // figure8
  double gt_rate_hz = 200.0;     // ground truth records (plus one at every frame)
  double knot_spacing_s = 0.0;   // GT spline; <= 0: the file's sample interval
  int threads = 2;               // render threads
};

struct SimSummary {
  std::string trajectory;  // what was flown
  bool hybrid = false;
  double duration_s = 0.0;
  uint64_t frames = 0;  // written (colour + depth pairs)
  uint64_t frames_dropped = 0;
  uint64_t imu_samples = 0;
  uint64_t imu_saturated = 0;  // samples with a saturation flag
  uint64_t gt_records = 0;
  uint64_t events = 0;
  double render_s = 0.0;  // time inside Renderer::render
  double render_fps = 0.0;
  double wall_s = 0.0;
  uint64_t output_bytes = 0;
  Eigen::Vector3d room_size_m = Eigen::Vector3d::Zero();
  size_t clutter_objects = 0;
  Rig rig;                   // as written into the log
  bool real_images = false;  // --images
  // --images: how far the spline the IMU follows is from the ground truth the
  // images were taken at (what the synthetic IMU cannot know about).
  double spline_rms_position_residual_m = 0.0;
  double spline_max_position_residual_m = 0.0;
  double spline_max_rotation_residual_rad = 0.0;
  std::vector<drivers::LogProblem> problems;  // --images: what the reader reported
};

// Where the records go, in time order. The .klog sink wraps KlogWriter; tests
// use their own to hash or count.
class SimSink {
 public:
  virtual ~SimSink() = default;
  virtual void begin(const Rig& rig) = 0;
  virtual void imu(const ImuSample& s) = 0;
  // type is kRgb or kDepth; view.stride_bytes = width * bytes per pixel.
  virtual void image(drivers::RecordType type, int64_t t_ns, uint32_t seq, const ImageView& view) = 0;
  virtual void ground_truth(const GroundTruthPose& gt) = 0;
  virtual void event(const Event& e) = 0;
  virtual void end() = 0;
  virtual uint64_t bytes() const { return 0; }
};

// The built-in rig: a forward-looking RGB-D camera (Kinect-class pinhole,
// mild radtan distortion) on a BMX055 at 400 Hz.
Rig default_sim_rig(int width = 640, int height = 480, double fps = 30.0, double imu_rate_hz = 400.0);
Eigen::Isometry3d to_isometry(const Mat4d& T);
Mat4d to_mat4(const Eigen::Isometry3d& T);

// A rig file in the project's schema (drivers/rig_yaml.hpp) replaces `rig`;
// its IMU noise figures, when it has any, replace those of `imu`. Throws
// std::runtime_error naming the file and field.
void load_sim_rig_yaml(const std::string& path, Rig& rig, ImuModel& imu);
// EuRoC ASL sensor files, read by drivers::read_euroc_sensor_yaml (the EuRoC
// reader's own). Return false when the file does not exist; throw
// std::runtime_error naming file and key when it is malformed (the IMU file
// must state all four noise figures).
bool read_euroc_imu_yaml(const std::string& path, ImuModel& model, double& rate_hz);
bool read_euroc_T_BS(const std::string& path, Eigen::Isometry3d& T_BS);

// --images: real images, synthesised IMU (called by run_simulation).
SimSummary run_image_simulation(const SimOptions& options, SimSink& sink);

// Runs the whole simulation into `sink`. Throws SimOptionError for bad
// options or missing files, std::runtime_error for malformed inputs.
SimSummary run_simulation(const SimOptions& options, SimSink& sink);
// Same, written to options.out_path as a .klog.
SimSummary run_simulation(const SimOptions& options);

std::string format_summary(const SimSummary& s);

}  // namespace kestrel::tools

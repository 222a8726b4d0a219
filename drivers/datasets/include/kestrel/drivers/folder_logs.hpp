// LogSources over public dataset folders: EuRoC MAV (ASL layout or the flat
// layout of ../shared/data/euroc/<seq>/) and TUM RGB-D. What each reader
// takes from which file, and its choices, are in docs/log-format.md.
#pragma once

#include <array>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/open_log.hpp"

namespace kestrel::drivers {
namespace text {
class StreamLogSource;
}

// Both readers index their tables at construction (IMU and ground truth in
// memory, images listed but decoded only when replayed) and merge the
// streams in time order; at equal times IMU comes first.
class FolderLogSource : public LogSource {
 public:
  ~FolderLogSource() override;
  const Rig& rig() const override;
  bool next(LogRecord& out) override;
  void rewind() override;
  const std::vector<LogProblem>& problems() const override;

  // The files the streams were read from ("" when a stream is absent).
  const std::string& imu_file() const { return imu_file_; }
  const std::string& ground_truth_file() const { return gt_file_; }
  size_t imu_count() const;
  size_t rgb_count() const;  // listed images whose file exists
  size_t depth_count() const;
  size_t right_count() const;  // a stereo pair's right images (EuRoC cam1) whose file exists
  size_t ground_truth_count() const;

 protected:
  FolderLogSource();
  std::unique_ptr<text::StreamLogSource> impl_;
  std::string imu_file_;
  std::string gt_file_;
};

// EuRoC: `path` is a sequence folder holding mav0/, a mav0/ folder, or a flat
// folder with imu0.csv. cam0 images become kRgb records in kGray8; a
// depth0/ folder (as written by export_euroc) becomes kDepth records; a
// kestrel_rig.yaml beside the sensor folders replaces the sensor.yaml rig.
// Throws std::runtime_error when there is no IMU table or a sensor.yaml is malformed.
class EurocReader final : public FolderLogSource {
 public:
  explicit EurocReader(const std::string& path);
  std::string format_name() const override { return "euroc"; }
  bool flat_layout() const { return flat_; }

 private:
  bool flat_ = false;
};

// TUM-VI (the "dataset-<name>_512_16" export): mav0/cam0, cam1, imu0 as in
// EuRoC's ASL layout (16-bit grey PNGs become 8-bit grey), the Kalibr chain
// dso/camchain.yaml (equidistant; cam1 makes it a stereo rig), the IMU noise of
// dso/imu_config.yaml, ground truth from mav0/mocap0/data.csv. A missing
// calibration, right image or IMU file is reported and survived (monocular /
// default figures); right images whose stamp has no left image are named.
// Throws std::runtime_error without mav0/ or an IMU table, or when the chain
// is malformed (naming the file and the field).
class TumviReader final : public FolderLogSource {
 public:
  // A right image pairs with the left one within this (the cameras are triggered together).
  static constexpr int64_t kStereoPairToleranceNs = 1'000'000;
  explicit TumviReader(const std::string& path);
  std::string format_name() const override { return "tumvi"; }
  const std::string& camchain_file() const { return camchain_file_; }

 private:
  std::string camchain_file_;
};

// TUM RGB-D: rgb.txt (required), depth.txt, groundtruth.txt, accelerometer.txt.
class TumReader final : public FolderLogSource {
 public:
  struct Options {
    int64_t max_association_dt_ns = 20'000'000;  // rgb <-> depth, as TUM's associate.py uses
  };
  explicit TumReader(const std::string& path);
  TumReader(const std::string& path, const Options& options);
  std::string format_name() const override { return "tum"; }
  size_t associated_pairs() const { return pairs_; }

 private:
  size_t pairs_ = 0;
};

// One EuRoC ASL sensor file (mav0/<sensor>/sensor.yaml, or <sensor>_sensor.yaml
// in the flat layout), as the dataset writes it (OpenCV's "%YAML:1.0" first line
// tolerated). The one reader of these files: the EuRoC reader builds its rig
// from it, the simulator's hybrid mode takes the real IMU's noise and the
// camera placement from it. Keys other than T_BS are optional, present ones
// are checked; a malformed file throws std::runtime_error naming it and the key.
struct EurocSensorYaml {
  Mat4d T_BS{};  // sensor -> body, row-major ("T_BS: {rows, cols, data}" or a bare list of 16)
  std::optional<double> rate_hz;
  // Cameras.
  std::optional<std::array<int, 2>> resolution_px;      // width, height
  std::optional<std::array<double, 4>> intrinsics_px;   // fu fv cu cv (focal lengths > 0)
  DistortionModel distortion = DistortionModel::kNone;  // radial-tangential (radtan), equidistant, none
  std::vector<double> distortion_coefficients;          // up to 5
  // IMUs (continuous-time densities, as Kalibr states them).
  std::optional<double> gyro_noise_density_rad_s_sqrthz;  // gyroscope_noise_density
  std::optional<double> gyro_random_walk_rad_s2_sqrthz;   // gyroscope_random_walk
  std::optional<double> acc_noise_density_mps2_sqrthz;    // accelerometer_noise_density
  std::optional<double> acc_random_walk_mps3_sqrthz;      // accelerometer_random_walk
};
EurocSensorYaml read_euroc_sensor_yaml(const std::string& path);

// True when `path` looks like an EuRoC / a TUM folder (used by open_log).
bool is_euroc_folder(const std::string& path);
bool is_tum_folder(const std::string& path);
// A folder with mav0/ and dso/camchain.yaml or mav0/mocap0/ (EuRoC has neither).
bool is_tumvi_folder(const std::string& path);

}  // namespace kestrel::drivers

// The camera-IMU time offset from rotation alone: the rotation the camera saw
// between two frames (vision only, body frame) is compared with the gyro's
// integral over the same interval shifted by each candidate offset, and the
// offset whose shift fits best over the last seconds of flight wins.
//
// Why this and not only the window's t_d state: shifting every pixel by its
// image velocity times t_d is, to first order, the same as moving each pose by
// (v t_d, w t_d), so in the window vision cannot tell t_d from the poses and
// only the IMU's second-order terms can - which the window's inflated IMU noise
// leaves too weak to move t_d (docs/optimizer.md). The gyro, compared with the
// camera's own rotation, sees the offset directly wherever the angular velocity
// changes. The window keeps its t_d state; this estimate is its measurement.
//
// Fixed memory, no allocation after construction; one thread (the tracking
// thread feeds both gyro samples and camera rotations).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <memory>
#include <string>

namespace kestrel::core {

struct TimeOffsetCalibratorOptions {
  double search_ms = 60.0;    // offsets tried: [-search_ms, +search_ms]
  double step_ms = 0.5;       // grid of the search; the minimum is refined by a parabola
  double memory_s = 30.0;     // evidence older than this fades (e^-1): the offset and the gyro bias may drift
  int min_intervals = 90;     // camera intervals (about 3 s at 30 Hz) before a first estimate
  double max_sigma_ms = 1.0;  // an estimate less certain than this is not published
  double sigma_floor_ms = 0.2;  // the 1-sigma reported is at least this (the residual is not white)
  double gate_rad = 0.05;       // an interval no candidate offset explains within this is an outlier
  double max_interval_s = 0.5;  // longer camera intervals are not used (the gyro history, the bias)
  int gyro_capacity = 4096;     // samples kept: 2 s at 2 kHz, beyond the longest interval + 2 search windows
  std::string validate() const;
};

struct TimeOffsetEstimate {
  bool valid = false;
  double td_s = 0.0;          // a frame stamped t was taken at t + td_s on the IMU's clock
  double sigma_s = 0.0;       // 1-sigma
  double intervals = 0;       // evidence behind it (forgetting-weighted count)
  double residual_rad = 0.0;  // rms per axis of camera - gyro rotation at the estimate
};

class TimeOffsetCalibrator {
 public:
  // R_BC: the camera's rotation in the body (IMU) frame, from the rig.
  TimeOffsetCalibrator(const TimeOffsetCalibratorOptions& opt, const Eigen::Matrix3d& R_BC);
  ~TimeOffsetCalibrator();
  TimeOffsetCalibrator(const TimeOffsetCalibrator&) = delete;
  TimeOffsetCalibrator& operator=(const TimeOffsetCalibrator&) = delete;

  // Gyro samples in increasing time, the caller's bias estimate taken off
  // (what is left is fitted as a constant); others are ignored.
  void add_gyro(int64_t t_ns, const Eigen::Vector3d& gyro_rps);
  // The camera's rotation from the frame stamped t0 to the frame stamped t1,
  // measured by vision alone, in the first camera's frame (R_C0C1). It is
  // used once the gyro has reached t1 + search_ms. Long intervals (a frame
  // against its keyframe) show the offset better than consecutive frames:
  // the angular velocity differs more between their ends, the noise does not grow.
  void add_camera_rotation(int64_t t0_ns, int64_t t1_ns, const Eigen::Matrix3d& R_C0C1);

  TimeOffsetEstimate estimate() const { return est_; }
  void reset();

  int64_t used_intervals() const { return used_; }
  int64_t gated_intervals() const { return gated_; }
  int64_t dropped_intervals() const { return dropped_; }  // pending ring full or the gyro history too short

 private:
  struct Gyro {
    int64_t t_ns = 0;
    Eigen::Vector3d w;
    Eigen::Quaterniond q;  // the body's attitude integrated from the first sample kept (q_B0B)
  };
  struct Interval {
    int64_t t0_ns = 0, t1_ns = 0;
    Eigen::Quaterniond q_B0B1;  // the camera's rotation, in the body frame
  };
  const Gyro& gyro_at(int k) const { return gyro_[(g_head_ + k) % opt_.gyro_capacity]; }
  bool relative(int64_t a_ns, int64_t b_ns, Eigen::Quaterniond* q_ab) const;
  bool attitude(int64_t t_ns, Eigen::Quaterniond* out) const;
  void absorb(const Interval& iv);
  void solve();

  TimeOffsetCalibratorOptions opt_;
  Eigen::Matrix3d R_BC_;
  int n_grid_ = 0;
  std::unique_ptr<Gyro[]> gyro_;
  int g_head_ = 0, g_n_ = 0;
  static constexpr int kPending = 64;
  Interval pending_[kPending];
  int p_head_ = 0, p_n_ = 0;
  // Per candidate offset: sum of |d|^2 and of dt * d (d = camera - gyro
  // rotation); shared: sum of dt^2 (a constant gyro bias is fitted away).
  std::unique_ptr<double[]> sdd_;
  std::unique_ptr<Eigen::Vector3d[]> sd_;
  std::unique_ptr<double[]> cost_;
  std::unique_ptr<Eigen::Vector3d[]> d_;  // scratch: one interval's residual per offset
  double stt_ = 0.0, n_eff_ = 0.0;
  int64_t last_t1_ns_ = -1;
  TimeOffsetEstimate est_;
  int64_t used_ = 0, gated_ = 0, dropped_ = 0;
};

}  // namespace kestrel::core

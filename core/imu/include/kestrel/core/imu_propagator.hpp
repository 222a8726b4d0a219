// IMU-only strapdown propagation and static initialisation.
//
// This is the estimator of last resort: what the tracker coasts on when vision
// fails, and, until the visual front end exists, the honest "IMU dead
// reckoning" baseline that replay runs and bench scores. It never looks at
// ground truth: the initial attitude comes from gravity, yaw and position are
// zero, the gyro bias comes from a stationary period.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>

#include "kestrel/msgs.hpp"

namespace kestrel::core {

inline Eigen::Vector3d to_eigen(const Vec3d& v) { return {v[0], v[1], v[2]}; }

struct NavState {
  int64_t t_ns = 0;
  Eigen::Vector3d p_WB = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_WB = Eigen::Quaterniond::Identity();
  Eigen::Vector3d v_WB = Eigen::Vector3d::Zero();
  Eigen::Vector3d bg_rps = Eigen::Vector3d::Zero();   // gyro bias
  Eigen::Vector3d ba_mps2 = Eigen::Vector3d::Zero();  // accelerometer bias
};

// A NavState as plain numbers (trivially copyable), for the seqlock
// mailboxes that hand states between threads (rt::Mailbox).
struct PackedNavState {
  int64_t t_ns;
  double p[3], q[4], v[3], bg[3], ba[3];  // q: w, x, y, z
};
PackedNavState pack(const NavState& x);
NavState unpack(const PackedNavState& x);

// Why an IMU sample was not used. Counted, never thrown.
struct ImuRejectCounts {
  uint64_t non_finite = 0;
  uint64_t saturated = 0;
  uint64_t out_of_order = 0;  // time not after the previous sample (duplicates included)
  uint64_t gaps = 0;          // spacing larger than max_gap_ns: integrated across, but counted
};

struct ImuPropagatorOptions {
  double gravity_mps2 = 9.81;
  int64_t max_gap_ns = 50'000'000;  // above this a gap is reported
  int64_t max_integration_step_ns =
      200'000'000;  // beyond this, hold the state instead of integrating garbage
};

// Gravity and gap limits from the rig (gap: five IMU periods).
ImuPropagatorOptions imu_propagator_options(const Rig& rig);

// Midpoint (trapezoidal) strapdown integration in W (z up, gravity -z).
class ImuPropagator {
 public:
  explicit ImuPropagator(const ImuPropagatorOptions& opt = {}) : opt_(opt) {}

  void reset(const NavState& s);
  // Replaces the state without dropping the last sample as the integration
  // anchor: a correction of the estimate, not a restart. s.t_ns must be the
  // current state's time (else this is a reset).
  void correct(const NavState& s);
  bool initialized() const { return initialized_; }
  // Returns false when the sample was rejected (see counts()).
  bool propagate(const ImuSample& s);
  const NavState& state() const { return state_; }
  const ImuRejectCounts& counts() const { return counts_; }

 private:
  ImuPropagatorOptions opt_;
  NavState state_;
  bool initialized_ = false;
  bool have_prev_ = false;
  Eigen::Vector3d prev_gyro_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d prev_acc_ = Eigen::Vector3d::Zero();
  ImuRejectCounts counts_;
};

// True when a sample carries numbers the estimator may use.
bool imu_sample_usable(const ImuSample& s);

struct StaticInitOptions {
  int64_t window_ns = 500'000'000;  // stationary span needed
  int64_t block_ns = 100'000'000;   // the window is judged by the means of blocks this long
  // Stationarity: every block mean within these bounds of the window mean.
  // Judging block means, not samples, lets a vehicle sitting with its motors
  // running (vibration: 0.6 m/s^2, 0.05 rad/s sample spread on EuRoC) count
  // as still, while a slow real motion does not.
  double max_gyro_dev_rps = 0.03;
  double max_acc_dev_mps2 = 0.3;
  double gravity_mps2 = 9.81;
};

// Collects samples until a stationary window is seen, then yields the initial
// state: roll and pitch from the mean specific force, gyro bias from the mean
// rate, yaw and position zero (unobservable), velocity zero.
// Fixed memory: per-block sums over a sliding window of blocks.
class StaticInitializer {
 public:
  static constexpr int kMaxBlocks = 32;
  explicit StaticInitializer(const StaticInitOptions& opt = {}) : opt_(opt) {}
  // Returns true once initialisation succeeded; `out` then holds the state at s.t_ns.
  bool add(const ImuSample& s, NavState& out);
  void reset();
  // Means over the last complete window (valid after enough samples), for
  // callers that must start without a still period.
  bool window_means(Eigen::Vector3d* gyro_mean, Eigen::Vector3d* acc_mean) const;

 private:
  struct Block {
    Eigen::Vector3d sum_g = Eigen::Vector3d::Zero();
    Eigen::Vector3d sum_a = Eigen::Vector3d::Zero();
    int n = 0;
  };
  int ring_size() const;
  bool window_stats(Eigen::Vector3d* mean_g, Eigen::Vector3d* mean_a, double* dev_g, double* dev_a) const;
  StaticInitOptions opt_;
  Block blocks_[kMaxBlocks];
  int n_blocks_ = 0;  // complete blocks held (oldest first, ring)
  int head_ = 0;      // ring index of the oldest complete block
  Block cur_;
  int64_t cur_start_ns_ = -1;
  int64_t last_t_ns_ = -1;
};

}  // namespace kestrel::core

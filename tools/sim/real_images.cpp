// `kestrel sim --images DIR`: real images, synthesised IMU. The reverse of the
// hybrid logs (rendered images, real IMU): a recording with ground truth and
// no IMU (7-Scenes, TUM RGB-D, ETH3D...) gets an IMU synthesised along a
// smoothing spline through its ground truth, with the rig's noise model, so
// the full visual-inertial estimator runs on real frames (docs/simulator.md).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>

#include "kestrel/drivers/open_log.hpp"
#include "kestrel/tools/simulator.hpp"

namespace kestrel::tools {

SimSummary run_image_simulation(const SimOptions& o, SimSink& sink) {
  using Clock = std::chrono::steady_clock;
  const auto wall0 = Clock::now();
  drivers::LogOpenOptions lo;
  try {
    lo.format = drivers::parse_log_format(o.images_format);
  } catch (const std::runtime_error& e) {
    throw SimOptionError(e.what());
  }
  lo.rig_path = o.rig_path;
  lo.fps = o.fps.value_or(30.0);
  std::unique_ptr<drivers::LogSource> src = drivers::open_log(o.images_path, lo);

  // The ground truth, once through: it is what the IMU follows.
  std::vector<GtSample> gt;
  drivers::LogRecord rec;
  while (src->next(rec)) {
    if (rec.type == drivers::RecordType::kImu)
      throw SimOptionError(o.images_path + ": has an IMU of its own; --images is for recordings without one");
    if (rec.type != drivers::RecordType::kGroundTruth) continue;
    GtSample s;
    s.t_ns = rec.gt.t_ns;
    s.p_WB = Eigen::Vector3d(rec.gt.p_WB[0], rec.gt.p_WB[1], rec.gt.p_WB[2]);
    s.q_WB = Eigen::Quaterniond(rec.gt.q_WB[0], rec.gt.q_WB[1], rec.gt.q_WB[2], rec.gt.q_WB[3]).normalized();
    if (!gt.empty() && s.t_ns <= gt.back().t_ns) continue;  // the reader reported it
    gt.push_back(s);
  }
  if (gt.size() < 4) {
    throw SimOptionError(o.images_path + ": " + std::to_string(gt.size()) +
                         " ground-truth poses; --images needs a recording with ground truth");
  }
  SplineFitOptions fo;
  fo.knot_spacing_s = o.knot_spacing_s > 0 ? o.knot_spacing_s : 0.1;
  fo.position_smoothing = o.position_smoothing;
  SplineTrajectory traj = SplineTrajectory::fit(gt, fo);
  traj.set_description("real images of " + o.images_path + ", IMU along a spline through its " +
                       std::to_string(gt.size()) + " ground-truth poses");

  // The recording's rig (its camera, depth and T_BC: the ground truth is the
  // body's) with an IMU: the rig file's noise figures when it has them, else
  // the BMX055's.
  Rig rig = src->rig();
  ImuModel model = ImuModel::bmx055(o.acc_bias_tau_s);
  if (rig.imu.gyro_noise_density_rad_s_sqrthz > 0 && rig.imu.acc_noise_density_mps2_sqrthz > 0) {
    model.gyro_noise_density_rad_s_sqrthz = rig.imu.gyro_noise_density_rad_s_sqrthz;
    model.gyro_random_walk_rad_s2_sqrthz = rig.imu.gyro_random_walk_rad_s2_sqrthz;
    model.acc_noise_density_mps2_sqrthz = rig.imu.acc_noise_density_mps2_sqrthz;
    model.acc_random_walk_mps3_sqrthz = rig.imu.acc_random_walk_mps3_sqrthz;
    model.acc_bias_tau_s = rig.imu.acc_bias_tau_s;
  }
  if (!o.noise) model = model.ideal();
  rig.imu_rate_hz = o.imu_rate_hz.value_or(rig.imu_rate_hz > 0 ? rig.imu_rate_hz : 400.0);
  rig.imu = model.to_rig();
  rig.name = rig.name.empty() ? "real-images+synth-imu" : rig.name + "+synth-imu";

  SimSummary sum;
  sum.trajectory = traj.description();
  sum.duration_s = traj.duration_s();
  sum.rig = rig;
  {
    double se = 0;
    for (const GtSample& g : gt) {
      const double e = (traj.state(1e-9 * static_cast<double>(g.t_ns - traj.t0_ns())).p_WB - g.p_WB).norm();
      se += e * e;
    }
    sum.spline_rms_position_residual_m = std::sqrt(se / static_cast<double>(gt.size()));
    sum.spline_max_position_residual_m = traj.max_position_residual_m();
    sum.spline_max_rotation_residual_rad = traj.max_rotation_residual_rad();
  }

  // One pass in time order: the recording's records as they are, the IMU
  // samples up to each record's time first.
  ImuSynth synth(model, rig.imu_rate_hz, rig.gravity_mps2, o.seed);
  const int64_t t0 = traj.t0_ns();
  const uint64_t n_imu = static_cast<uint64_t>(std::floor(traj.duration_s() * rig.imu_rate_hz + 1e-9)) + 1;
  uint64_t ki = 0;
  int64_t next_bias_event = t0;
  auto imu_until = [&](int64_t t_ns) {
    for (; ki < n_imu; ++ki) {
      const int64_t ti =
          t0 + static_cast<int64_t>(std::llround(static_cast<double>(ki) * 1e9 / rig.imu_rate_hz));
      if (ti > t_ns) return;
      const ImuSample m = synth.sample(traj.state(1e-9 * static_cast<double>(ti - t0)), ti);
      if (m.flags & (kImuGyroSaturated | kImuAccSaturated)) ++sum.imu_saturated;
      if (ti >= next_bias_event && o.noise) {
        const Eigen::Vector3d& bg = synth.gyro_bias_rps();
        const Eigen::Vector3d& ba = synth.acc_bias_mps2();
        char buf[256];
        std::snprintf(buf, sizeof buf, "true_bias gyro_rps=%.9g,%.9g,%.9g acc_mps2=%.9g,%.9g,%.9g", bg.x(),
                      bg.y(), bg.z(), ba.x(), ba.y(), ba.z());
        sink.event(Event{ti, EventCode::kInfo, buf});
        ++sum.events;
        next_bias_event += 1'000'000'000;
      }
      sink.imu(m);
      ++sum.imu_samples;
    }
  };
  sink.begin(rig);
  src->rewind();
  bool first = true;
  while (src->next(rec)) {
    const int64_t t = rec.type == drivers::RecordType::kGroundTruth ? rec.gt.t_ns
                      : rec.type == drivers::RecordType::kEvent     ? rec.event.t_ns
                                                                    : rec.image.t_ns;
    if (first) {
      sink.event(Event{std::min(t, t0), EventCode::kInfo, "kestrel sim: " + traj.description()});
      ++sum.events;
      first = false;
    }
    imu_until(t);
    switch (rec.type) {
      case drivers::RecordType::kRgb:
      case drivers::RecordType::kDepth:
      case drivers::RecordType::kRight:
        sink.image(rec.type, rec.image.t_ns, rec.image.seq, rec.image.view());
        sum.frames += rec.type == drivers::RecordType::kRgb;
        break;
      case drivers::RecordType::kGroundTruth:
        sink.ground_truth(rec.gt);
        ++sum.gt_records;
        break;
      case drivers::RecordType::kEvent:
        sink.event(rec.event);
        ++sum.events;
        break;
      case drivers::RecordType::kImu:
        break;
    }
  }
  imu_until(t0 + static_cast<int64_t>(std::llround(traj.duration_s() * 1e9)));
  sink.end();
  sum.problems = src->problems();
  sum.output_bytes = sink.bytes();
  sum.wall_s = std::chrono::duration<double>(Clock::now() - wall0).count();
  return sum;
}

}  // namespace kestrel::tools

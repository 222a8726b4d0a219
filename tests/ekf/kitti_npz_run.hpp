// The first 100 steps of paper 003's KITTI 0027 through the EKF-SLAM filter
// with the settings `kestrel ekf-slam` uses (docs/ekf.md): shared by the
// correctness test (test_npz_reader) and the timing test (test_npz_timing).
#pragma once

#include <vector>

#include "kestrel/core/ekf_slam.hpp"
#include "kestrel/drivers/npz_reader.hpp"

namespace kestrel::test {

struct KittiShortRun {
  int used = 0;         // observations the updates used
  int gated = 0;        // ... and rejected by the gate
  double p_norm_m = 0;  // distance of the final pose from the start
};

inline KittiShortRun run_kitti_100_steps(const drivers::KittiVislamSequence& seq) {
  KittiShortRun out;
  kestrel::core::ekf::StereoCamera cam;
  cam.fsu = seq.K[0];
  cam.fsv = seq.K[4];
  cam.cu = seq.K[2];
  cam.cv = seq.K[5];
  cam.baseline_m = seq.baseline_m;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) cam.T_CB.R(r, c) = seq.cam_T_imu[4 * r + c];
    cam.T_CB.p(r) = seq.cam_T_imu[4 * r + 3];
  }
  kestrel::core::EkfSlamOptions opt;
  opt.max_missed_frames = 0;
  opt.pixel_sigma_px = 2.0;  // the values `kestrel ekf-slam` uses (docs/ekf.md)
  opt.vel_sigma_mps = 1.0;
  opt.gyro_vel_sigma_rps = 0.1;
  kestrel::core::EkfSlam ekf(opt, cam);
  std::vector<kestrel::core::StereoObservation> obs;
  for (size_t t = 0; t < 100; ++t) {
    if (t > 0)
      ekf.predict_velocity(Eigen::Vector3d(&seq.v_B_mps[3 * (t - 1)]),
                           Eigen::Vector3d(&seq.w_B_rps[3 * (t - 1)]), seq.t_s[t] - seq.t_s[t - 1]);
    obs.clear();
    for (size_t k = seq.step_begin[t]; k < seq.step_begin[t + 1]; ++k) {
      const auto& f = seq.features[k];
      obs.push_back({f.id, f.uL, f.vL, f.uR, f.vR});
    }
    const auto st = ekf.update(obs.data(), static_cast<int>(obs.size()));
    out.used += st.used;
    out.gated += st.gated;
    ekf.clear_frozen();
  }
  out.p_norm_m = ekf.pose().p.norm();
  return out;
}

}  // namespace kestrel::test

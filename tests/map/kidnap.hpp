// The kidnap measurement (docs/map.md): a simulated figure-8 flight (a lap
// every 11.4 s) whose lens is covered for 2 s while the vehicle moves on, on
// its second lap, then back over ground the first lap mapped. Replayed
// through the whole harness with the map, loop closing and relocalisation on:
// how long after the camera returns is the map localised again?
#pragma once

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>

#include "kestrel/replay_runner.hpp"
#include "kestrel/tools/simulator.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "map_pipeline.hpp"
#include "test_data.hpp"

namespace kestrel::map_test {

struct KidnapTrial {
  uint64_t seed = 0;
  bool lost = false;  // the map said not localised after the cover
  bool relocalised = false;
  double reloc_after_s = NAN;  // from the camera's return to the first relocalised pose
  uint64_t relocalisations = 0;
  double ate_odom_m = NAN, ate_map_m = NAN;  // se3-aligned, whole flight
  std::string summary;
};

constexpr double kKidnapAt_s = 16.0, kKidnapLen_s = 2.0, kKidnapFlight_s = 26.0;

inline KidnapTrial kidnap_trial(uint64_t seed, const std::string& backend = "window") {
  KidnapTrial k;
  k.seed = seed;
  const std::string dir = test::temp_dir("kidnap_" + std::to_string(seed));
  tools::SimOptions so = figure8(kKidnapFlight_s, seed, 320, 240);
  so.cover_at_s = kKidnapAt_s;
  so.cover_s = kKidnapLen_s;
  so.out_path = dir + "/kidnap.klog";
  tools::run_simulation(so);
  cli::ReplayOptions ro;
  ro.path = so.out_path;
  ro.pace = drivers::ReplayPace::kLockstep;
  ro.config = map_config(backend);
  int64_t t0 = -1;
  uint64_t relocs_before = 0;
  ro.on_pose = [&](const core::PoseSample& p) {
    if (t0 < 0) t0 = p.t_ns;
    const double t = 1e-9 * static_cast<double>(p.t_ns - t0);
    if (t < kKidnapAt_s) {
      relocs_before = p.map.relocalisations;
      return;
    }
    if (!p.map.localized) k.lost = true;
    if (!k.relocalised && p.map.relocalisations > relocs_before) {
      k.relocalised = true;
      k.reloc_after_s = t - (kKidnapAt_s + kKidnapLen_s);
    }
  };
  const cli::ReplayReport r = cli::run_replay(ro);
  k.relocalisations = r.map.relocalisations;
  std::vector<std::string> w;
  const tools::Trajectory gt = tools::load_trajectory(so.out_path, &w);
  tools::EvalOptions eo;
  eo.align = tools::Alignment::kSe3;
  k.ate_odom_m = tools::evaluate(gt, r.trajectory, eo).ate_m.rmse;
  k.ate_map_m = tools::evaluate(gt, r.map_trajectory, eo).ate_m.rmse;
  k.summary = r.backend_summary;
  std::printf(
      "KIDNAP %s seed %llu: lost %s, relocalised %s (%.2f s after the camera returned), %llu "
      "relocalisations; se3 ATE odometry %.1f mm, map frame %.1f mm\n",
      backend.c_str(), static_cast<unsigned long long>(seed), k.lost ? "yes" : "no",
      k.relocalised ? "yes" : "no", k.reloc_after_s, static_cast<unsigned long long>(k.relocalisations),
      1e3 * k.ate_odom_m, 1e3 * k.ate_map_m);
  std::filesystem::remove_all(dir);
  return k;
}

}  // namespace kestrel::map_test

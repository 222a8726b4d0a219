// Wall-clock budgets of the KITTI path (label timing, out of the sanitized
// suites): loading paper 003's 0027.npz and 100 steps of the EKF-SLAM filter
// on it, on a release build of a noisy 2-core machine. What the run computes is
// test_npz_reader's to check.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>

#include "kitti_npz_run.hpp"
#include "test_data.hpp"

namespace {

TEST(NpzTiming, RealKitti0027LoadAndHundredStepsWithinBudget) {
  KESTREL_REQUIRE_SHARED("kitti-vislam-features/0027.npz");
  const auto t0 = std::chrono::steady_clock::now();
  const auto seq =
      kestrel::drivers::load_kitti_vislam_npz(kestrel::test::shared_path("kitti-vislam-features/0027.npz"));
  const auto t1 = std::chrono::steady_clock::now();
  const kestrel::test::KittiShortRun run = kestrel::test::run_kitti_100_steps(seq);
  const auto t2 = std::chrono::steady_clock::now();
  const double load_s = std::chrono::duration<double>(t1 - t0).count();
  const double run_s = std::chrono::duration<double>(t2 - t1).count();
  std::printf("[ kitti 0027 ] load %.2f s, 100 steps %.3f s (%d observations used)\n", load_s, run_s,
              run.used);
  EXPECT_LT(load_s, 10.0);
  EXPECT_LT(run_s, 3.0);
}

}  // namespace

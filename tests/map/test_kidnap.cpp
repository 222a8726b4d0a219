// A kidnap (the camera covered 2 s while moving) on a fixed seed: the map
// notices it is lost and relocalises within a second of the camera's return.
// bench_kidnap runs the same over many seeds for the figure in docs/map.md.
#include "kidnap.hpp"

namespace kestrel::map_test {
namespace {

TEST(Kidnap, RelocalisedWithinASecondOfTheCameraReturning) {
  const KidnapTrial k = kidnap_trial(4);
  std::printf("%s\n", k.summary.c_str());
  EXPECT_TRUE(k.lost) << "the cover never made the map say lost: nothing was tested";
  ASSERT_TRUE(k.relocalised);
  EXPECT_LE(k.reloc_after_s, 1.0);
  EXPECT_LT(k.ate_map_m, 0.05);
}

}  // namespace
}  // namespace kestrel::map_test

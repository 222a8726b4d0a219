// libFuzzer target: any byte string as a map file (core/map/map_file.hpp),
// both as it is and sealed as a payload with a fresh header and CRC, so the
// mutations reach the decoder's checks behind the checksum. Built only with
// -DKESTREL_BUILD_FUZZ=ON and clang; the seed corpus is a small real map
// (map_fuzz_seed.cpp).
#include <cstddef>
#include <cstdint>
#include <vector>

#include "kestrel/core/bytes.hpp"
#include "kestrel/core/map_file.hpp"
#include "map_sim.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace kestrel;
  static core::Map* map = [] {
    core::MapOptions o;
    o.max_keyframes = 16;
    o.max_points = 4096;
    return new core::Map(o, 300);  // no vocabulary: any file's checksum is accepted, the rest is checked
  }();
  const core::MapCamera cam = map_test::sim_camera();
  for (int sealed = 0; sealed < 2; ++sealed) {
    std::vector<uint8_t> bytes = sealed ? core::seal(core::kMapMagic, core::kMapVersion,
                                                     std::vector<uint8_t>(data, data + size))
                                        : std::vector<uint8_t>(data, data + size);
    // The map must be empty for each input: a fresh one costs a few MB, so
    // erase what a successful decode left.
    map->for_each_keyframe([&](int k) { map->erase_keyframe(k); });
    (void)core::decode_map(bytes.data(), bytes.size(), cam, map);
  }
  return 0;
}

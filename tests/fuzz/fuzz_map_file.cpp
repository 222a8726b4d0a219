// The map file (`--map-in`, core/map/map_file.hpp): any bytes as a map file,
// both as they are and sealed as a payload with a fresh header and CRC, so
// the mutations reach the decoder's checks behind the checksum. A decode must
// refuse with a reason or fill the map, never crash. Seeds: the whole file
// and the payload of a small map built as the map tests build theirs.
#include <random>

#include "fuzz_target.hpp"
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
    std::vector<uint8_t> bytes =
        sealed ? core::seal(core::kMapMagic, core::kMapVersion, std::vector<uint8_t>(data, data + size))
               : std::vector<uint8_t>(data, data + size);
    // The map must be empty for each input: a fresh one costs a few MB, so
    // erase what a successful decode left.
    map->for_each_keyframe([&](int k) { map->erase_keyframe(k); });
    (void)core::decode_map(bytes.data(), bytes.size(), cam, map);
  }
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  using namespace kestrel;
  map_test::SimRoom room(600, 3);
  map_test::DriftedMap dm(nullptr);
  std::mt19937_64 rng(1);
  for (int k = 0; k < 3; ++k) {
    const Eigen::Isometry3d T = map_test::SimRoom::camera(Eigen::Vector3d(0.1 * k, 0, 1.5), 0.4 * k);
    dm.add(room, T, T, k * 100'000'000, 1, rng);
  }
  const std::vector<uint8_t> file = core::encode_map(dm.map, map_test::sim_camera());
  write_file(dir + "/map.kmap", file.data(), file.size());
  write_file(dir + "/payload.bin", file.data() + 16, file.size() - 20);  // header: 16 bytes, CRC: 4
  return 2;
}

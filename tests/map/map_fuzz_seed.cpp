// Writes the seed corpus for fuzz_map_decoder: the payload of a small real
// map (the fuzzer seals each input itself) and the whole file.
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>

#include "kestrel/core/map_file.hpp"
#include "map_sim.hpp"

int main(int argc, char** argv) {
  using namespace kestrel;
  if (argc != 2) {
    std::fprintf(stderr, "usage: %s CORPUS_DIR\n", argv[0]);
    return 2;
  }
  map_test::SimRoom room(600, 3);
  map_test::DriftedMap dm(nullptr);
  std::mt19937_64 rng(1);
  for (int k = 0; k < 3; ++k) {
    const Eigen::Isometry3d T = map_test::SimRoom::camera(Eigen::Vector3d(0.1 * k, 0, 1.5), 0.4 * k);
    dm.add(room, T, T, k * 100'000'000, 1, rng);
  }
  const std::vector<uint8_t> file = core::encode_map(dm.map, map_test::sim_camera());
  const std::string dir = argv[1];
  auto write = [](const std::string& path, const uint8_t* p, size_t n) {
    std::FILE* f = std::fopen(path.c_str(), "wb");
    if (f == nullptr || std::fwrite(p, 1, n, f) != n) {
      std::fprintf(stderr, "cannot write %s\n", path.c_str());
      std::exit(1);
    }
    std::fclose(f);
  };
  write(dir + "/map.kmap", file.data(), file.size());
  write(dir + "/payload.bin", file.data() + 16, file.size() - 20);  // header: 16 bytes, CRC: 4
  return 0;
}

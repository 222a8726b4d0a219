#include "kestrel/dense/dense_files.hpp"

#include <octomap/OcTree.h>

#include <cstdio>
#include <cstring>
#include <stdexcept>

namespace kestrel::dense {

void write_ply(const std::string& path, const std::vector<core::SurfacePoint>& points) {
  std::FILE* f = std::fopen(path.c_str(), "wb");
  if (f == nullptr) throw std::runtime_error("dense map: cannot write " + path);
  std::fprintf(
      f,
      "ply\nformat binary_little_endian 1.0\ncomment kestrel dense map: TSDF zero crossings, frame W "
      "(the trajectory's)\nelement vertex %zu\nproperty float x\nproperty float y\nproperty float z\n"
      "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
      points.size());
  bool ok = true;
  for (const core::SurfacePoint& p : points) {
    unsigned char rec[15];
    static_assert(sizeof(float) == 4, "PLY float is 4 bytes");
    std::memcpy(rec, p.p.data(), 12);  // x86 and aarch64 are little endian, as the header says
    std::memcpy(rec + 12, p.rgb, 3);
    ok = ok && std::fwrite(rec, sizeof rec, 1, f) == 1;
  }
  ok = std::fclose(f) == 0 && ok;
  if (!ok) throw std::runtime_error("dense map: write error on " + path);
}

std::size_t write_octomap_bt(const std::string& path, const core::TsdfMap& map) {
  octomap::OcTree tree(map.options().voxel_size_m);
  std::vector<Eigen::Vector3f> occupied, free;
  map.occupied_voxels(occupied);
  map.free_voxels(free);
  for (const Eigen::Vector3f& p : free) tree.updateNode(octomap::point3d(p.x(), p.y(), p.z()), false, true);
  for (const Eigen::Vector3f& p : occupied)
    tree.updateNode(octomap::point3d(p.x(), p.y(), p.z()), true, true);
  tree.updateInnerOccupancy();
  if (!tree.writeBinary(path)) throw std::runtime_error("dense map: cannot write " + path);
  return occupied.size() + free.size();
}

}  // namespace kestrel::dense

// The dense map's files: the surface as a PLY point cloud (binary little
// endian, vertex x y z as float with red green blue), occupancy as an OctoMap
// .bt (liboctomap's binary tree, what planners read). docs/dense.md.
#pragma once

#include <string>
#include <vector>

#include "kestrel/core/tsdf_map.hpp"

namespace kestrel::dense {

// Throws std::runtime_error naming the file when it cannot be written.
void write_ply(const std::string& path, const std::vector<core::SurfacePoint>& points);
// Occupied and free voxels as leaves at the map's voxel size (the OctoMap
// resolution); unknown space stays unknown. Returns the number of leaves.
std::size_t write_octomap_bt(const std::string& path, const core::TsdfMap& map);

}  // namespace kestrel::dense

#include "kestrel/core/tsdf_map.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <stdexcept>

namespace kestrel::core {

namespace {
void require(bool ok, const char* what) {
  if (!ok) throw std::invalid_argument(std::string("dense.") + what);
}

uint16_t depth_at(const ImageView& d, int u, int v) {
  uint16_t z;
  std::memcpy(&z, d.data + static_cast<std::ptrdiff_t>(v) * d.stride_bytes + 2 * u, 2);
  return z;
}
}  // namespace

void TsdfOptions::validate() const {
  require(std::isfinite(voxel_size_m) && voxel_size_m >= 0.005 && voxel_size_m <= 1.0,
          "voxel_size_m must be in [0.005, 1] m");
  require(std::isfinite(memory_budget_mb) && memory_budget_mb >= 1 && memory_budget_mb <= 65536,
          "memory_budget_mb must be in [1, 65536] MB");
  require(std::isfinite(truncation_voxels) && truncation_voxels >= 1 && truncation_voxels <= 16,
          "truncation_voxels must be in [1, 16]");
  require(std::isfinite(max_depth_m) && max_depth_m > 0, "max_depth_m must be > 0 m");
  require(pixel_stride >= 1 && pixel_stride <= 64, "pixel_stride must be in [1, 64]");
  require(carve_stride >= 1 && carve_stride <= 256, "carve_stride must be in [1, 256]");
  require(std::isfinite(weight_reference_depth_m) && weight_reference_depth_m > 0,
          "weight_reference_depth_m must be > 0 m");
  require(std::isfinite(max_weight) && max_weight > 0, "max_weight must be > 0");
  require(std::isfinite(min_weight) && min_weight >= 0 && min_weight < max_weight,
          "min_weight must be in [0, max_weight)");
  require(std::isfinite(evict_distance_m) && evict_distance_m > 0, "evict_distance_m must be > 0 m");
}

const char* to_string(Occupancy o) {
  switch (o) {
    case Occupancy::kFree:
      return "free";
    case Occupancy::kOccupied:
      return "occupied";
    case Occupancy::kUnknown:
      break;
  }
  return "unknown";
}

TsdfMap::TsdfMap(const TsdfOptions& opt) : opt_(opt) {
  opt_.validate();
  block_size_m_ = opt_.voxel_size_m * kBlockSide;
  trunc_m_ = opt_.truncation_voxels * opt_.voxel_size_m;
  // Per block: its voxels, its record, two hash slots, the view list and stamp.
  const double per_block =
      sizeof(Voxel) * kBlockVoxels + sizeof(Block) + 2 * sizeof(int32_t) + 3 * sizeof(int32_t);
  capacity_ = static_cast<int>(std::min(opt_.memory_budget_mb * 1048576.0 / per_block, 1.0e8));
  if (capacity_ < 1) throw std::invalid_argument("dense.memory_budget_mb too small for one voxel block");
  uint32_t table = 1;
  while (table < 2u * static_cast<uint32_t>(capacity_)) table <<= 1;
  table_mask_ = table - 1;
  table_.assign(table, -1);
  blocks_.assign(static_cast<std::size_t>(capacity_), Block{});
  voxels_.assign(static_cast<std::size_t>(capacity_) * kBlockVoxels, Voxel{});
  free_list_.reserve(static_cast<std::size_t>(capacity_));
  for (int i = capacity_ - 1; i >= 0; --i) free_list_.push_back(i);
  in_view_.reserve(static_cast<std::size_t>(capacity_));
  view_stamp_.assign(static_cast<std::size_t>(capacity_), 0);
}

std::size_t TsdfMap::memory_bytes() const {
  return voxels_.capacity() * sizeof(Voxel) + blocks_.capacity() * sizeof(Block) +
         table_.capacity() * sizeof(int32_t) + free_list_.capacity() * sizeof(int32_t) +
         in_view_.capacity() * sizeof(int32_t) + view_stamp_.capacity() * sizeof(uint32_t);
}

void TsdfMap::clear() {
  std::fill(table_.begin(), table_.end(), -1);
  std::fill(blocks_.begin(), blocks_.end(), Block{});
  std::fill(voxels_.begin(), voxels_.end(), Voxel{});
  std::fill(view_stamp_.begin(), view_stamp_.end(), 0u);
  free_list_.clear();
  for (int i = capacity_ - 1; i >= 0; --i) free_list_.push_back(i);
  in_view_.clear();
  in_use_ = 0;
  counters_ = TsdfCounters{};
}

uint32_t TsdfMap::slot_of(const Eigen::Vector3i& k) const {
  // The spatial hash of Teschner et al. (2003): three large primes, XOR.
  const uint32_t h = (static_cast<uint32_t>(k.x()) * 73856093u) ^ (static_cast<uint32_t>(k.y()) * 19349663u) ^
                     (static_cast<uint32_t>(k.z()) * 83492791u);
  return h & table_mask_;
}

Eigen::Vector3i TsdfMap::block_key(const Eigen::Vector3d& p) const {
  return Eigen::Vector3i(static_cast<int>(std::floor(p.x() / block_size_m_)),
                         static_cast<int>(std::floor(p.y() / block_size_m_)),
                         static_cast<int>(std::floor(p.z() / block_size_m_)));
}

int TsdfMap::find(const Eigen::Vector3i& key) const {
  for (uint32_t s = slot_of(key);; s = (s + 1) & table_mask_) {
    const int32_t b = table_[s];
    if (b < 0) return -1;
    if (blocks_[static_cast<std::size_t>(b)].key == key) return b;
  }
}

void TsdfMap::erase(int block) {
  const Eigen::Vector3i key = blocks_[static_cast<std::size_t>(block)].key;
  uint32_t i = slot_of(key);
  while (table_[i] != block) i = (i + 1) & table_mask_;
  // Backward-shift deletion keeps every probe chain unbroken without tombstones.
  table_[i] = -1;
  for (uint32_t j = (i + 1) & table_mask_; table_[j] >= 0; j = (j + 1) & table_mask_) {
    const uint32_t home = slot_of(blocks_[static_cast<std::size_t>(table_[j])].key);
    const bool home_in_gap = i <= j ? (home > i && home <= j) : (home > i || home <= j);
    if (home_in_gap) continue;
    table_[i] = table_[j];
    table_[j] = -1;
    i = j;
  }
  blocks_[static_cast<std::size_t>(block)].used = false;
  Voxel* v = &voxels_[static_cast<std::size_t>(block) * kBlockVoxels];
  std::fill(v, v + kBlockVoxels, Voxel{});
  free_list_.push_back(block);
  --in_use_;
}

bool TsdfMap::evict_one_far(const Eigen::Vector3d& cam_M) {
  // One sweep evicts every block beyond the distance, so a full pool costs
  // one scan per frame, not one per block wanted.
  const double d2 = opt_.evict_distance_m * opt_.evict_distance_m;
  bool any = false;
  for (int b = 0; b < capacity_; ++b) {
    const Block& blk = blocks_[static_cast<std::size_t>(b)];
    if (!blk.used || view_stamp_[static_cast<std::size_t>(b)] == static_cast<uint32_t>(counters_.frames))
      continue;
    const Eigen::Vector3d c = (blk.key.cast<double>() + Eigen::Vector3d::Constant(0.5)) * block_size_m_;
    if ((c - cam_M).squaredNorm() > d2) {
      erase(b);
      ++counters_.blocks_evicted;
      any = true;
    }
  }
  return any;
}

int TsdfMap::find_or_allocate(const Eigen::Vector3i& key, const Eigen::Vector3d& cam_M) {
  int b = find(key);
  if (b < 0) {
    if (free_list_.empty() && evicted_in_frame_ != counters_.frames) {
      evicted_in_frame_ = counters_.frames;
      evict_one_far(cam_M);
    }
    if (free_list_.empty()) {
      ++counters_.blocks_refused;
      return -1;
    }
    b = free_list_.back();
    free_list_.pop_back();
    Block& blk = blocks_[static_cast<std::size_t>(b)];
    blk.key = key;
    blk.used = true;
    uint32_t s = slot_of(key);
    while (table_[s] >= 0) s = (s + 1) & table_mask_;
    table_[s] = b;
    ++in_use_;
    ++counters_.blocks_allocated;
  }
  const auto stamp = static_cast<uint32_t>(counters_.frames);
  if (view_stamp_[static_cast<std::size_t>(b)] != stamp) {
    view_stamp_[static_cast<std::size_t>(b)] = stamp;
    blocks_[static_cast<std::size_t>(b)].last_seen = stamp;
    in_view_.push_back(b);
  }
  return b;
}

void TsdfMap::integrate(const ImageView& depth, const ImageView& rgb, const CameraIntrinsics& cam,
                        const DepthModel& dm, const Eigen::Isometry3d& T_MC) {
  fuse<false>(depth, rgb, cam, dm, T_MC);
}

void TsdfMap::deintegrate(const ImageView& depth, const ImageView& rgb, const CameraIntrinsics& cam,
                          const DepthModel& dm, const Eigen::Isometry3d& T_MC) {
  fuse<true>(depth, rgb, cam, dm, T_MC);
}

int TsdfMap::list_existing(const Eigen::Vector3i& key) {
  const int b = find(key);
  if (b < 0) return -1;
  const auto stamp = static_cast<uint32_t>(counters_.frames);
  if (view_stamp_[static_cast<std::size_t>(b)] != stamp) {
    view_stamp_[static_cast<std::size_t>(b)] = stamp;
    blocks_[static_cast<std::size_t>(b)].last_seen = stamp;
    in_view_.push_back(b);
  }
  return b;
}

template <bool kRemove>
void TsdfMap::fuse(const ImageView& depth, const ImageView& rgb, const CameraIntrinsics& cam,
                   const DepthModel& dm, const Eigen::Isometry3d& T_MC) {
  // kRemove lists only the blocks that exist (what was fused is in them, unless
  // evicted since) and subtracts each observation's weighted share again.
  auto list = [&](const Eigen::Vector3i& key, const Eigen::Vector3d& cam_M) {
    if constexpr (kRemove) {
      (void)cam_M;
      list_existing(key);
    } else {
      find_or_allocate(key, cam_M);
    }
  };
  if (depth.data == nullptr || depth.format != PixelFormat::kDepthU16 || depth.width != cam.width ||
      depth.height != cam.height)
    return;
  ++counters_.frames;
  in_view_.clear();
  const bool colour = rgb.data != nullptr && rgb.width == depth.width && rgb.height == depth.height &&
                      (rgb.format == PixelFormat::kRgb8 || rgb.format == PixelFormat::kBgr8);
  const Eigen::Vector3d cam_M = T_MC.translation();
  const double max_z = std::min(opt_.max_depth_m, dm.max_range_m);
  const double min_z = dm.min_range_m;

  // 1. The blocks this frame can say something about: the band around each
  // surface point, and (on a sparser grid) the blocks its ray crosses.
  for (int v = 0; v < depth.height; v += opt_.pixel_stride) {
    for (int u = 0; u < depth.width; u += opt_.pixel_stride) {
      const double z = dm.scale_m_per_unit * depth_at(depth, u, v);
      if (!(z >= min_z && z <= max_z)) {
        ++counters_.pixels_invalid;
        continue;
      }
      const Eigen::Vector3d ray_C((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0);
      const Eigen::Vector3d ray_M = T_MC.linear() * ray_C;
      const double band_z = trunc_m_ / ray_C.norm();
      // The band is at most 2 * truncation long; blocks are >= 2.7 truncations:
      // its ends and middle reach every block it touches.
      for (double s : {z - band_z, z, z + band_z}) list(block_key(cam_M + ray_M * s), cam_M);
      if (u % opt_.carve_stride == 0 && v % opt_.carve_stride == 0) {
        const double step_z = 0.5 * block_size_m_ / ray_C.norm();
        for (double s = min_z; s < z - band_z; s += step_z) list(block_key(cam_M + ray_M * s), cam_M);
      }
    }
  }

  // 2. Projective update of every voxel of those blocks: signed distance
  // along the optical axis, truncated, weighted by the depth's variance.
  const Eigen::Isometry3d T_CM = T_MC.inverse();
  const Eigen::Matrix3f R = T_CM.linear().cast<float>();
  const Eigen::Vector3f t = T_CM.translation().cast<float>();
  const auto trunc = static_cast<float>(trunc_m_);
  const auto vox = static_cast<float>(opt_.voxel_size_m);
  const double sigma_ref =
      dm.sigma_coeff_per_m * opt_.weight_reference_depth_m * opt_.weight_reference_depth_m;
  const auto max_w = static_cast<float>(opt_.max_weight);
  const bool bgr = rgb.format == PixelFormat::kBgr8;
  for (int b : in_view_) {
    const Eigen::Vector3f origin = (blocks_[static_cast<std::size_t>(b)].key.cast<float>() * kBlockSide +
                                    Eigen::Vector3f::Constant(0.5f)) *
                                   vox;
    Voxel* vx = &voxels_[static_cast<std::size_t>(b) * kBlockVoxels];
    for (int i = 0; i < kBlockVoxels; ++i) {
      // The voxel index split into its three coordinates (integer division on purpose).
      const int row = i / kBlockSide, layer = i / (kBlockSide * kBlockSide);
      const Eigen::Vector3f p_M =
          origin + vox * Eigen::Vector3f(static_cast<float>(i % kBlockSide),
                                         static_cast<float>(row % kBlockSide), static_cast<float>(layer));
      const Eigen::Vector3f p_C = R * p_M + t;
      if (p_C.z() < static_cast<float>(min_z)) continue;
      const int u = static_cast<int>(std::lround(cam.fx * p_C.x() / p_C.z() + cam.cx));
      const int v = static_cast<int>(std::lround(cam.fy * p_C.y() / p_C.z() + cam.cy));
      if (u < 0 || v < 0 || u >= depth.width || v >= depth.height) continue;
      const double z = dm.scale_m_per_unit * depth_at(depth, u, v);
      if (!(z >= min_z && z <= max_z)) continue;
      float sdf = static_cast<float>(z) - p_C.z();
      if (sdf < -trunc) continue;  // hidden behind the surface: nothing known
      sdf = std::min(sdf, trunc);
      const double sigma = dm.sigma_coeff_per_m * z * z;
      const auto w =
          static_cast<float>(sigma_ref > 0 && sigma > 0 ? (sigma_ref * sigma_ref) / (sigma * sigma) : 1.0);
      Voxel& x = vx[i];
      if constexpr (kRemove) {
        // The exact inverse of the update below while the weight did not
        // saturate; a voxel left with (almost) nothing is unknown again.
        const float W = x.weight - w;
        if (W <= 1e-3f) {
          x = Voxel{};
        } else {
          x.sdf_m = std::clamp((x.sdf_m * x.weight - sdf * w) / W, -trunc, trunc);
          if (colour && std::fabs(sdf) < vox) {
            const uint8_t* px = rgb.data + static_cast<std::ptrdiff_t>(v) * rgb.stride_bytes + 3 * u;
            for (int c = 0; c < 3; ++c) {
              const float in = px[bgr ? 2 - c : c];
              x.rgb[c] =
                  static_cast<uint8_t>(std::clamp(std::lround((x.rgb[c] * x.weight - in * w) / W), 0L, 255L));
            }
          }
          x.weight = W;
        }
        ++counters_.voxels_updated;
        continue;
      }
      const float W = x.weight + w;
      x.sdf_m = (x.sdf_m * x.weight + sdf * w) / W;
      if (colour && std::fabs(sdf) < vox) {
        const uint8_t* px = rgb.data + static_cast<std::ptrdiff_t>(v) * rgb.stride_bytes + 3 * u;
        for (int c = 0; c < 3; ++c) {
          const float in = px[bgr ? 2 - c : c];
          x.rgb[c] = static_cast<uint8_t>(std::lround((x.rgb[c] * x.weight + in * w) / W));
        }
      }
      x.weight = std::min(W, max_w);
      ++counters_.voxels_updated;
    }
  }
}

const TsdfMap::Voxel* TsdfMap::voxel_at(const Eigen::Vector3d& p) const {
  const Eigen::Vector3i key = block_key(p);
  const int b = find(key);
  if (b < 0) return nullptr;
  const Eigen::Vector3d local = p / opt_.voxel_size_m - key.cast<double>() * kBlockSide;
  const int x = std::clamp(static_cast<int>(std::floor(local.x())), 0, kBlockSide - 1);
  const int y = std::clamp(static_cast<int>(std::floor(local.y())), 0, kBlockSide - 1);
  const int z = std::clamp(static_cast<int>(std::floor(local.z())), 0, kBlockSide - 1);
  return &voxels_[static_cast<std::size_t>(b) * kBlockVoxels + x + kBlockSide * (y + kBlockSide * z)];
}

Occupancy TsdfMap::classify(const Voxel& v) const {
  if (v.weight < opt_.min_weight) return Occupancy::kUnknown;
  // Occupied: the surface passes within this voxel's cell, or the voxel is
  // inside the band behind it.
  return v.sdf_m < 0.5f * static_cast<float>(opt_.voxel_size_m) ? Occupancy::kOccupied : Occupancy::kFree;
}

Occupancy TsdfMap::occupancy(const Eigen::Vector3d& p_M) const {
  if (!p_M.allFinite()) return Occupancy::kUnknown;
  const Voxel* v = voxel_at(p_M);
  return v == nullptr ? Occupancy::kUnknown : classify(*v);
}

bool TsdfMap::distance(const Eigen::Vector3d& p_M, float& sdf_m) const {
  if (!p_M.allFinite()) return false;
  const Voxel* v = voxel_at(p_M);
  if (v == nullptr || v->weight < opt_.min_weight) return false;
  sdf_m = v->sdf_m;
  return true;
}

Occupancy TsdfMap::segment(const Eigen::Vector3d& a, const Eigen::Vector3d& b) const {
  if (!a.allFinite() || !b.allFinite()) return Occupancy::kUnknown;
  const double len = (b - a).norm();
  const int n = 1 + static_cast<int>(std::ceil(len / (0.5 * opt_.voxel_size_m)));
  bool unknown = false;
  for (int i = 0; i <= n; ++i) {
    const Occupancy o = occupancy(a + (b - a) * (static_cast<double>(i) / n));
    if (o == Occupancy::kOccupied) return o;
    if (o == Occupancy::kUnknown) unknown = true;
  }
  return unknown ? Occupancy::kUnknown : Occupancy::kFree;
}

Eigen::Vector3f TsdfMap::voxel_centre(int b, int i) const {
  const Eigen::Vector3i k =
      blocks_[static_cast<std::size_t>(b)].key * kBlockSide +
      Eigen::Vector3i(i % kBlockSide, (i / kBlockSide) % kBlockSide, i / (kBlockSide * kBlockSide));
  return (k.cast<float>() + Eigen::Vector3f::Constant(0.5f)) * static_cast<float>(opt_.voxel_size_m);
}

template <class Emit>
void TsdfMap::block_surface(int b, Emit&& emit) const {
  const auto vox = static_cast<float>(opt_.voxel_size_m);
  const auto min_w = static_cast<float>(opt_.min_weight);
  const Voxel* vx = &voxels_[static_cast<std::size_t>(b) * kBlockVoxels];
  for (int i = 0; i < kBlockVoxels; ++i) {
    const Voxel& a = vx[i];
    if (a.weight < min_w) continue;
    const Eigen::Vector3f pa = voxel_centre(b, i);
    for (int axis = 0; axis < 3; ++axis) {
      Eigen::Vector3f pb = pa;
      pb[axis] += vox;
      const Voxel* nb = voxel_at(pb.cast<double>());
      if (nb == nullptr || nb->weight < min_w) continue;
      // A sign change between two voxels that both saw the surface (not the
      // +truncation/-truncation jump at the band's edge behind an object).
      if ((a.sdf_m > 0) == (nb->sdf_m > 0)) continue;
      if (std::fabs(a.sdf_m - nb->sdf_m) > 2.0f * vox) continue;
      const float f = a.sdf_m / (a.sdf_m - nb->sdf_m);
      SurfacePoint s;
      s.p = pa + f * (pb - pa);
      const Voxel& c = std::fabs(a.sdf_m) <= std::fabs(nb->sdf_m) ? a : *nb;
      std::memcpy(s.rgb, c.rgb, 3);
      if (!emit(s)) return;
    }
  }
}

void TsdfMap::extract_surface(std::vector<SurfacePoint>& out) const {
  for (int b = 0; b < capacity_; ++b) {
    if (blocks_[static_cast<std::size_t>(b)].used) {
      block_surface(b, [&](const SurfacePoint& s) {
        out.push_back(s);
        return true;
      });
    }
  }
}

int TsdfMap::extract_block_surface(int b, SurfacePoint* out, int max) const {
  int n = 0;
  if (b < 0 || b >= capacity_ || !blocks_[static_cast<std::size_t>(b)].used) return 0;
  block_surface(b, [&](const SurfacePoint& s) {
    if (n >= max) return false;
    out[n++] = s;
    return true;
  });
  return n;
}

void TsdfMap::occupied_voxels(std::vector<Eigen::Vector3f>& out) const {
  for (int b = 0; b < capacity_; ++b) {
    if (!blocks_[static_cast<std::size_t>(b)].used) continue;
    const Voxel* vx = &voxels_[static_cast<std::size_t>(b) * kBlockVoxels];
    for (int i = 0; i < kBlockVoxels; ++i)
      if (classify(vx[i]) == Occupancy::kOccupied) out.push_back(voxel_centre(b, i));
  }
}

void TsdfMap::free_voxels(std::vector<Eigen::Vector3f>& out) const {
  for (int b = 0; b < capacity_; ++b) {
    if (!blocks_[static_cast<std::size_t>(b)].used) continue;
    const Voxel* vx = &voxels_[static_cast<std::size_t>(b) * kBlockVoxels];
    for (int i = 0; i < kBlockVoxels; ++i)
      if (classify(vx[i]) == Occupancy::kFree) out.push_back(voxel_centre(b, i));
  }
}

}  // namespace kestrel::core

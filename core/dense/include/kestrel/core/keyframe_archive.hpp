// The dense keyframes' depth and colour, kept (downsampled) in fixed memory so
// the map can be fused again along poses that a bundle adjustment or a loop
// closure corrected (issue 44 item 2): a TSDF fused along the odometry keeps
// every surface where the drift put it; re-integrating the archive along the
// map's keyframe poses moves the surfaces with the estimate. A ring sized once
// from a memory budget: when it is full the oldest keyframe is overwritten and
// counted, and a re-integration no longer has it. Pure computation: no
// threads, no I/O (docs/dense.md, "Consistency with loops").
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <vector>

#include "kestrel/core/tsdf_map.hpp"
#include "kestrel/msgs.hpp"

namespace kestrel::core {

struct KeyframeArchiveOptions {
  // Memory for the archived images, allocated at construction [MiB]; 0 = no archive.
  double budget_mb = 64.0;
  // Every n-th pixel in u and v is kept (the point, not an average: averaging
  // depth across an edge invents surfaces between foreground and background).
  int stride_px = 2;
  void validate() const;  // throws std::invalid_argument naming the key (dense.archive_...)
};

struct KeyframeArchiveCounters {
  uint64_t stored = 0;
  uint64_t overwritten = 0;  // the ring was full: the oldest keyframe is lost to a re-integration
};

// What a re-integration did.
struct ReintegrationReport {
  int fused = 0;       // keyframes fused along a corrected pose
  int no_pose = 0;     // keyframes the pose source had nothing for: left out, counted
  int64_t cpu_ns = 0;  // wall time of the fusion on the calling thread
};

class KeyframeArchive {
 public:
  // Full-resolution camera (the rig's, depth registered to it). Allocates the
  // ring: capacity = budget / (w/stride * h/stride * 5 bytes).
  KeyframeArchive(const KeyframeArchiveOptions& opt, const CameraIntrinsics& cam);

  // Keeps a keyframe (depth u16 in the rig's units, colour RGB8 or data ==
  // nullptr) fused at T_WC. Images must be of the camera's size (false
  // otherwise, nothing kept). Allocation-free.
  bool store(int64_t t_ns, const Eigen::Isometry3d& T_WC, const ImageView& depth, const ImageView& rgb);

  int capacity() const { return capacity_; }
  int size() const { return size_; }
  // i = 0 is the oldest kept.
  int64_t t_ns(int i) const { return entries_[index(i)].t_ns; }
  const Eigen::Isometry3d& T_WC(int i) const { return entries_[index(i)].T_WC; }
  ImageView depth(int i) const;
  ImageView rgb(int i) const;  // data == nullptr when the keyframe had no colour
  // The intrinsics of the archived images (the rig's scaled by 1/stride).
  const CameraIntrinsics& camera() const { return cam_small_; }
  const KeyframeArchiveCounters& counters() const { return counters_; }
  std::size_t memory_bytes() const { return depth_.size() * sizeof(uint16_t) + rgb_.size(); }
  void clear();

 private:
  struct Entry {
    int64_t t_ns = 0;
    Eigen::Isometry3d T_WC = Eigen::Isometry3d::Identity();
    bool has_rgb = false;
    PixelFormat rgb_format = PixelFormat::kRgb8;  // RGB or BGR, as it came
  };
  int index(int i) const { return (head_ + i) % capacity_; }

  KeyframeArchiveOptions opt_;
  CameraIntrinsics cam_full_, cam_small_;
  int capacity_ = 0;
  int head_ = 0;  // oldest
  int size_ = 0;
  std::vector<Entry> entries_;
  std::vector<uint16_t> depth_;  // capacity_ * w * h
  std::vector<uint8_t> rgb_;     // capacity_ * w * h * 3
  KeyframeArchiveCounters counters_;
};

// Clears `map` and fuses every archived keyframe along the camera pose
// `T_MC_of(t_ns, T_WC_fused, T_MC)` gives (false: no pose, the keyframe is
// left out and counted). Not for the real-time threads (the map's own
// integrate is allocation-free, the callback decides for itself).
ReintegrationReport reintegrate(
    const KeyframeArchive& archive, const DepthModel& depth_model, TsdfMap& map,
    const std::function<bool(int64_t t_ns, const Eigen::Isometry3d& T_WC, Eigen::Isometry3d& T_MC)>& T_MC_of);

}  // namespace kestrel::core

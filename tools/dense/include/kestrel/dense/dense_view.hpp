// The dense map for the live viewer (issue 44 item 3): the surface as points,
// block by block, sending only the blocks that changed since they were last
// sent, under a bandwidth cap. Runs on kst-dense (which owns the map), so the
// map is never read while it is written; the viewer thread only forwards the
// finished messages. A block that does not fit this round stays dirty and goes
// in a later one (newest state only, nothing queued twice). docs/dense.md.
//
// Message (little-endian): u8 type = 6, 3 bytes 0, u32 record count, f32
// block size [m], f32 quantisation range [m]; then per block: i32 x, y, z (the
// block's integer coordinates), u16 n, and n points of 6 bytes: u8 qx, qy, qz,
// r, g, b, position = (key + q / 255 * range / block size) * block size.
// n = 0: the block is gone (evicted, or has no surface any more).
#pragma once

#include <Eigen/Core>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "kestrel/core/tsdf_map.hpp"

namespace kestrel::dense {

inline constexpr uint8_t kDenseViewMessageType = 6;
inline constexpr std::size_t kDenseViewHeaderBytes = 16;
inline constexpr std::size_t kDenseViewRecordBytes = 14;
inline constexpr std::size_t kDenseViewPointBytes = 6;
// A block's surface has at most 3 crossings per voxel.
inline constexpr int kDenseViewMaxBlockPoints = 3 * core::TsdfMap::kBlockVoxels;
// The smallest message that holds any one block.
inline constexpr std::size_t kDenseViewMinMessageBytes =
    kDenseViewHeaderBytes + kDenseViewRecordBytes + kDenseViewPointBytes * kDenseViewMaxBlockPoints;

// The stream's settings (the config's `viewer:` section, docs/dense.md).
struct DenseViewOptions {
  double max_kbps = 2000;  // viewer.dense_max_kbps [kbit/s]
  // viewer.dense_period_s [s]: rounds start at most this often, so a block
  // several keyframes touched in between is extracted and sent once.
  double period_s = 0.5;
  void validate() const;  // throws std::invalid_argument naming the key
};

// A token bucket in bytes: refilled at max_kbps, holding at most burst_s of it.
class ByteBudget {
 public:
  ByteBudget(double max_kbps, double burst_s);
  // Bytes that may go now (refilled to now_ns).
  std::size_t available(int64_t now_ns);
  void spend(std::size_t bytes);

 private:
  double bytes_per_ns_;
  double cap_bytes_;
  double tokens_;
  int64_t last_ns_ = -1;
};

struct DenseViewCounters {
  uint64_t messages = 0;
  uint64_t bytes = 0;
  uint64_t blocks_sent = 0;
  uint64_t blocks_removed = 0;  // n = 0 records
  uint64_t points_sent = 0;
  uint64_t rounds_full = 0;  // a round stopped at the byte limit: some changed blocks wait
};

class DenseViewEncoder {
 public:
  // Per-slot state for every block the map can hold: allocated here, once.
  explicit DenseViewEncoder(const core::TsdfMap& map);

  // Any thread: the next round sends every block again (a browser connected).
  void request_all() noexcept { resend_all_.store(true, std::memory_order_relaxed); }
  // The map's thread: writes the changed blocks into out[0, max_bytes)
  // (max_bytes >= kDenseViewMinMessageBytes, else nothing), from where the
  // previous round stopped; returns the message size, 0 when nothing changed.
  // Allocation-free.
  std::size_t encode(uint8_t* out, std::size_t max_bytes);
  // The map was cleared (TsdfMap::clear restarts its frame stamps) and maybe
  // re-fused: the next rounds send every block again and remove the ones gone.
  void reset();
  const DenseViewCounters& counters() const { return counters_; }

 private:
  struct Sent {
    Eigen::Vector3i key = Eigen::Vector3i::Zero();
    uint32_t stamp = 0;
    bool sent = false;
  };
  const core::TsdfMap& map_;
  std::vector<Sent> sent_;
  std::vector<core::SurfacePoint> scratch_;
  int cursor_ = 0;
  std::atomic<bool> resend_all_{false};
  DenseViewCounters counters_;
};

// Where kst-dense puts finished messages (the viewer's BinaryStream, adapted
// by the pipeline, so this library does not depend on the viewer's). Called
// on kst-dense only; implementations must not block.
class DenseViewSink {
 public:
  virtual ~DenseViewSink() = default;
  virtual bool wanted() = 0;               // a browser is connected
  virtual bool take_resend_request() = 0;  // true once after a browser asked for everything
  // A free buffer (nullptr: none, try later); stays the caller's until publish().
  virtual uint8_t* acquire(std::size_t* capacity) = 0;
  virtual void publish(std::size_t bytes) = 0;
};

// One decoded block (tests, tools): points in the map's frame.
struct DenseViewBlock {
  Eigen::Vector3i key = Eigen::Vector3i::Zero();
  std::vector<core::SurfacePoint> points;  // empty: the block is gone
};
// Throws std::runtime_error naming the byte offset of a malformed message.
std::vector<DenseViewBlock> decode_dense_view(const uint8_t* data, std::size_t size);

}  // namespace kestrel::dense

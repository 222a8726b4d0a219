#include "kestrel/dense/dense_view.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <stdexcept>
#include <string>

namespace kestrel::dense {

namespace {
// Points reach past their block by up to one voxel (a crossing towards the
// next block's voxel): the range is the block plus a quarter.
constexpr double kRangeBlocks = 1.25;

void put(uint8_t* p, const void* v, std::size_t n) { std::memcpy(p, v, n); }
}  // namespace

void DenseViewOptions::validate() const {
  // One message must fit the one-second burst: the largest block is ~9 kB.
  if (!(max_kbps >= 100 && max_kbps <= 1e6))
    throw std::invalid_argument("viewer.dense_max_kbps must be in [100, 1000000] kbit/s");
  if (!(period_s >= 0 && period_s <= 10))
    throw std::invalid_argument("viewer.dense_period_s must be in [0, 10] s");
}

ByteBudget::ByteBudget(double max_kbps, double burst_s)
    : bytes_per_ns_(max_kbps * 1000.0 / 8.0 * 1e-9),
      cap_bytes_(max_kbps * 1000.0 / 8.0 * burst_s),
      tokens_(0) {}

std::size_t ByteBudget::available(int64_t now_ns) {
  if (last_ns_ < 0) {
    last_ns_ = now_ns;
    tokens_ = cap_bytes_;  // a full bucket at the start: the first map goes out at once
  }
  if (now_ns > last_ns_) {
    tokens_ = std::min(cap_bytes_, tokens_ + bytes_per_ns_ * static_cast<double>(now_ns - last_ns_));
    last_ns_ = now_ns;
  }
  return tokens_ > 0 ? static_cast<std::size_t>(tokens_) : 0;
}

void ByteBudget::spend(std::size_t bytes) { tokens_ -= static_cast<double>(bytes); }

DenseViewEncoder::DenseViewEncoder(const core::TsdfMap& map)
    : map_(map), sent_(static_cast<std::size_t>(map.block_capacity())), scratch_(kDenseViewMaxBlockPoints) {}

void DenseViewEncoder::reset() {
  // Stamps restart with the cleared map: every block still there is sent
  // again (stamp 0 is older than any), every one gone is sent as removed.
  for (Sent& s : sent_) s.stamp = 0;
  cursor_ = 0;
}

std::size_t DenseViewEncoder::encode(uint8_t* out, std::size_t max_bytes) {
  if (max_bytes < kDenseViewMinMessageBytes || sent_.empty()) return 0;
  // Every block again, but what the browsers hold stays known: a block sent
  // and since evicted still goes out as removed.
  if (resend_all_.exchange(false, std::memory_order_relaxed))
    for (Sent& s : sent_) s.stamp = 0;
  const double block_m = map_.block_size_m();
  const double range_m = kRangeBlocks * block_m;
  std::size_t at = kDenseViewHeaderBytes;
  uint32_t records = 0;
  auto record = [&](const Eigen::Vector3i& key, int n) {
    const int32_t k[3] = {key.x(), key.y(), key.z()};
    put(out + at, k, 12);
    const auto n16 = static_cast<uint16_t>(n);
    put(out + at + 12, &n16, 2);
    at += kDenseViewRecordBytes;
    ++records;
  };
  const int cap = static_cast<int>(sent_.size());
  int visited = 0;
  bool full = false;
  for (; visited < cap; ++visited) {
    const int b = (cursor_ + visited) % cap;
    Sent& s = sent_[static_cast<std::size_t>(b)];
    const bool used = map_.block_used(b);
    const bool moved = s.sent && (!used || map_.block_key_of(b) != s.key);
    const bool changed = used && (!s.sent || moved || map_.block_updated(b) > s.stamp);
    if (!moved && !changed) continue;
    const int n = changed ? map_.extract_block_surface(b, scratch_.data(), kDenseViewMaxBlockPoints) : 0;
    const std::size_t need =
        (moved ? kDenseViewRecordBytes : 0) +
        (changed ? kDenseViewRecordBytes + kDenseViewPointBytes * static_cast<std::size_t>(n) : 0);
    if (at + need > max_bytes) {
      full = true;
      break;
    }
    if (moved) {
      record(s.key, 0);
      ++counters_.blocks_removed;
      s.sent = false;
    }
    if (changed) {
      const Eigen::Vector3i key = map_.block_key_of(b);
      // A block whose surface vanished (carved) is sent empty: the page drops it.
      record(key, n);
      const Eigen::Vector3d origin = key.cast<double>() * block_m;
      for (int i = 0; i < n; ++i) {
        const core::SurfacePoint& p = scratch_[static_cast<std::size_t>(i)];
        uint8_t* q = out + at + kDenseViewPointBytes * static_cast<std::size_t>(i);
        for (int a = 0; a < 3; ++a) {
          const double f = (static_cast<double>(p.p[a]) - origin[a]) / range_m;
          q[a] = static_cast<uint8_t>(std::lround(std::clamp(f, 0.0, 1.0) * 255.0));
        }
        std::memcpy(q + 3, p.rgb, 3);
      }
      at += kDenseViewPointBytes * static_cast<std::size_t>(n);
      s.key = key;
      s.stamp = map_.block_updated(b);
      s.sent = true;
      ++counters_.blocks_sent;
      counters_.points_sent += static_cast<uint64_t>(n);
    }
  }
  cursor_ = (cursor_ + visited) % cap;
  if (full) ++counters_.rounds_full;
  if (records == 0) return 0;
  out[0] = kDenseViewMessageType;
  out[1] = out[2] = out[3] = 0;
  put(out + 4, &records, 4);
  const auto bf = static_cast<float>(block_m), rf = static_cast<float>(range_m);
  put(out + 8, &bf, 4);
  put(out + 12, &rf, 4);
  ++counters_.messages;
  counters_.bytes += at;
  return at;
}

std::vector<DenseViewBlock> decode_dense_view(const uint8_t* data, std::size_t size) {
  auto fail = [](std::size_t at, const std::string& what) {
    throw std::runtime_error("dense view message: byte " + std::to_string(at) + ": " + what);
  };
  if (size < kDenseViewHeaderBytes) fail(size, "shorter than its header");
  if (data[0] != kDenseViewMessageType)
    fail(0, "not a dense view message (type " + std::to_string(data[0]) + ")");
  uint32_t records;
  float block_m, range_m;
  std::memcpy(&records, data + 4, 4);
  std::memcpy(&block_m, data + 8, 4);
  std::memcpy(&range_m, data + 12, 4);
  if (!(block_m > 0) || !(range_m > 0)) fail(8, "block size or range not positive");
  std::vector<DenseViewBlock> out;
  std::size_t at = kDenseViewHeaderBytes;
  for (uint32_t r = 0; r < records; ++r) {
    if (at + kDenseViewRecordBytes > size) fail(at, "record " + std::to_string(r) + " cut short");
    int32_t k[3];
    uint16_t n;
    std::memcpy(k, data + at, 12);
    std::memcpy(&n, data + at + 12, 2);
    at += kDenseViewRecordBytes;
    if (at + kDenseViewPointBytes * n > size)
      fail(at, "points of record " + std::to_string(r) + " cut short");
    DenseViewBlock b;
    b.key = Eigen::Vector3i(k[0], k[1], k[2]);
    b.points.resize(n);
    for (int i = 0; i < n; ++i) {
      const uint8_t* q = data + at + kDenseViewPointBytes * static_cast<std::size_t>(i);
      for (int a = 0; a < 3; ++a) {
        b.points[static_cast<std::size_t>(i)].p[a] =
            static_cast<float>(static_cast<double>(b.key[a]) * block_m + q[a] / 255.0 * range_m);
      }
      std::memcpy(b.points[static_cast<std::size_t>(i)].rgb, q + 3, 3);
    }
    at += kDenseViewPointBytes * n;
    out.push_back(std::move(b));
  }
  if (at != size) fail(at, "trailing bytes");
  return out;
}

}  // namespace kestrel::dense

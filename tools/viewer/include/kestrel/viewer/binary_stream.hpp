// Finished binary messages from another non-real-time thread to the viewer
// (the dense map's blocks from kst-dense, docs/dense.md). The producer owns the
// data the messages describe and encodes them itself, so the viewer never
// reads that data while it is written; the viewer thread only forwards the
// bytes to every browser. A few slots sized at start-up travel through two
// SPSC rings; no slot free: the producer simply does not encode this round
// (its state stays dirty and goes later), so nothing waits on the viewer.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::viewer {

class BinaryStream {
 public:
  static constexpr std::size_t kSlots = 4;
  // Allocates kSlots buffers of slot_bytes: call at start-up.
  explicit BinaryStream(std::size_t slot_bytes);
  BinaryStream(const BinaryStream&) = delete;
  BinaryStream& operator=(const BinaryStream&) = delete;

  // ---- producer (one thread). Allocation- and lock-free.
  // At least one browser is connected: encoding is worth it.
  bool wanted() const noexcept { return wanted_.load(std::memory_order_relaxed); }
  // True once after the viewer asked for everything again (a browser connected, or missed a message).
  bool take_resend_request() noexcept { return resend_.exchange(false, std::memory_order_acquire); }
  // A free buffer of *capacity bytes, or nullptr when the viewer holds them all.
  // It stays the producer's until publish().
  uint8_t* acquire(std::size_t* capacity) noexcept;
  // The buffer acquire() gave holds `bytes` bytes: hand it to the viewer.
  void publish(std::size_t bytes) noexcept;

  // ---- viewer thread.
  void set_wanted(bool on) noexcept { wanted_.store(on, std::memory_order_relaxed); }
  void request_resend() noexcept { resend_.store(true, std::memory_order_release); }
  // The oldest published message, or false; hand it back with release().
  bool take(const uint8_t** data, std::size_t* size, uint32_t* slot) noexcept;
  void release(uint32_t slot) noexcept { (void)free_.try_push(slot); }

  uint64_t published() const noexcept { return published_.load(std::memory_order_relaxed); }

 private:
  std::vector<std::vector<uint8_t>> buffers_;
  std::vector<std::size_t> sizes_;  // written by the producer before the push, read after the pop
  rt::SpscRing<uint32_t, kSlots> filled_, free_;
  std::atomic<bool> wanted_{false};
  std::atomic<bool> resend_{false};
  std::atomic<uint64_t> published_{0};
};

}  // namespace kestrel::viewer

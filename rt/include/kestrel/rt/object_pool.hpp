// Pool of N large objects (image buffers) handed out by handle, so frames move
// through rings as a 32-bit number instead of a copy or a shared_ptr.
//
// Memory: the N objects are allocated ONCE, in the constructor (T can be a VGA
// image, too big for a ring slot or a thread stack); acquire/release/get never
// allocate.
//
// Handles: uint32_t = generation (high 16 bits) | slot index (low 16 bits).
// Generations start at 1, so handle 0 (kInvalidHandle, also the default value
// of a handle field in a message) is never valid. A stale handle (slot already
// released, maybe reacquired) is refused by get() and release() until the
// 16-bit generation wraps (65535 reuses of one slot).
//
// Full policy: acquire() returns kInvalidHandle when every object is out and
// counts it in failed_acquires(); the caller drops its frame.
//
// Thread contract: acquire(), release() and get() are lock-free and may be
// called from any threads concurrently (the free list is a Treiber stack
// whose head carries a 32-bit tag against ABA). The holder of a handle owns
// the object: hand it to another thread only through something that orders
// memory (an SpscRing push/pop does); release() publishes the holder's writes
// to the next acquirer. get() on a handle you do not hold is a logic error
// (it may return an object another thread is writing).
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <type_traits>

namespace kestrel::rt {

using PoolHandle = std::uint32_t;
inline constexpr PoolHandle kInvalidHandle = 0;

template <class T, std::size_t N>
class ObjectPool {
  static_assert(N >= 1 && N < 0xFFFFu, "ObjectPool: 1 <= N < 65535 (16-bit slot index)");

 public:
  // Value-initialises the N objects (zeroed images: this also faults the pages
  // in at start-up rather than on the first frame).
  ObjectPool() : ObjectPool([](T&) {}) {}  // NOLINT(cppcoreguidelines-pro-type-member-init): delegates

  // init(T&) runs once per object at construction, e.g. to size a buffer.
  template <class Init>
  // NOLINTNEXTLINE(cppcoreguidelines-pro-type-member-init): every slot's atomics are stored below
  explicit ObjectPool(Init init) : objects_(new T[N]()) {
    for (std::size_t i = 0; i < N; ++i) {
      init(objects_[i]);
      live_[i].store(kInvalidHandle, std::memory_order_relaxed);
      gen_[i].store(0, std::memory_order_relaxed);
      next_[i].store(i + 1 < N ? static_cast<std::uint32_t>(i + 1) : kNil, std::memory_order_relaxed);
    }
    head_.store(pack(0, 0), std::memory_order_release);
  }

  ObjectPool(const ObjectPool&) = delete;
  ObjectPool& operator=(const ObjectPool&) = delete;

  // A free object's handle, or kInvalidHandle when all N are out.
  [[nodiscard]] PoolHandle acquire() noexcept {
    std::uint64_t old = head_.load(std::memory_order_acquire);
    std::uint32_t idx = kNil;
    for (;;) {
      idx = index_of(old);
      if (idx == kNil) {
        failed_acquires_.fetch_add(1, std::memory_order_relaxed);
        return kInvalidHandle;
      }
      // May read a next_ that a concurrent pop/push is changing; then the tag
      // has moved on and the CAS below fails, so the stale value is never used.
      const std::uint32_t next = next_[idx].load(std::memory_order_relaxed);
      // Acquire on success: we see the releasing thread's writes to the object.
      if (head_.compare_exchange_weak(old, pack(tag_of(old) + 1, next), std::memory_order_acquire,
                                      std::memory_order_acquire)) {
        break;
      }
    }
    std::uint32_t gen = (gen_[idx].load(std::memory_order_relaxed) + 1) & 0xFFFFu;
    if (gen == 0) gen = 1;
    gen_[idx].store(gen, std::memory_order_relaxed);
    const PoolHandle h = (gen << 16) | idx;
    // Release, paired with release()'s acq_rel CAS: the gen_ store above is
    // visible to whoever acquires this slot next (via the free-list chain).
    live_[idx].store(h, std::memory_order_release);
    in_use_.fetch_add(1, std::memory_order_relaxed);
    return h;
  }

  // The object behind h, or nullptr if h is invalid or stale.
  [[nodiscard]] T* get(PoolHandle h) noexcept {
    const std::uint32_t idx = h & 0xFFFFu;
    if (h == kInvalidHandle || idx >= N) return nullptr;
    return live_[idx].load(std::memory_order_relaxed) == h ? &objects_[idx] : nullptr;
  }
  [[nodiscard]] const T* get(PoolHandle h) const noexcept { return const_cast<ObjectPool*>(this)->get(h); }

  // Returns the object to the pool. False (and counted) for an invalid, stale
  // or already released handle: a double release never corrupts the list.
  bool release(PoolHandle h) noexcept {
    const std::uint32_t idx = h & 0xFFFFu;
    PoolHandle expected = h;
    if (h == kInvalidHandle || idx >= N ||
        !live_[idx].compare_exchange_strong(expected, kInvalidHandle, std::memory_order_acq_rel,
                                            std::memory_order_relaxed)) {
      bad_releases_.fetch_add(1, std::memory_order_relaxed);
      return false;
    }
    in_use_.fetch_sub(1, std::memory_order_relaxed);
    std::uint64_t old = head_.load(std::memory_order_relaxed);
    do {
      next_[idx].store(index_of(old), std::memory_order_relaxed);
      // Release on success: publishes next_[idx] and our writes to the object.
    } while (!head_.compare_exchange_weak(old, pack(tag_of(old) + 1, idx), std::memory_order_release,
                                          std::memory_order_relaxed));
    return true;
  }

  [[nodiscard]] static constexpr std::size_t capacity() noexcept { return N; }
  [[nodiscard]] std::size_t in_use() const noexcept { return in_use_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t failed_acquires() const noexcept {
    return failed_acquires_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] std::uint64_t bad_releases() const noexcept {
    return bad_releases_.load(std::memory_order_relaxed);
  }

 private:
  static constexpr std::uint32_t kNil = 0xFFFFFFFFu;
  static std::uint64_t pack(std::uint32_t tag, std::uint32_t idx) noexcept {
    return (static_cast<std::uint64_t>(tag) << 32) | idx;
  }
  static std::uint32_t index_of(std::uint64_t v) noexcept { return static_cast<std::uint32_t>(v); }
  static std::uint32_t tag_of(std::uint64_t v) noexcept { return static_cast<std::uint32_t>(v >> 32); }

  std::unique_ptr<T[]> objects_;
  std::atomic<std::uint32_t> next_[N];
  std::atomic<PoolHandle> live_[N];                 // current handle of an acquired slot, 0 when free
  std::atomic<std::uint32_t> gen_[N];               // last generation handed out per slot
  alignas(64) std::atomic<std::uint64_t> head_{0};  // tag:32 | index:32
  alignas(64) std::atomic<std::size_t> in_use_{0};
  std::atomic<std::uint64_t> failed_acquires_{0};
  std::atomic<std::uint64_t> bad_releases_{0};
};

}  // namespace kestrel::rt

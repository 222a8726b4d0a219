// Lock-free single-producer / single-consumer ring with fixed capacity.
//
// The API follows rigtorp's SPSCQueue (try_push / try_emplace report failure,
// front / pop on the consumer side), written from scratch for Kestrel:
//  - storage is inside the object (no heap), so a ring sized at start-up never
//    allocates again;
//  - full policy is "reject newest and count": a failed push returns false and
//    bumps drops(); the producer never blocks and never overwrites what the
//    consumer has not seen yet;
//  - head and tail live on separate cache lines, and each side keeps a private
//    copy of the other side's index so the shared line is only read when the
//    cached value says "full" (producer) or "empty" (consumer).
//
// Thread contract: exactly one producer thread calls try_push / try_emplace /
// note_drop, exactly one consumer thread calls front / pop / try_pop. size(),
// empty(), drops() may be called from any thread and are approximate while the
// other sides run.
#pragma once

#include <atomic>
#include <cassert>
#include <cstddef>
#include <cstdint>
#include <new>
#include <type_traits>
#include <utility>

namespace kestrel::rt {

// Fixed at 64 rather than std::hardware_destructive_interference_size: that
// constant varies with -march/-mtune and g++ warns when it leaks into an ABI.
inline constexpr std::size_t kCacheLine = 64;

template <class T, std::size_t N>
// NOLINTNEXTLINE(cppcoreguidelines-pro-type-member-init): storage_ is raw (below)
class SpscRing {
  static_assert(N >= 1, "SpscRing needs a capacity of at least 1");
  static_assert(std::is_nothrow_destructible_v<T>, "elements must be nothrow destructible");

 public:
  using value_type = T;

  SpscRing() = default;  // NOLINT(cppcoreguidelines-pro-type-member-init)
  SpscRing(const SpscRing&) = delete;
  SpscRing& operator=(const SpscRing&) = delete;

  ~SpscRing() {
    while (front() != nullptr) pop();
  }

  // ---- producer side -------------------------------------------------------

  template <class... A>
  [[nodiscard]] bool try_emplace(A&&... args) noexcept(std::is_nothrow_constructible_v<T, A&&...>) {
    static_assert(std::is_constructible_v<T, A&&...>, "T is not constructible from these arguments");
    const std::uint64_t tail = tail_.load(std::memory_order_relaxed);
    if (tail - head_cache_ == N) {
      // Looks full with the stale copy: refresh it. Acquire pairs with the
      // consumer's release in pop(), so the slot it freed is really done with.
      head_cache_ = head_.load(std::memory_order_acquire);
      if (tail - head_cache_ == N) {
        note_drop();
        return false;
      }
    }
    ::new (raw_slot(tail)) T(std::forward<A>(args)...);
    // Release publishes the constructed element to the consumer's acquire.
    tail_.store(tail + 1, std::memory_order_release);
    return true;
  }

  [[nodiscard]] bool try_push(const T& v) noexcept(std::is_nothrow_copy_constructible_v<T>) {
    return try_emplace(v);
  }
  [[nodiscard]] bool try_push(T&& v) noexcept(std::is_nothrow_move_constructible_v<T>) {
    return try_emplace(std::move(v));
  }

  // For producers that discard a message before trying to push it (e.g. a
  // driver that already knows the ring is full); keeps one drop tally.
  void note_drop(std::uint64_t n = 1) noexcept {
    // Single writer: a plain load + store is enough and cheaper than an RMW.
    drops_.store(drops_.load(std::memory_order_relaxed) + n, std::memory_order_relaxed);
  }

  // ---- consumer side -------------------------------------------------------

  // Oldest element, or nullptr when empty. Valid until pop().
  [[nodiscard]] T* front() noexcept {
    const std::uint64_t head = head_.load(std::memory_order_relaxed);
    if (head == tail_cache_) {
      tail_cache_ = tail_.load(std::memory_order_acquire);
      if (head == tail_cache_) return nullptr;
    }
    return slot(head);
  }

  // Destroys the oldest element. Precondition: front() != nullptr.
  void pop() noexcept {
    const std::uint64_t head = head_.load(std::memory_order_relaxed);
    assert(head != tail_.load(std::memory_order_acquire) && "pop() on an empty SpscRing");
    slot(head)->~T();
    // Release: the producer may reuse the slot only after the destructor ran.
    head_.store(head + 1, std::memory_order_release);
  }

  // Moves the oldest element out. Convenience over front()+pop().
  [[nodiscard]] bool try_pop(T& out) noexcept(std::is_nothrow_move_assignable_v<T>) {
    T* p = front();
    if (p == nullptr) return false;
    out = std::move(*p);
    pop();
    return true;
  }

  // ---- any thread ----------------------------------------------------------

  [[nodiscard]] std::size_t size() const noexcept {
    // Head first: tail only grows, so the difference never goes negative; it
    // can exceed N if the other sides moved in between, hence the clamp.
    const std::uint64_t head = head_.load(std::memory_order_acquire);
    const std::uint64_t tail = tail_.load(std::memory_order_acquire);
    const std::uint64_t n = tail - head;
    return n > N ? N : static_cast<std::size_t>(n);
  }
  [[nodiscard]] bool empty() const noexcept { return size() == 0; }
  [[nodiscard]] static constexpr std::size_t capacity() noexcept { return N; }
  [[nodiscard]] std::uint64_t drops() const noexcept { return drops_.load(std::memory_order_relaxed); }
  // Total pushed since construction (monotonic), e.g. for perf dumps.
  [[nodiscard]] std::uint64_t pushed() const noexcept { return tail_.load(std::memory_order_relaxed); }

 private:
  // 64-bit counters that never wrap in practice (584 years at 1 GHz); the slot
  // is counter % N, which keeps all N slots usable (no sacrificial slot).
  void* raw_slot(std::uint64_t i) noexcept { return storage_ + static_cast<std::size_t>(i % N) * sizeof(T); }
  // Only for slots that hold a live element (launder needs one).
  T* slot(std::uint64_t i) noexcept { return std::launder(static_cast<T*>(raw_slot(i))); }

  // Consumer-owned line.
  alignas(kCacheLine) std::atomic<std::uint64_t> head_{0};
  std::uint64_t tail_cache_ = 0;
  // Producer-owned line.
  alignas(kCacheLine) std::atomic<std::uint64_t> tail_{0};
  std::uint64_t head_cache_ = 0;
  std::atomic<std::uint64_t> drops_{0};
  // Elements start on their own line so the indices never share with them;
  // the 64-byte class alignment rounds sizeof up, so whatever follows this
  // object does not share the last element line either.
  // Raw slots, constructed in place by push: zeroing them would fault in
  // pages the ring may never use and cost a pass over N elements.
  alignas(kCacheLine > alignof(T) ? kCacheLine : alignof(T)) unsigned char storage_[N * sizeof(T)];
};

}  // namespace kestrel::rt

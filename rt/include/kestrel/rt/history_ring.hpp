// Overwrite-oldest ring for look-back by timestamp (IMU history for delayed
// camera frames, delayed fusion).
//
// Full policy: the newest sample always goes in and the oldest one is
// overwritten (counted in overwrites()): for a look-back buffer the recent
// past matters, and a caller that finds its timestamp older than oldest()
// knows the buffer was sized too small for its delay.
//
// Thread contract: NOT thread-safe. One thread owns the ring (the tracking
// thread fills it from the IMU SPSC ring and queries it); nothing else touches
// it. Storage is inside the object, no heap.
#pragma once

#include <cassert>
#include <cstddef>
#include <cstdint>
#include <new>
#include <type_traits>
#include <utility>

namespace kestrel::rt {

// storage_ is raw memory, constructed slot by slot in push(): nothing to initialise.
template <class T, std::size_t N>
class HistoryRing {  // NOLINT(cppcoreguidelines-pro-type-member-init)
  static_assert(N >= 1, "HistoryRing needs a capacity of at least 1");

 public:
  using value_type = T;

  HistoryRing() = default;  // NOLINT(cppcoreguidelines-pro-type-member-init)
  HistoryRing(const HistoryRing&) = delete;
  HistoryRing& operator=(const HistoryRing&) = delete;
  ~HistoryRing() { clear(); }

  // Appends v; when full, replaces the oldest element. Elements are expected
  // in non-decreasing time order for lower_bound_time() to be meaningful.
  void push(const T& v) {
    if (size_ < N) {
      ::new (raw(index(size_))) T(v);
      ++size_;
    } else {
      at(oldest_) = v;
      oldest_ = (oldest_ + 1) % N;
      ++overwrites_;
    }
  }

  // Drops the k oldest elements (e.g. samples no longer needed).
  void pop_front(std::size_t k = 1) noexcept {
    if (k > size_) k = size_;
    for (std::size_t i = 0; i < k; ++i) {
      at(oldest_).~T();
      oldest_ = (oldest_ + 1) % N;
    }
    size_ -= k;
    if (size_ == 0) oldest_ = 0;
  }

  void clear() noexcept { pop_front(size_); }

  [[nodiscard]] std::size_t size() const noexcept { return size_; }
  [[nodiscard]] bool empty() const noexcept { return size_ == 0; }
  [[nodiscard]] bool full() const noexcept { return size_ == N; }
  [[nodiscard]] static constexpr std::size_t capacity() noexcept { return N; }
  [[nodiscard]] std::uint64_t overwrites() const noexcept { return overwrites_; }

  // i = 0 is the oldest element, size()-1 the newest. Precondition: i < size().
  [[nodiscard]] T& operator[](std::size_t i) noexcept {
    assert(i < size_);
    return at(index(i));
  }
  [[nodiscard]] const T& operator[](std::size_t i) const noexcept {
    assert(i < size_);
    return at(index(i));
  }
  [[nodiscard]] const T& oldest() const noexcept { return (*this)[0]; }
  [[nodiscard]] const T& newest() const noexcept { return (*this)[size_ - 1]; }

  // Index (oldest-first) of the first element whose time get_t(elem) is >= t_ns,
  // or size() if every element is older. Binary search, O(log N); requires the
  // contents in non-decreasing time order. get_t: (const T&) -> int64_t.
  template <class GetT>
  [[nodiscard]] std::size_t lower_bound_time(std::int64_t t_ns, GetT get_t) const {
    std::size_t lo = 0;
    std::size_t hi = size_;
    while (lo < hi) {
      const std::size_t mid = lo + (hi - lo) / 2;
      if (static_cast<std::int64_t>(get_t((*this)[mid])) < t_ns) {
        lo = mid + 1;
      } else {
        hi = mid;
      }
    }
    return lo;
  }

 private:
  std::size_t index(std::size_t i) const noexcept { return (oldest_ + i) % N; }
  void* raw(std::size_t slot) noexcept { return storage_ + slot * sizeof(T); }
  T& at(std::size_t slot) noexcept {
    return *std::launder(reinterpret_cast<T*>(storage_ + slot * sizeof(T)));
  }
  const T& at(std::size_t slot) const noexcept {
    return *std::launder(reinterpret_cast<const T*>(storage_ + slot * sizeof(T)));
  }

  std::size_t oldest_ = 0;  // slot of element 0
  std::size_t size_ = 0;
  std::uint64_t overwrites_ = 0;
  alignas(T) unsigned char storage_[N * sizeof(T)];
};

}  // namespace kestrel::rt

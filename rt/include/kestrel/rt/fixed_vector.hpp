// Vector with in-place storage for at most N elements: never allocates.
//
// Full policy: push_back / emplace_back refuse (false / nullptr) instead of
// growing, so capacity is a start-up decision and overflow a visible event.
// Works with non-trivial T (placement new, explicit destruction). Not
// thread-safe (a plain container).
#pragma once

#include <cassert>
#include <cstddef>
#include <new>
#include <type_traits>
#include <utility>

namespace kestrel::rt {

template <class T, std::size_t N>
class FixedVector {
 public:
  using value_type = T;
  using size_type = std::size_t;
  using iterator = T*;
  using const_iterator = const T*;
  using reference = T&;
  using const_reference = const T&;

  FixedVector() noexcept = default;
  FixedVector(const FixedVector& o) noexcept(std::is_nothrow_copy_constructible_v<T>) {
    for (const T& v : o) ::new (raw(size_++)) T(v);
  }
  FixedVector(FixedVector&& o) noexcept(std::is_nothrow_move_constructible_v<T>) {
    for (T& v : o) ::new (raw(size_++)) T(std::move(v));
    o.clear();
  }
  FixedVector& operator=(const FixedVector& o) {
    if (this != &o) {
      clear();
      for (const T& v : o) ::new (raw(size_++)) T(v);
    }
    return *this;
  }
  FixedVector& operator=(FixedVector&& o) noexcept(std::is_nothrow_move_constructible_v<T>) {
    if (this != &o) {
      clear();
      for (T& v : o) ::new (raw(size_++)) T(std::move(v));
      o.clear();
    }
    return *this;
  }
  ~FixedVector() { clear(); }

  [[nodiscard]] bool push_back(const T& v) { return emplace_back(v) != nullptr; }
  [[nodiscard]] bool push_back(T&& v) { return emplace_back(std::move(v)) != nullptr; }

  // Constructs in place; returns the new element, or nullptr when full.
  template <class... A>
  [[nodiscard]] T* emplace_back(A&&... args) {
    if (size_ == N) return nullptr;
    T* p = ::new (raw(size_)) T(std::forward<A>(args)...);
    ++size_;  // after construction: a throwing constructor leaves size unchanged
    return p;
  }

  void pop_back() noexcept {
    assert(size_ > 0);
    data()[--size_].~T();
  }

  void clear() noexcept {
    while (size_ > 0) pop_back();
  }

  // Removes element i, keeping order (moves the tail down by one).
  void erase(std::size_t i) {
    assert(i < size_);
    for (std::size_t k = i + 1; k < size_; ++k) data()[k - 1] = std::move(data()[k]);
    pop_back();
  }
  // Removes element i in O(1) by moving the last element into its place.
  void erase_unordered(std::size_t i) {
    assert(i < size_);
    if (i + 1 != size_) data()[i] = std::move(data()[size_ - 1]);
    pop_back();
  }

  [[nodiscard]] std::size_t size() const noexcept { return size_; }
  [[nodiscard]] bool empty() const noexcept { return size_ == 0; }
  [[nodiscard]] bool full() const noexcept { return size_ == N; }
  [[nodiscard]] static constexpr std::size_t capacity() noexcept { return N; }

  // Pointer arithmetic over the storage is fine: live elements are contiguous.
  [[nodiscard]] T* data() noexcept { return std::launder(reinterpret_cast<T*>(storage_)); }
  [[nodiscard]] const T* data() const noexcept { return std::launder(reinterpret_cast<const T*>(storage_)); }

  [[nodiscard]] T& operator[](std::size_t i) noexcept {
    assert(i < size_);
    return data()[i];
  }
  [[nodiscard]] const T& operator[](std::size_t i) const noexcept {
    assert(i < size_);
    return data()[i];
  }
  [[nodiscard]] T& front() noexcept { return (*this)[0]; }
  [[nodiscard]] const T& front() const noexcept { return (*this)[0]; }
  [[nodiscard]] T& back() noexcept { return (*this)[size_ - 1]; }
  [[nodiscard]] const T& back() const noexcept { return (*this)[size_ - 1]; }

  [[nodiscard]] iterator begin() noexcept { return data(); }
  [[nodiscard]] iterator end() noexcept { return data() + size_; }
  [[nodiscard]] const_iterator begin() const noexcept { return data(); }
  [[nodiscard]] const_iterator end() const noexcept { return data() + size_; }

 private:
  void* raw(std::size_t i) noexcept { return storage_ + i * sizeof(T); }

  std::size_t size_ = 0;
  alignas(T) unsigned char storage_[(N > 0 ? N : 1) * sizeof(T)];
};

}  // namespace kestrel::rt

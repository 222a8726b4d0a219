// Element type that records constructions and destructions and detects use
// of dead objects and double destruction (rigtorp-style lifetime testing).
#pragma once

#include <cstdint>

namespace kestrel::rt::test {

struct Lifetimes {
  int constructed = 0;
  int destroyed = 0;
  int bad = 0;  // destroyed twice, or copied/moved from a dead object
  [[nodiscard]] int alive() const { return constructed - destroyed; }
};

inline Lifetimes& lifetimes() {
  static Lifetimes l;
  return l;
}

class Tracked {
 public:
  static constexpr std::uint32_t kAlive = 0xA11CEu;
  static constexpr std::uint32_t kDead = 0xDEADu;

  explicit Tracked(int v = 0) noexcept : v_(v) { ++lifetimes().constructed; }
  Tracked(const Tracked& o) noexcept : v_(o.v_) {
    check(o);
    ++lifetimes().constructed;
  }
  Tracked(Tracked&& o) noexcept : v_(o.v_) {
    check(o);
    o.v_ = -1;
    ++lifetimes().constructed;
  }
  Tracked& operator=(const Tracked& o) noexcept {
    check(*this);
    check(o);
    v_ = o.v_;
    return *this;
  }
  Tracked& operator=(Tracked&& o) noexcept {
    check(*this);
    check(o);
    v_ = o.v_;
    o.v_ = -1;
    return *this;
  }
  ~Tracked() {
    check(*this);
    magic_ = kDead;
    ++lifetimes().destroyed;
  }
  [[nodiscard]] int value() const {
    check(*this);
    return v_;
  }

 private:
  static void check(const Tracked& t) {
    if (t.magic_ != kAlive) ++lifetimes().bad;
  }
  int v_;
  std::uint32_t magic_ = kAlive;
};

// Move-only, non-default-constructible.
class MoveOnly {
 public:
  explicit MoveOnly(int v) : t_(v) {}
  MoveOnly(MoveOnly&&) noexcept = default;
  MoveOnly& operator=(MoveOnly&&) noexcept = default;
  MoveOnly(const MoveOnly&) = delete;
  MoveOnly& operator=(const MoveOnly&) = delete;
  [[nodiscard]] int value() const { return t_.value(); }

 private:
  Tracked t_;
};

}  // namespace kestrel::rt::test

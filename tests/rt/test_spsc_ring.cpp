#include <gtest/gtest.h>

#include <cstdint>
#include <string>
#include <type_traits>

#include "kestrel/rt/spsc_ring.hpp"
#include "lifetime_tracker.hpp"

namespace kestrel::rt {
namespace {

using test::lifetimes;
using test::MoveOnly;
using test::Tracked;

static_assert(alignof(SpscRing<int, 4>) >= 64, "indices must sit on their own cache lines");

// Fill, check full behaviour, drain, and repeat enough times to wrap the
// indices across the storage many times; values must come out in order.
template <std::size_t N>
void fill_drain_wrap() {
  SpscRing<int, N> q;
  EXPECT_EQ(q.capacity(), N);
  EXPECT_TRUE(q.empty());
  EXPECT_EQ(q.front(), nullptr);
  int next_in = 0;
  int next_out = 0;
  std::uint64_t expected_drops = 0;
  for (int round = 0; round < 7; ++round) {
    // Partial fills shift the start position so every slot is used as the head.
    const std::size_t fill = round % 2 == 0 ? N : (N + 1) / 2;
    for (std::size_t i = 0; i < fill; ++i) ASSERT_TRUE(q.try_push(next_in++));
    EXPECT_EQ(q.size(), fill);
    if (fill == N) {
      EXPECT_FALSE(q.try_push(-1)) << "a full ring must reject the newest element";
      EXPECT_FALSE(q.try_emplace(-2));
      expected_drops += 2;
      EXPECT_EQ(q.size(), N);
    }
    EXPECT_EQ(q.drops(), expected_drops);
    while (int* p = q.front()) {
      EXPECT_EQ(*p, next_out++);
      q.pop();
    }
    EXPECT_TRUE(q.empty());
  }
  EXPECT_EQ(next_in, next_out);
  EXPECT_EQ(q.pushed(), static_cast<std::uint64_t>(next_in));
}

TEST(SpscRing, CapacityOne) { fill_drain_wrap<1>(); }
TEST(SpscRing, CapacityTwo) { fill_drain_wrap<2>(); }
TEST(SpscRing, CapacityOdd) {
  fill_drain_wrap<3>();
  fill_drain_wrap<7>();
  fill_drain_wrap<1000>();
}
TEST(SpscRing, CapacityPowerOfTwo) { fill_drain_wrap<64>(); }

TEST(SpscRing, InterleavedPushPopKeepsOrder) {
  SpscRing<int, 5> q;
  int in = 0;
  int out = 0;
  for (int step = 0; step < 1000; ++step) {
    // Push two, pop one until full, then drain: exercises every head/tail offset.
    if (q.size() < 5) {
      ASSERT_TRUE(q.try_push(in++));
      if (q.size() < 5) {
        ASSERT_TRUE(q.try_push(in++));
      }
    }
    int v = -1;
    ASSERT_TRUE(q.try_pop(v));
    EXPECT_EQ(v, out++);
  }
  int v = -1;
  while (q.try_pop(v)) EXPECT_EQ(v, out++);
  EXPECT_EQ(in, out);
  EXPECT_FALSE(q.try_pop(v));
}

TEST(SpscRing, NoteDropCounts) {
  SpscRing<int, 2> q;
  q.note_drop();
  q.note_drop(4);
  EXPECT_EQ(q.drops(), 5u);
}

TEST(SpscRing, LifetimeOfElements) {
  lifetimes() = {};
  {
    SpscRing<Tracked, 3> q;
    EXPECT_EQ(lifetimes().constructed, 0) << "storage must be raw, not default-constructed";
    ASSERT_TRUE(q.try_emplace(1));
    Tracked t2(2);
    ASSERT_TRUE(q.try_push(t2));           // copy
    ASSERT_TRUE(q.try_push(Tracked(3)));   // move
    EXPECT_FALSE(q.try_push(Tracked(4)));  // full: rejected, temporary destroyed once
    EXPECT_EQ(lifetimes().alive(), 4);     // three in the ring + t2
    EXPECT_EQ(q.front()->value(), 1);
    q.pop();
    EXPECT_EQ(lifetimes().alive(), 3);
    // Wrap with live elements: the destructor must destroy exactly those left.
    ASSERT_TRUE(q.try_emplace(5));
    EXPECT_FALSE(q.try_emplace(6));
  }
  EXPECT_EQ(lifetimes().alive(), 0) << "leak or double destroy";
  EXPECT_EQ(lifetimes().bad, 0);
}

TEST(SpscRing, MoveOnlyElements) {
  lifetimes() = {};
  {
    SpscRing<MoveOnly, 4> q;
    for (int i = 0; i < 4; ++i) ASSERT_TRUE(q.try_emplace(i));
    MoveOnly extra(99);
    EXPECT_FALSE(q.try_push(std::move(extra)));
    MoveOnly out(-5);
    ASSERT_TRUE(q.try_pop(out));
    EXPECT_EQ(out.value(), 0);
    EXPECT_EQ(q.front()->value(), 1);
    ASSERT_TRUE(q.try_push(MoveOnly(4)));
  }
  EXPECT_EQ(lifetimes().alive(), 0);
  EXPECT_EQ(lifetimes().bad, 0);
}

TEST(SpscRing, NonTrivialStdType) {
  SpscRing<std::string, 3> q;
  ASSERT_TRUE(q.try_emplace(100, 'x'));  // long enough to live on the heap
  ASSERT_TRUE(q.try_push(std::string("short")));
  EXPECT_EQ(q.front()->size(), 100u);
  q.pop();
  EXPECT_EQ(*q.front(), "short");
  // Leaves one element for the destructor (ASan/LSan would flag a leak).
}

struct alignas(128) OverAligned {
  int v = 0;
};

TEST(SpscRing, OverAlignedElements) {
  SpscRing<OverAligned, 3> q;
  for (int i = 0; i < 3; ++i) {
    ASSERT_TRUE(q.try_push(OverAligned{i}));
    EXPECT_EQ(reinterpret_cast<std::uintptr_t>(q.front()) % 128, 0u);
    q.pop();
  }
}

}  // namespace
}  // namespace kestrel::rt

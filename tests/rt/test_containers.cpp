#include <gtest/gtest.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/rt/fixed_vector.hpp"
#include "kestrel/rt/history_ring.hpp"
#include "lifetime_tracker.hpp"

namespace kestrel::rt {
namespace {

using test::lifetimes;
using test::MoveOnly;
using test::Tracked;

struct Sample {
  std::int64_t t_ns;
  int value;
};
std::int64_t time_of(const Sample& s) { return s.t_ns; }

TEST(HistoryRing, OverwritesOldestAndCounts) {
  HistoryRing<Sample, 4> h;
  EXPECT_TRUE(h.empty());
  for (int i = 0; i < 10; ++i) h.push({i * 100, i});
  EXPECT_TRUE(h.full());
  EXPECT_EQ(h.size(), 4u);
  EXPECT_EQ(h.overwrites(), 6u);
  for (std::size_t i = 0; i < 4; ++i) EXPECT_EQ(h[i].value, 6 + static_cast<int>(i)) << "oldest-first order";
  EXPECT_EQ(h.oldest().value, 6);
  EXPECT_EQ(h.newest().value, 9);
}

TEST(HistoryRing, LowerBoundTimeAgainstLinearScan) {
  HistoryRing<Sample, 16> h;
  // Wrapped contents with repeated timestamps.
  std::int64_t t = 0;
  for (int i = 0; i < 37; ++i) {
    t += (i % 3 == 0) ? 0 : 250;
    h.push({t, i});
  }
  for (std::int64_t q = h.oldest().t_ns - 300; q <= h.newest().t_ns + 300; q += 50) {
    std::size_t expected = h.size();
    for (std::size_t i = 0; i < h.size(); ++i) {
      if (h[i].t_ns >= q) {
        expected = i;
        break;
      }
    }
    EXPECT_EQ(h.lower_bound_time(q, time_of), expected) << "query " << q;
  }
  EXPECT_EQ(h.lower_bound_time(-1'000'000, time_of), 0u);
  EXPECT_EQ(h.lower_bound_time(h.newest().t_ns + 1, time_of), h.size());
}

TEST(HistoryRing, EmptyLookup) {
  HistoryRing<Sample, 3> h;
  EXPECT_EQ(h.lower_bound_time(0, time_of), 0u);
}

TEST(HistoryRing, PopFrontAndLifetimes) {
  lifetimes() = {};
  {
    HistoryRing<Tracked, 5> h;
    EXPECT_EQ(lifetimes().constructed, 0);
    for (int i = 0; i < 8; ++i) h.push(Tracked(i));
    EXPECT_EQ(h.size(), 5u);
    h.pop_front(2);
    EXPECT_EQ(h.size(), 3u);
    EXPECT_EQ(h[0].value(), 5);
    h.push(Tracked(8));
    EXPECT_EQ(h.newest().value(), 8);
    h.pop_front(100);
    EXPECT_TRUE(h.empty());
    h.push(Tracked(9));
    EXPECT_EQ(h.oldest().value(), 9);
  }
  EXPECT_EQ(lifetimes().alive(), 0);
  EXPECT_EQ(lifetimes().bad, 0);
}

TEST(FixedVector, PushUntilFull) {
  FixedVector<int, 3> v;
  EXPECT_TRUE(v.empty());
  EXPECT_TRUE(v.push_back(1));
  EXPECT_TRUE(v.push_back(2));
  EXPECT_NE(v.emplace_back(3), nullptr);
  EXPECT_TRUE(v.full());
  EXPECT_FALSE(v.push_back(4));
  EXPECT_EQ(v.emplace_back(5), nullptr);
  int sum = 0;
  for (int x : v) sum += x;
  EXPECT_EQ(sum, 6);
  v.pop_back();
  EXPECT_EQ(v.size(), 2u);
  EXPECT_EQ(v.back(), 2);
}

TEST(FixedVector, NonTrivialElements) {
  lifetimes() = {};
  {
    FixedVector<Tracked, 4> v;
    EXPECT_EQ(lifetimes().constructed, 0);
    ASSERT_TRUE(v.emplace_back(1));
    ASSERT_TRUE(v.push_back(Tracked(2)));
    const Tracked t3(3);
    ASSERT_TRUE(v.push_back(t3));
    ASSERT_TRUE(v.emplace_back(4));
    EXPECT_FALSE(v.push_back(Tracked(5)));
    FixedVector<Tracked, 4> copy = v;
    FixedVector<Tracked, 4> moved = std::move(copy);
    EXPECT_TRUE(copy.empty());
    EXPECT_EQ(moved.size(), 4u);
    v.erase(1);  // keeps order
    ASSERT_EQ(v.size(), 3u);
    EXPECT_EQ(v[0].value(), 1);
    EXPECT_EQ(v[1].value(), 3);
    EXPECT_EQ(v[2].value(), 4);
    v.erase_unordered(0);
    ASSERT_EQ(v.size(), 2u);
    EXPECT_EQ(v[0].value(), 4);
    copy = moved;
    EXPECT_EQ(copy.size(), 4u);
    copy.clear();
    EXPECT_EQ(lifetimes().alive(), 1 + 2 + 4);  // t3, v, moved
  }
  EXPECT_EQ(lifetimes().alive(), 0);
  EXPECT_EQ(lifetimes().bad, 0);
}

TEST(FixedVector, MoveOnlyAndHeapOwningElements) {
  FixedVector<MoveOnly, 2> m;
  ASSERT_TRUE(m.emplace_back(7));
  ASSERT_TRUE(m.push_back(MoveOnly(8)));
  EXPECT_EQ(m[1].value(), 8);
  FixedVector<std::unique_ptr<int>, 2> p;
  ASSERT_TRUE(p.push_back(std::make_unique<int>(3)));
  FixedVector<std::string, 2> s;
  ASSERT_TRUE(s.emplace_back(64, 'k'));
  FixedVector<std::string, 2> s2 = s;
  EXPECT_EQ(s2[0], std::string(64, 'k'));
  // Destructors free everything: LSan (debug preset) flags a leak otherwise.
}

}  // namespace
}  // namespace kestrel::rt

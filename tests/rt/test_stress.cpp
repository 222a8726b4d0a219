// Two-thread stress tests (label `stress`, run under ThreadSanitizer by the
// tsan preset). Each is bounded by an item count and a wall-time budget,
// whichever comes first, so a slow sanitizer build still finishes quickly.
#include <gtest/gtest.h>

#include <array>
#include <atomic>
#include <cstdint>
#include <thread>
#include <vector>

#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/doorbell.hpp"
#include "kestrel/rt/mailbox.hpp"
#include "kestrel/rt/object_pool.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::rt {
namespace {

constexpr std::int64_t kBudgetNs = 2 * kNsPerS;

// Checked every 1024 items; a deadline, not a rate.
struct Budget {
  std::int64_t deadline_ns = now_ns() + kBudgetNs;
  [[nodiscard]] bool exhausted(std::uint64_t i) const { return (i & 1023u) == 0 && now_ns() > deadline_ns; }
};

struct Msg {
  std::uint64_t seq;
  std::uint64_t check;  // derived from seq: catches a torn or stale slot
};
constexpr std::uint64_t mix(std::uint64_t s) { return s * 0x9E3779B97F4A7C15ull ^ 0xD1B54A32D192ED03ull; }

template <std::size_t N>
void spsc_sequence_stress(std::uint64_t max_items) {
  auto q = std::make_unique<SpscRing<Msg, N>>();
  std::atomic<bool> done{false};
  std::atomic<std::uint64_t> produced{0};
  std::uint64_t failed_pushes = 0;

  std::thread producer([&] {
    Budget budget;
    std::uint64_t seq = 0;
    while (seq < max_items && !budget.exhausted(seq)) {
      if (q->try_push(Msg{seq, mix(seq)})) {
        ++seq;
      } else {
        ++failed_pushes;  // full: retry (every failure is also a drop())
      }
    }
    produced.store(seq, std::memory_order_relaxed);
    done.store(true, std::memory_order_release);
  });

  std::uint64_t expected = 0;
  std::uint64_t errors = 0;
  for (;;) {
    if (Msg* m = q->front()) {
      if (m->seq != expected || m->check != mix(m->seq)) ++errors;
      expected = m->seq + 1;
      q->pop();
    } else if (done.load(std::memory_order_acquire)) {
      if (q->front() == nullptr) break;  // re-check: items pushed before `done`
    }
  }
  producer.join();
  EXPECT_EQ(errors, 0u) << "out-of-order, lost, duplicated or torn items";
  EXPECT_EQ(expected, produced.load());
  EXPECT_GT(produced.load(), 1000u);
  EXPECT_EQ(q->drops(), failed_pushes);
  EXPECT_TRUE(q->empty());
}

TEST(SpscRingStress, SequenceCapacity1024) { spsc_sequence_stress<1024>(5'000'000); }
TEST(SpscRingStress, SequenceCapacity1) { spsc_sequence_stress<1>(500'000); }
TEST(SpscRingStress, SequenceCapacity3) { spsc_sequence_stress<3>(1'000'000); }

// A consumer that sleeps on a doorbell between drains, with a timeout far
// longer than the test: a ring lost between its last look and its wait would
// show as a timed-out wait (and a stalled test), so every wait must be rung.
TEST(DoorbellStress, NoRingIsSleptThrough) {
  auto q = std::make_unique<SpscRing<std::uint64_t, 8>>();
  Doorbell bell;
  std::atomic<bool> done{false};
  constexpr std::uint64_t kItems = 200'000;
  std::thread producer([&] {
    Budget budget;
    std::uint64_t seq = 0;
    while (seq < kItems && !budget.exhausted(seq)) {
      if (q->try_push(seq)) {
        ++seq;
        bell.ring();
      } else {
        std::this_thread::yield();
      }
    }
    done.store(true, std::memory_order_release);
    bell.ring();
  });
  std::uint64_t expected = 0;
  std::uint64_t errors = 0;
  std::uint64_t timeouts = 0;
  for (;;) {
    while (std::uint64_t* v = q->front()) {
      if (*v != expected) ++errors;
      expected = *v + 1;
      q->pop();
    }
    if (done.load(std::memory_order_acquire) && q->empty()) break;
    const int64_t t0 = now_ns();
    if (!bell.wait_for_ns(10 * kNsPerS) && now_ns() - t0 >= 10 * kNsPerS) ++timeouts;
  }
  producer.join();
  EXPECT_EQ(errors, 0u);
  EXPECT_EQ(timeouts, 0u);
  EXPECT_GT(expected, 0u);
}

// Every field equals the publish counter; a reader must never see a mix.
template <std::size_t Words, class Word>
struct Uniform {
  using word_type = Word;
  std::array<Word, Words> f;
};

template <class T>
void mailbox_stress(int readers) {
  auto box = std::make_unique<Mailbox<T>>();
  std::atomic<bool> done{false};
  std::atomic<std::uint64_t> torn{0};
  std::atomic<std::uint64_t> backwards{0};
  std::atomic<std::uint64_t> reads{0};

  std::vector<std::thread> pool;
  for (int r = 0; r < readers; ++r) {
    pool.emplace_back([&] {
      std::uint64_t last_value = 0;
      std::uint64_t last_version = 0;
      std::uint64_t n = 0;
      T out{};
      while (!done.load(std::memory_order_acquire)) {
        std::uint64_t version = 0;
        if (!box->read(out, &version)) continue;
        ++n;
        const auto v0 = static_cast<std::uint64_t>(out.f[0]);
        for (const auto x : out.f) {
          if (static_cast<std::uint64_t>(x) != v0) {
            torn.fetch_add(1, std::memory_order_relaxed);
            break;
          }
        }
        if (v0 < last_value || version < last_version) backwards.fetch_add(1, std::memory_order_relaxed);
        // Value i was published as version i (the counter starts at 1).
        if (static_cast<std::uint64_t>(static_cast<typename T::word_type>(version)) != v0) {
          torn.fetch_add(1, std::memory_order_relaxed);
        }
        last_value = v0;
        last_version = version;
      }
      reads.fetch_add(n, std::memory_order_relaxed);
    });
  }

  Budget budget;
  std::uint64_t published = 0;
  T v{};
  while (published < 2'000'000 && !budget.exhausted(published)) {
    ++published;
    for (auto& x : v.f) x = static_cast<typename T::word_type>(published);
    box->publish(v);
  }
  done.store(true, std::memory_order_release);
  for (auto& t : pool) t.join();
  EXPECT_EQ(torn.load(), 0u) << "a reader saw a torn value";
  EXPECT_EQ(backwards.load(), 0u) << "a reader saw time go backwards";
  EXPECT_EQ(box->version(), published);
  EXPECT_GT(reads.load(), 0u);
}

TEST(MailboxStress, NoTornReadsLargeStruct) { mailbox_stress<Uniform<33, std::uint64_t>>(2); }
TEST(MailboxStress, NoTornReadsOddSizedStruct) { mailbox_stress<Uniform<5, std::uint32_t>>(1); }

// Producer acquires an image-sized buffer, stamps it, passes the handle
// through a ring; the consumer checks the stamp and releases it.
TEST(ObjectPoolStress, AcquireHereReleaseThere) {
  using Buffer = std::array<std::uint64_t, 512>;
  auto pool = std::make_unique<ObjectPool<Buffer, 8>>();
  auto ring = std::make_unique<SpscRing<PoolHandle, 16>>();
  std::atomic<bool> done{false};
  std::uint64_t sent = 0;
  std::uint64_t pool_empty = 0;

  std::thread producer([&] {
    Budget budget;
    while (sent < 1'000'000 && !budget.exhausted(sent)) {
      const PoolHandle h = pool->acquire();
      if (h == kInvalidHandle) {
        ++pool_empty;
        continue;
      }
      Buffer* b = pool->get(h);
      for (auto& w : *b) w = sent;
      while (!ring->try_push(h)) {
      }
      ++sent;
    }
    done.store(true, std::memory_order_release);
  });

  std::uint64_t received = 0;
  std::uint64_t errors = 0;
  for (;;) {
    PoolHandle h = kInvalidHandle;
    if (ring->try_pop(h)) {
      const Buffer* b = pool->get(h);
      if (b == nullptr) {
        ++errors;
        continue;
      }
      for (auto w : *b) errors += (w != received);
      ++received;
      if (!pool->release(h)) ++errors;
    } else if (done.load(std::memory_order_acquire) && ring->empty()) {
      break;
    }
  }
  producer.join();
  EXPECT_EQ(errors, 0u);
  EXPECT_EQ(received, sent);
  EXPECT_EQ(pool->in_use(), 0u);
  EXPECT_EQ(pool->failed_acquires(), pool_empty);
  EXPECT_EQ(pool->bad_releases(), 0u);
}

// Both threads acquire and release concurrently (the free list is shared):
// a slot must never be handed to two holders at once (ABA on the list head).
TEST(ObjectPoolStress, ConcurrentAcquireReleaseNeverSharesASlot) {
  auto pool = std::make_unique<ObjectPool<std::atomic<int>, 4>>();
  std::atomic<std::uint64_t> shared{0};
  std::atomic<std::uint64_t> ops{0};
  auto worker = [&](int id) {
    Budget budget;
    std::uint64_t i = 0;
    std::array<PoolHandle, 2> held{};
    while (i < 1'000'000 && !budget.exhausted(i)) {
      // Hold up to two objects at a time to churn the list order.
      for (auto& h : held) {
        h = pool->acquire();
        if (h == kInvalidHandle) continue;
        if (pool->get(h)->exchange(id, std::memory_order_relaxed) != 0) shared.fetch_add(1);
      }
      for (auto& h : held) {
        if (h == kInvalidHandle) continue;
        if (pool->get(h)->exchange(0, std::memory_order_relaxed) != id) shared.fetch_add(1);
        if (!pool->release(h)) shared.fetch_add(1);
      }
      ++i;
    }
    ops.fetch_add(i);
  };
  std::thread a(worker, 1);
  std::thread b(worker, 2);
  a.join();
  b.join();
  EXPECT_EQ(shared.load(), 0u);
  EXPECT_EQ(pool->in_use(), 0u);
  EXPECT_GT(ops.load(), 1000u);
  // All four come back out exactly once.
  std::array<PoolHandle, 4> all{};
  for (auto& h : all) {
    h = pool->acquire();
    EXPECT_NE(h, kInvalidHandle);
  }
  EXPECT_EQ(pool->acquire(), kInvalidHandle);
}

}  // namespace
}  // namespace kestrel::rt

// Linked with kestrel_alloc_hook (ALLOC_HOOK): the counter must see heap use,
// and the rt containers must show none on their steady-state paths.
#include <gtest/gtest.h>

#include <cstdint>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/rt/doorbell.hpp"
#include "kestrel/rt/fixed_vector.hpp"
#include "kestrel/rt/history_ring.hpp"
#include "kestrel/rt/latency_histogram.hpp"
#include "kestrel/rt/mailbox.hpp"
#include "kestrel/rt/object_pool.hpp"
#include "kestrel/rt/perf.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::rt {
namespace {

// Makes p observable so the compiler cannot elide the allocation.
void escape(void* p) { asm volatile("" : : "g"(p) : "memory"); }

TEST(AllocCounter, HookIsLinked) { EXPECT_TRUE(alloc_hook_linked()); }

TEST(AllocCounter, SeesAllocations) {
  const std::uint64_t total0 = alloc_count_total();
  AllocCountScope scope;
  {
    std::vector<int> v(1000);
    escape(v.data());
    auto p = std::make_unique<std::string>(200, 'a');
    escape(p.get());
    auto aligned = std::make_unique<SpscRing<int, 8>>();  // 64-byte aligned new
    escape(aligned.get());
    int* arr = new int[7];
    escape(arr);
    delete[] arr;
  }
  EXPECT_GE(scope.count(), 5u);
  EXPECT_GE(scope.bytes(), 1000u * sizeof(int) + 200u);
  EXPECT_GE(alloc_count_total() - total0, scope.count());
}

TEST(AllocCounter, ZeroWhenNothingAllocates) {
  AllocCountScope scope;
  int x = 0;
  for (int i = 0; i < 1000; ++i) x += i;
  escape(&x);
  EXPECT_EQ(scope.count(), 0u);
}

TEST(AllocCounter, CountsArePerThread) {
  AllocCountScope scope;
  std::uint64_t other = 0;
  std::thread t([&] {
    AllocCountScope s;
    std::vector<int> v(100);
    escape(v.data());
    other = s.count();
  });  // std::thread's own state is allocated by this thread: counted here.
  t.join();
  EXPECT_GE(other, 1u);
  const std::uint64_t mine = scope.count();
  EXPECT_LE(mine, 2u) << "only the std::thread bookkeeping, not the other thread's vector";
}

// The real-time paths of rt: steady-state operations allocate nothing.
TEST(AllocCounter, RtPathsDoNotAllocate) {
  auto ring = std::make_unique<SpscRing<std::int64_t, 64>>();
  auto history = std::make_unique<HistoryRing<std::int64_t, 32>>();
  auto vec = std::make_unique<FixedVector<std::int64_t, 16>>();
  auto mailbox = std::make_unique<Mailbox<std::int64_t>>();
  ObjectPool<std::vector<std::uint8_t>, 4> pool([](std::vector<std::uint8_t>& b) { b.resize(640 * 480); });
  auto hist = std::make_unique<LatencyHistogram>();
  PerfRegistry reg;
  PerfCounter* count = reg.register_counter("n", PerfKind::kCount);
  PerfCounter* elapsed = reg.register_counter("e", PerfKind::kElapsed);
  PerfCounter* interval = reg.register_counter("i", PerfKind::kInterval);
  Doorbell bell;

  AllocCountScope scope;
  for (std::int64_t i = 0; i < 1000; ++i) {
    if (!ring->try_push(i)) ring->note_drop();
    if (std::int64_t* f = ring->front(); f != nullptr && i % 2 == 0) ring->pop();
    history->push(i);
    if (!vec->push_back(i)) vec->clear();
    mailbox->publish(i);
    std::int64_t out = 0;
    escape(&out);
    (void)mailbox->read(out);
    const PoolHandle h = pool.acquire();
    if (auto* img = pool.get(h)) (*img)[0] = static_cast<std::uint8_t>(i);
    pool.release(h);
    hist->record(i * 100);
    count->inc();
    { ScopedTimer t(elapsed); }
    interval->tick();
    bell.ring();
    (void)bell.wait_for_ns(0);
  }
  EXPECT_EQ(scope.count(), 0u);
  EXPECT_GT(ring->drops(), 0u);
}

}  // namespace
}  // namespace kestrel::rt

#include <cstdlib>

// Eigen's dynamic matrices allocate with malloc: the hook must see it too
// (outside sanitizer builds, which own malloc).
TEST(AllocCounter, CountsMallocOutsideSanitizers) {
  if (!kestrel::rt::alloc_hook_counts_malloc()) GTEST_SKIP() << "sanitizer build: malloc not interposed";
  const kestrel::rt::AllocCountScope scope;
  void* volatile p = std::malloc(100);
  std::free(p);
  EXPECT_EQ(scope.count(), 1u);
  void* volatile q = std::calloc(4, 8);
  std::free(q);
  EXPECT_EQ(scope.count(), 2u);
}

TEST(AllocCounter, OperatorNewIsCountedOnceWithMallocInterposed) {
  const kestrel::rt::AllocCountScope scope;
  int* volatile p = new int(3);
  delete p;
  EXPECT_EQ(scope.count(), 1u);
}

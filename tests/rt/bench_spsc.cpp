// SPSC ring throughput and round-trip latency, ours vs boost::lockfree::spsc_queue
// (same capacity, same element, same pinning). rigtorp-style methodology:
//  - Throughput: the benchmark thread pushes batches of 1 Mi sequence numbers,
//    a consumer thread pops and checks them; an iteration ends when the
//    consumer has acknowledged the whole batch. items/s = end-to-end rate.
//  - RoundTrip: ping through ring 1 to an echo thread, pong back through
//    ring 2; time per iteration = one round trip.
//  - PushPopSameThread: 64 pushes then 64 pops on one thread (code-path cost).
// Threads are pinned to two different CPUs when the process may use two.
#include <benchmark/benchmark.h>
#include <sched.h>

#include <atomic>
#include <cstdint>
#include <memory>
#include <thread>

#include "kestrel/rt/spsc_ring.hpp"
#include "kestrel/rt/thread_setup.hpp"

#if KESTREL_HAVE_BOOST
#include <boost/lockfree/spsc_queue.hpp>
#endif

namespace {

using kestrel::rt::SpscRing;
using Item = std::int64_t;
constexpr std::size_t kCapacity = 4096;
constexpr std::int64_t kBatch = 1 << 20;
constexpr std::int64_t kAckEvery = 1024;  // consumer publishes progress this often
constexpr Item kStop = -1;

struct Ours {
  SpscRing<Item, kCapacity> q;
  bool push(Item v) { return q.try_push(v); }
  bool pop(Item& v) {
    Item* p = q.front();
    if (p == nullptr) return false;
    v = *p;
    q.pop();
    return true;
  }
};

#if KESTREL_HAVE_BOOST
struct Boost {
  boost::lockfree::spsc_queue<Item, boost::lockfree::capacity<kCapacity>> q;
  bool push(Item v) { return q.push(v); }
  bool pop(Item& v) { return q.pop(v); }
};
#endif

int cpu_for(int k) { return kestrel::rt::allowed_cpu_count() >= 2 ? kestrel::rt::nth_allowed_cpu(k) : -1; }

// Pins the calling thread for the benchmark's duration, then restores.
class ScopedPin {
 public:
  explicit ScopedPin(int cpu) {
    sched_getaffinity(0, sizeof old_, &old_);
    if (cpu >= 0) (void)kestrel::rt::apply_thread_spec({"bench-main", 0, cpu, 0});
  }
  ~ScopedPin() { sched_setaffinity(0, sizeof old_, &old_); }

 private:
  cpu_set_t old_{};
};

template <class Q>
void BM_Throughput(benchmark::State& state) {
  auto q = std::make_unique<Q>();
  alignas(64) std::atomic<std::int64_t> acked{0};
  std::atomic<std::int64_t> errors{0};
  std::thread consumer([&] {
    (void)kestrel::rt::apply_thread_spec({"bench-cons", 0, cpu_for(1), 0});
    std::int64_t expect = 0;
    std::int64_t bad = 0;
    for (;;) {
      Item v;
      if (!q->pop(v)) continue;
      if (v == kStop) break;
      bad += (v != expect);
      ++expect;
      if (expect % kAckEvery == 0) acked.store(expect, std::memory_order_release);
    }
    errors.store(bad);
  });
  ScopedPin pin(cpu_for(0));
  std::int64_t next = 0;
  for (auto _ : state) {
    const std::int64_t end = next + kBatch;
    while (next < end) {
      if (q->push(next)) ++next;
    }
    while (acked.load(std::memory_order_acquire) < end) {
    }
  }
  while (!q->push(kStop)) {
  }
  consumer.join();
  state.SetItemsProcessed(state.iterations() * kBatch);
  state.counters["errors"] = static_cast<double>(errors.load());
}

template <class Q>
void BM_RoundTrip(benchmark::State& state) {
  auto ping = std::make_unique<Q>();
  auto pong = std::make_unique<Q>();
  std::thread echo([&] {
    (void)kestrel::rt::apply_thread_spec({"bench-echo", 0, cpu_for(1), 0});
    for (;;) {
      Item v;
      while (!ping->pop(v)) {
      }
      if (v == kStop) break;
      while (!pong->push(v)) {
      }
    }
  });
  ScopedPin pin(cpu_for(0));
  Item seq = 0;
  std::int64_t errors = 0;
  for (auto _ : state) {
    while (!ping->push(seq)) {
    }
    Item back;
    while (!pong->pop(back)) {
    }
    errors += (back != seq);
    ++seq;
  }
  while (!ping->push(kStop)) {
  }
  echo.join();
  state.counters["errors"] = static_cast<double>(errors);
}

// One thread, push then pop: the instruction cost of the two paths without
// any cache-line transfer; stable even on a loaded machine.
template <class Q>
void BM_PushPopSameThread(benchmark::State& state) {
  auto q = std::make_unique<Q>();
  Item i = 0;
  Item sum = 0;
  for (auto _ : state) {
    for (int k = 0; k < 64; ++k) {
      if (!q->push(i++)) state.SkipWithError("push failed");
    }
    for (int k = 0; k < 64; ++k) {
      Item v = 0;
      if (!q->pop(v)) state.SkipWithError("pop failed");
      sum += v;
    }
  }
  benchmark::DoNotOptimize(sum);
  state.SetItemsProcessed(state.iterations() * 64);
}

BENCHMARK_TEMPLATE(BM_PushPopSameThread, Ours);
#if KESTREL_HAVE_BOOST
BENCHMARK_TEMPLATE(BM_PushPopSameThread, Boost);
#endif
BENCHMARK_TEMPLATE(BM_Throughput, Ours)->UseRealTime();
#if KESTREL_HAVE_BOOST
BENCHMARK_TEMPLATE(BM_Throughput, Boost)->UseRealTime();
#endif
BENCHMARK_TEMPLATE(BM_RoundTrip, Ours)->UseRealTime();
#if KESTREL_HAVE_BOOST
BENCHMARK_TEMPLATE(BM_RoundTrip, Boost)->UseRealTime();
#endif

}  // namespace

BENCHMARK_MAIN();

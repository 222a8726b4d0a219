#include <gtest/gtest.h>

#include <cstdio>
#include <memory>
#include <stdexcept>
#include <string>

#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/perf.hpp"

namespace kestrel::rt {
namespace {

TEST(Clock, MonotonicAndSleepsToDeadline) {
  const std::int64_t t0 = now_ns();
  EXPECT_GT(t0, 0);
  const std::int64_t deadline = t0 + 2 * kNsPerMs;
  sleep_until_ns(deadline);
  const std::int64_t t1 = now_ns();
  EXPECT_GE(t1, deadline) << "absolute sleep never returns early";
  sleep_until_ns(t0);  // past deadline: immediate
  EXPECT_GE(now_ns(), t1);
  EXPECT_GE(thread_cpu_time_ns(), 0);
  EXPECT_GE(process_cpu_time_ns(), thread_cpu_time_ns() / 2);
}

TEST(Clock, PeriodicDeadlineSkipsMissedPeriods) {
  PeriodicDeadline d(1000, 100);
  EXPECT_EQ(d.next(1000), 1100);
  EXPECT_EQ(d.next(1150), 1200);
  EXPECT_EQ(d.overruns(), 0u);
  // Woke at 1530: periods ending 1300, 1400, 1500 are gone.
  EXPECT_EQ(d.next(1530), 1600);
  EXPECT_EQ(d.overruns(), 3u);
}

TEST(Perf, CountElapsedInterval) {
  auto reg = std::make_unique<PerfRegistry>();
  PerfCounter* drops = reg->register_counter("cam.drops", PerfKind::kCount);
  PerfCounter* solve = reg->register_counter("opt.solve", PerfKind::kElapsed);
  PerfCounter* imu = reg->register_counter("imu.interval", PerfKind::kInterval);
  ASSERT_NE(drops, nullptr);
  EXPECT_EQ(reg->register_counter("cam.drops", PerfKind::kCount), drops) << "same name, same counter";
  EXPECT_EQ(reg->size(), 3u);

  drops->inc();
  drops->inc(4);
  EXPECT_EQ(drops->snapshot().count, 5u);

  // Synthetic samples far longer than the scoped one below (even under TSan).
  solve->add_elapsed(300 * kNsPerMs);
  solve->add_elapsed(100 * kNsPerMs);
  solve->stop();  // without start: ignored
  { ScopedTimer t(solve); }
  const auto s = solve->snapshot();
  EXPECT_EQ(s.count, 3u);
  EXPECT_EQ(s.max_ns, 300 * kNsPerMs);
  EXPECT_LT(s.min_ns, 100 * kNsPerMs) << "the scoped timer's own sample";
  EXPECT_GE(s.min_ns, 0);
  solve->start();
  solve->stop();
  EXPECT_EQ(solve->snapshot().count, 4u);

  imu->tick(1000);  // arms only
  imu->tick(1010);
  imu->tick(1030);
  const auto i = imu->snapshot();
  EXPECT_EQ(i.count, 2u);
  EXPECT_EQ(i.min_ns, 10);
  EXPECT_EQ(i.max_ns, 20);
  EXPECT_DOUBLE_EQ(i.mean_ns(), 15.0);

  const std::string text = reg->to_string();
  EXPECT_NE(text.find("cam.drops"), std::string::npos);
  EXPECT_NE(text.find("interval"), std::string::npos);
  std::FILE* f = std::tmpfile();
  ASSERT_NE(f, nullptr);
  reg->dump(f);
  EXPECT_EQ(std::ftell(f), static_cast<long>(text.size()));
  std::fclose(f);

  reg->reset_all();
  EXPECT_EQ(drops->snapshot().count, 0u);
  EXPECT_EQ(reg->find("opt.solve"), solve);
  EXPECT_EQ(reg->find("nope"), nullptr);
}

TEST(Perf, FullRegistryAndKindClashAreReportedNotFatal) {
  auto reg = std::make_unique<PerfRegistry>();
  PerfCounter* c = reg->register_counter("x", PerfKind::kCount);
  PerfCounter* clash = reg->register_counter("x", PerfKind::kElapsed);
  ASSERT_NE(clash, nullptr);
  EXPECT_NE(clash, c);
  EXPECT_EQ(reg->refused(), 1u);
  for (std::size_t k = 1; k < PerfRegistry::kCapacity; ++k) {
    const std::string name = "c" + std::to_string(k);
    ASSERT_NE(reg->register_counter(name.c_str(), PerfKind::kCount), nullptr);
  }
  EXPECT_EQ(reg->size(), PerfRegistry::kCapacity);
  PerfCounter* over = reg->register_counter("one.too.many", PerfKind::kCount);
  ASSERT_NE(over, nullptr);
  over->inc();  // usable, just not listed
  EXPECT_EQ(reg->refused(), 2u);
  EXPECT_NE(reg->to_string().find("2 registrations refused"), std::string::npos);
}

TEST(Perf, LongNamesAreCut) {
  PerfRegistry reg;
  const std::string longname(100, 'n');
  PerfCounter* c = reg.register_counter(longname.c_str(), PerfKind::kCount);
  EXPECT_EQ(std::string(c->name()).size(), PerfCounter::kMaxName);
  EXPECT_EQ(&perf_registry(), &perf_registry());
}

// values() outlives the registry, keeps registration order, and a path that
// was never registered is an error rather than a silent zero.
TEST(Perf, ValuesCopyEveryCounterByPath) {
  PerfValues v;
  {
    auto reg = std::make_unique<PerfRegistry>();
    PerfCounter* drops = reg->register_counter("rings.imu_drops", PerfKind::kCount);
    PerfCounter* solve = reg->register_counter("window.solve", PerfKind::kElapsed);
    drops->inc(3);
    drops->set(7);  // a mirror of a count kept elsewhere
    solve->add_elapsed(2'000);
    solve->add_elapsed(4'000);
    v = reg->values();
  }
  ASSERT_EQ(v.all().size(), 2u);
  EXPECT_EQ(v.all()[0].name, "rings.imu_drops");
  EXPECT_EQ(v.count("rings.imu_drops"), 7u);
  const PerfValue* s = v.find("window.solve");
  ASSERT_NE(s, nullptr);
  EXPECT_EQ(s->kind, PerfKind::kElapsed);
  EXPECT_EQ(s->count, 2u);
  EXPECT_EQ(s->total_ns, 6'000);
  EXPECT_EQ(s->min_ns, 2'000);
  EXPECT_EQ(s->max_ns, 4'000);
  EXPECT_EQ(v.find("rings.frame_drops"), nullptr);
  try {
    (void)v.count("rings.frame_drops");
    ADD_FAILURE() << "count() of an unknown path did not throw";
  } catch (const std::out_of_range& e) {
    EXPECT_NE(std::string(e.what()).find("rings.frame_drops"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace kestrel::rt

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <random>
#include <vector>

#include "kestrel/rt/latency_histogram.hpp"

namespace kestrel::rt {
namespace {

// Reference: the smallest sample such that at least p% are <= it.
std::int64_t reference_percentile(const std::vector<std::int64_t>& sorted, double p) {
  if (p <= 0.0) return sorted.front();
  std::size_t rank = static_cast<std::size_t>(std::ceil(p / 100.0 * static_cast<double>(sorted.size())));
  rank = std::clamp<std::size_t>(rank, 1, sorted.size());
  return sorted[rank - 1];
}

TEST(LatencyHistogram, BinLayoutCoversEveryValueOnce) {
  std::mt19937_64 rng(7);
  for (int i = 0; i < 200000; ++i) {
    const std::int64_t v =
        static_cast<std::int64_t>(rng() % (LatencyHistogram::kMaxTrackable + 1)) >> (rng() % 36);
    const std::size_t b = LatencyHistogram::bin_index(v);
    ASSERT_LT(b, LatencyHistogram::kBins);
    ASSERT_LE(LatencyHistogram::bin_lower(b), v);
    ASSERT_LT(v, LatencyHistogram::bin_lower(b) + LatencyHistogram::bin_width(b));
    // Relative resolution <= 1/128 of the value: the HDR bound.
    ASSERT_LE(LatencyHistogram::bin_width(b) * 128, std::max<std::int64_t>(v, 128));
  }
  // Consecutive bins tile the range without gaps.
  for (std::size_t b = 0; b + 1 < LatencyHistogram::kBins; ++b) {
    ASSERT_EQ(LatencyHistogram::bin_lower(b) + LatencyHistogram::bin_width(b),
              LatencyHistogram::bin_lower(b + 1));
  }
}

TEST(LatencyHistogram, PercentilesMatchSortedReference) {
  // Log-uniform latencies from 200 ns to 2 s, plus a cluster, fixed seed.
  std::mt19937_64 rng(12345);
  std::uniform_real_distribution<double> log_ns(std::log(200.0), std::log(2e9));
  std::normal_distribution<double> cluster(50'000.0, 3'000.0);
  auto h = std::make_unique<LatencyHistogram>();
  std::vector<std::int64_t> ref;
  for (int i = 0; i < 100000; ++i) {
    const double x = (i % 4 == 0) ? cluster(rng) : std::exp(log_ns(rng));
    const auto ns = static_cast<std::int64_t>(std::max(1.0, x));
    h->record(ns);
    ref.push_back(ns);
  }
  std::sort(ref.begin(), ref.end());
  EXPECT_EQ(h->count(), ref.size());
  EXPECT_EQ(h->min(), ref.front());
  EXPECT_EQ(h->max(), ref.back());
  double sum = 0;
  for (auto v : ref) sum += static_cast<double>(v);
  EXPECT_NEAR(h->mean(), sum / static_cast<double>(ref.size()), 1e-6 * h->mean());
  for (double p : {0.0, 0.1, 1.0, 10.0, 25.0, 50.0, 75.0, 90.0, 99.0, 99.9, 99.99, 100.0}) {
    const double want = static_cast<double>(reference_percentile(ref, p));
    const double got = static_cast<double>(h->percentile(p));
    EXPECT_LE(std::abs(got - want), 0.01 * want + 1.0) << "p" << p << " want " << want << " got " << got;
  }
  EXPECT_EQ(h->p50(), h->percentile(50));
  EXPECT_EQ(h->p99(), h->percentile(99));
}

TEST(LatencyHistogram, MergeEqualsRecordingEverything) {
  std::mt19937_64 rng(99);
  auto a = std::make_unique<LatencyHistogram>();
  auto b = std::make_unique<LatencyHistogram>();
  auto all = std::make_unique<LatencyHistogram>();
  for (int i = 0; i < 20000; ++i) {
    const auto v = static_cast<std::int64_t>(rng() % 10'000'000);
    (i % 3 == 0 ? *a : *b).record(v);
    all->record(v);
  }
  a->merge(*b);
  EXPECT_EQ(a->count(), all->count());
  EXPECT_EQ(a->min(), all->min());
  EXPECT_EQ(a->max(), all->max());
  EXPECT_DOUBLE_EQ(a->mean(), all->mean());
  for (double p : {1.0, 50.0, 90.0, 99.0}) EXPECT_EQ(a->percentile(p), all->percentile(p));
  const LatencyHistogram copy = *a;
  EXPECT_EQ(copy.p90(), a->p90());
  a->reset();
  EXPECT_EQ(a->count(), 0u);
  EXPECT_EQ(a->p50(), 0);
}

TEST(LatencyHistogram, OutOfRangeValues) {
  LatencyHistogram h;
  h.record(-5);
  h.record(LatencyHistogram::kMaxTrackable + 1000);
  EXPECT_EQ(h.negatives(), 1u);
  EXPECT_EQ(h.overflows(), 1u);
  EXPECT_EQ(h.min(), 0);
  EXPECT_EQ(h.max(), LatencyHistogram::kMaxTrackable + 1000) << "max stays exact";
  EXPECT_EQ(h.percentile(100), h.max());
}

}  // namespace
}  // namespace kestrel::rt

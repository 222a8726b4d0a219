// Fixed-bin latency histogram, log-linear like HdrHistogram: values below
// 128 ns get one bin each; above, every power-of-two range [2^e, 2^(e+1)) is
// split into 128 equal bins. A bin's midpoint is within 1/256 (0.4%) of any
// value in it, so percentiles carry <= 0.4% relative error from 0 ns up to
// 2^36 ns (68.7 s); larger values land in the top bin (counted in overflows(),
// while max() stays exact).
//
// record() is O(1), allocation-free and lock-free. Thread contract: ONE thread
// records; any thread may read (percentile, mean, merge from) concurrently and
// gets a slightly inconsistent but race-free view (relaxed atomic bins with
// single-writer load+store updates). merge()/reset() on a histogram belong to
// its recording thread (or a quiescent one).
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>

namespace kestrel::rt {

class LatencyHistogram {
 public:
  static constexpr int kSubBits = 7;  // 128 sub-bins per octave
  static constexpr int kMaxExp = 35;  // top octave [2^35, 2^36)
  static constexpr std::int64_t kSub = std::int64_t{1} << kSubBits;
  static constexpr std::size_t kBins = static_cast<std::size_t>(kSub) * (kMaxExp - kSubBits + 2);
  static constexpr std::int64_t kMaxTrackable = (std::int64_t{1} << (kMaxExp + 1)) - 1;

  // reset() and copy_from() store every bin: an initialiser would write the 3840 atomics twice.
  // NOLINTNEXTLINE(cppcoreguidelines-pro-type-member-init)
  LatencyHistogram() noexcept { reset(); }
  // NOLINTNEXTLINE(cppcoreguidelines-pro-type-member-init)
  LatencyHistogram(const LatencyHistogram& o) noexcept { copy_from(o); }
  LatencyHistogram& operator=(const LatencyHistogram& o) noexcept {
    if (this != &o) copy_from(o);
    return *this;
  }

  void record(std::int64_t ns) noexcept {
    if (ns < 0) {
      bump(negatives_, 1);
      ns = 0;
    }
    if (ns > kMaxTrackable) bump(overflows_, 1);
    bump(bins_[bin_index(ns)], 1);
    const std::uint64_t c = count_.load(std::memory_order_relaxed);
    if (c == 0 || ns < min_.load(std::memory_order_relaxed)) min_.store(ns, std::memory_order_relaxed);
    if (c == 0 || ns > max_.load(std::memory_order_relaxed)) max_.store(ns, std::memory_order_relaxed);
    sum_.store(sum_.load(std::memory_order_relaxed) + ns, std::memory_order_relaxed);
    count_.store(c + 1, std::memory_order_relaxed);
  }

  // p in percent, [0, 100]: the smallest recorded value (to bin resolution)
  // such that at least p% of the samples are <= it. 0 when empty.
  [[nodiscard]] std::int64_t percentile(double p) const noexcept {
    const std::uint64_t n = count();
    if (n == 0) return 0;
    if (p <= 0.0) return min();
    if (p >= 100.0) return max();
    double r = p / 100.0 * static_cast<double>(n);
    std::uint64_t rank = static_cast<std::uint64_t>(r);
    if (static_cast<double>(rank) < r) ++rank;  // ceil
    if (rank < 1) rank = 1;
    std::uint64_t seen = 0;
    for (std::size_t i = 0; i < kBins; ++i) {
      seen += bins_[i].load(std::memory_order_relaxed);
      if (seen >= rank) return clamp(bin_mid(i));
    }
    return max();
  }

  [[nodiscard]] std::int64_t p50() const noexcept { return percentile(50.0); }
  [[nodiscard]] std::int64_t p90() const noexcept { return percentile(90.0); }
  [[nodiscard]] std::int64_t p99() const noexcept { return percentile(99.0); }
  [[nodiscard]] std::int64_t p999() const noexcept { return percentile(99.9); }
  [[nodiscard]] std::int64_t min() const noexcept { return min_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::int64_t max() const noexcept { return max_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t count() const noexcept { return count_.load(std::memory_order_relaxed); }
  [[nodiscard]] double mean() const noexcept {
    const std::uint64_t n = count();
    return n > 0 ? static_cast<double>(sum_.load(std::memory_order_relaxed)) / static_cast<double>(n) : 0.0;
  }
  [[nodiscard]] std::uint64_t overflows() const noexcept {
    return overflows_.load(std::memory_order_relaxed);
  }
  [[nodiscard]] std::uint64_t negatives() const noexcept {
    return negatives_.load(std::memory_order_relaxed);
  }

  void merge(const LatencyHistogram& o) noexcept {
    const std::uint64_t on = o.count();
    if (on == 0) return;
    for (std::size_t i = 0; i < kBins; ++i) bump(bins_[i], o.bins_[i].load(std::memory_order_relaxed));
    const std::uint64_t c = count();
    if (c == 0 || o.min() < min()) min_.store(o.min(), std::memory_order_relaxed);
    if (c == 0 || o.max() > max()) max_.store(o.max(), std::memory_order_relaxed);
    bump(sum_, o.sum_.load(std::memory_order_relaxed));
    bump(overflows_, o.overflows());
    bump(negatives_, o.negatives());
    count_.store(c + on, std::memory_order_relaxed);
  }

  void reset() noexcept {
    for (auto& b : bins_) b.store(0, std::memory_order_relaxed);
    count_.store(0, std::memory_order_relaxed);
    sum_.store(0, std::memory_order_relaxed);
    min_.store(0, std::memory_order_relaxed);
    max_.store(0, std::memory_order_relaxed);
    overflows_.store(0, std::memory_order_relaxed);
    negatives_.store(0, std::memory_order_relaxed);
  }

  // Bin layout, public for tests and for tools that export the histogram.
  static std::size_t bin_index(std::int64_t ns) noexcept {
    if (ns < kSub) return static_cast<std::size_t>(ns);
    if (ns > kMaxTrackable) return kBins - 1;
    const auto v = static_cast<std::uint64_t>(ns);
    const int e = 63 - __builtin_clzll(v);  // v >= 128, so e >= kSubBits
    const std::uint64_t sub = (v >> (e - kSubBits)) - static_cast<std::uint64_t>(kSub);
    return static_cast<std::size_t>(kSub) * static_cast<std::size_t>(e - kSubBits + 1) +
           static_cast<std::size_t>(sub);
  }
  static std::int64_t bin_lower(std::size_t i) noexcept {
    if (i < static_cast<std::size_t>(kSub)) return static_cast<std::int64_t>(i);
    const int e = static_cast<int>(i / static_cast<std::size_t>(kSub)) - 1 + kSubBits;
    const auto sub = static_cast<std::int64_t>(i % static_cast<std::size_t>(kSub));
    return (kSub + sub) << (e - kSubBits);
  }
  static std::int64_t bin_width(std::size_t i) noexcept {
    if (i < static_cast<std::size_t>(kSub)) return 1;
    return std::int64_t{1} << (static_cast<int>(i / static_cast<std::size_t>(kSub)) - 1);
  }
  static std::int64_t bin_mid(std::size_t i) noexcept { return bin_lower(i) + (bin_width(i) - 1) / 2; }
  // Samples in bin i (i < kBins): for tools that export the whole distribution.
  [[nodiscard]] std::uint64_t bin_count(std::size_t i) const noexcept {
    return bins_[i].load(std::memory_order_relaxed);
  }

 private:
  template <class A, class V>
  static void bump(A& a, V n) noexcept {
    a.store(a.load(std::memory_order_relaxed) + n, std::memory_order_relaxed);
  }
  std::int64_t clamp(std::int64_t v) const noexcept {
    const std::int64_t lo = min();
    const std::int64_t hi = max();
    return v < lo ? lo : v > hi ? hi : v;
  }
  void copy_from(const LatencyHistogram& o) noexcept {
    for (std::size_t i = 0; i < kBins; ++i)
      bins_[i].store(o.bins_[i].load(std::memory_order_relaxed), std::memory_order_relaxed);
    count_.store(o.count(), std::memory_order_relaxed);
    sum_.store(o.sum_.load(std::memory_order_relaxed), std::memory_order_relaxed);
    min_.store(o.min(), std::memory_order_relaxed);
    max_.store(o.max(), std::memory_order_relaxed);
    overflows_.store(o.overflows(), std::memory_order_relaxed);
    negatives_.store(o.negatives(), std::memory_order_relaxed);
  }

  std::atomic<std::uint64_t> count_{0};
  std::atomic<std::int64_t> sum_{0};
  std::atomic<std::int64_t> min_{0};
  std::atomic<std::int64_t> max_{0};
  std::atomic<std::uint64_t> overflows_{0};
  std::atomic<std::uint64_t> negatives_{0};
  std::atomic<std::uint64_t> bins_[kBins];
};

}  // namespace kestrel::rt

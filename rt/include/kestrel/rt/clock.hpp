// The one clock: int64 nanoseconds on CLOCK_MONOTONIC (docs/timing.md).
// Sensor drivers stamp with now_ns(); periodic threads sleep to absolute
// deadlines so a late wake-up does not shift every later period.
#pragma once

#include <cstdint>

namespace kestrel::rt {

inline constexpr std::int64_t kNsPerUs = 1'000;
inline constexpr std::int64_t kNsPerMs = 1'000'000;
inline constexpr std::int64_t kNsPerS = 1'000'000'000;

// CLOCK_MONOTONIC, in ns. Not affected by wall-clock steps; starts at boot.
[[nodiscard]] std::int64_t now_ns() noexcept;

// Sleeps until now_ns() >= t_ns (clock_nanosleep, TIMER_ABSTIME); restarts
// after signals. Returns immediately for a deadline in the past.
void sleep_until_ns(std::int64_t t_ns) noexcept;

// Relative sleep, for tools and tests; periodic loops use sleep_until_ns.
void sleep_for_ns(std::int64_t dt_ns) noexcept;

// CPU time consumed by the calling thread (CLOCK_THREAD_CPUTIME_ID), in ns:
// compared with wall time it tells "slow" from "preempted".
[[nodiscard]] std::int64_t thread_cpu_time_ns() noexcept;

// CPU time consumed by the whole process (CLOCK_PROCESS_CPUTIME_ID), in ns.
[[nodiscard]] std::int64_t process_cpu_time_ns() noexcept;

// Absolute deadlines for a periodic loop: next() advances by one period and
// skips whole periods already missed (counted), so an overrun is reported
// instead of followed by a burst of catch-up iterations.
class PeriodicDeadline {
 public:
  PeriodicDeadline(std::int64_t start_ns, std::int64_t period_ns) noexcept
      : next_ns_(start_ns), period_ns_(period_ns > 0 ? period_ns : 1) {}

  // The deadline to sleep until for the coming iteration.
  [[nodiscard]] std::int64_t next(std::int64_t now) noexcept {
    next_ns_ += period_ns_;
    if (next_ns_ <= now) {
      const std::int64_t missed = (now - next_ns_) / period_ns_ + 1;
      overruns_ += static_cast<std::uint64_t>(missed);
      next_ns_ += missed * period_ns_;
    }
    return next_ns_;
  }
  [[nodiscard]] std::uint64_t overruns() const noexcept { return overruns_; }
  [[nodiscard]] std::int64_t period_ns() const noexcept { return period_ns_; }

 private:
  std::int64_t next_ns_;
  std::int64_t period_ns_;
  std::uint64_t overruns_ = 0;
};

}  // namespace kestrel::rt

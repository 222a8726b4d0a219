// A wake-up for one waiting thread: producers ring() after they hand something
// over (a ring push, a job), the consumer sleeps in wait_for_ns() until rung.
//
// Why not a condition variable: ring() runs on real-time threads, which take no
// lock. Why not a 100 us sleep loop: an idle pipeline would then wake 10 000
// times a second per thread, and a busy-yield burns a whole core (issue 45
// measured 35.7 CPU-s for 5.5 s of estimator work).
//
// A Linux futex on one word. ring() is one atomic exchange, plus a futex wake
// syscall only when the consumer is actually asleep; it never blocks and never
// allocates. A ring that arrives between the consumer's last look at its input
// and its wait is kept (the word says "rung"), so the wait returns at once and
// no hand-off is slept through. Spurious returns are allowed: the consumer
// always re-checks its input.
//
// Thread contract: ring() from any number of threads; wait_for_ns() from ONE
// consumer thread.
#pragma once

#include <atomic>
#include <cstdint>

namespace kestrel::rt {

class Doorbell {
 public:
  Doorbell() = default;
  Doorbell(const Doorbell&) = delete;
  Doorbell& operator=(const Doorbell&) = delete;

  // Wait-free for the caller apart from the wake syscall when a sleeper exists.
  void ring() noexcept;

  // Returns when rung since the previous wait returned, at once if that ring
  // came before this call, or after timeout_ns (a bound, so a consumer that
  // also watches a flag, e.g. "the source has finished", sees it in time).
  // Returns true when rung, false on timeout or spurious wake.
  bool wait_for_ns(int64_t timeout_ns) noexcept;

  // How often wait_for_ns() actually went to sleep (diagnostics: an idle
  // consumer's sleeps per second are its wake-up cost).
  std::uint64_t sleeps() const noexcept { return sleeps_.load(std::memory_order_relaxed); }

 private:
  static constexpr std::uint32_t kIdle = 0;
  static constexpr std::uint32_t kRung = 1;
  static constexpr std::uint32_t kSleeping = 2;
  std::atomic<std::uint32_t> state_{kIdle};
  std::atomic<std::uint64_t> sleeps_{0};
};

}  // namespace kestrel::rt

#include "kestrel/rt/doorbell.hpp"

#include <linux/futex.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include <climits>

namespace kestrel::rt {
namespace {

static_assert(sizeof(std::atomic<std::uint32_t>) == sizeof(std::uint32_t),
              "the futex word must be the atomic's own storage");

// Private futexes: the bell lives in one process, and the kernel can then skip
// the shared-mapping lookup.
void futex_wake(std::atomic<std::uint32_t>* word) noexcept {
  syscall(SYS_futex, reinterpret_cast<std::uint32_t*>(word), FUTEX_WAKE_PRIVATE, INT_MAX, nullptr, nullptr,
          0);
}

void futex_wait(std::atomic<std::uint32_t>* word, std::uint32_t expected, int64_t timeout_ns) noexcept {
  timespec rel{};
  rel.tv_sec = static_cast<time_t>(timeout_ns / 1'000'000'000);
  rel.tv_nsec = static_cast<long>(timeout_ns % 1'000'000'000);
  // EAGAIN (the word already moved on), EINTR and ETIMEDOUT all mean "look again".
  syscall(SYS_futex, reinterpret_cast<std::uint32_t*>(word), FUTEX_WAIT_PRIVATE, expected, &rel, nullptr, 0);
}

}  // namespace

void Doorbell::ring() noexcept {
  if (state_.exchange(kRung, std::memory_order_acq_rel) == kSleeping) futex_wake(&state_);
}

bool Doorbell::wait_for_ns(int64_t timeout_ns) noexcept {
  std::uint32_t expected = kIdle;
  if (!state_.compare_exchange_strong(expected, kSleeping, std::memory_order_acq_rel)) {
    // Rung since the last wait: take the ring and return without sleeping.
    state_.store(kIdle, std::memory_order_release);
    return true;
  }
  if (timeout_ns > 0) {
    sleeps_.fetch_add(1, std::memory_order_relaxed);
    futex_wait(&state_, kSleeping, timeout_ns);
  }
  return state_.exchange(kIdle, std::memory_order_acq_rel) == kRung;
}

}  // namespace kestrel::rt

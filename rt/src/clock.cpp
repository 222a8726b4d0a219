#include "kestrel/rt/clock.hpp"

#include <cerrno>
#include <ctime>

namespace kestrel::rt {
namespace {

std::int64_t read_clock(clockid_t id) noexcept {
  timespec ts{};
  clock_gettime(id, &ts);  // cannot fail for these clock ids
  return static_cast<std::int64_t>(ts.tv_sec) * kNsPerS + ts.tv_nsec;
}

timespec to_timespec(std::int64_t t_ns) noexcept {
  timespec ts{};
  ts.tv_sec = static_cast<time_t>(t_ns / kNsPerS);
  ts.tv_nsec = static_cast<long>(t_ns % kNsPerS);
  return ts;
}

}  // namespace

std::int64_t now_ns() noexcept { return read_clock(CLOCK_MONOTONIC); }
std::int64_t thread_cpu_time_ns() noexcept { return read_clock(CLOCK_THREAD_CPUTIME_ID); }
std::int64_t process_cpu_time_ns() noexcept { return read_clock(CLOCK_PROCESS_CPUTIME_ID); }

void sleep_until_ns(std::int64_t t_ns) noexcept {
  if (t_ns <= 0) return;
  const timespec ts = to_timespec(t_ns);
  // clock_nanosleep returns the error number (it does not set errno).
  while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
  }
}

void sleep_for_ns(std::int64_t dt_ns) noexcept {
  if (dt_ns <= 0) return;
  sleep_until_ns(now_ns() + dt_ns);
}

}  // namespace kestrel::rt

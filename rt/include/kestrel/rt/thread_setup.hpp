// Process and thread set-up for real-time operation, with explicit fallback.
//
// Every thread of the pipeline is declared once as a ThreadSpec in one table
// (docs/threads.md). setup_process() locks memory and prefaults the stack;
// start_thread()/apply_thread_spec() name, schedule and pin a thread. Nothing
// here is fatal: without CAP_IPC_LOCK / CAP_SYS_NICE / RLIMIT_RTPRIO the
// program still runs (SCHED_OTHER, unlocked memory) and the reports say what
// was refused and why, so a log shows whether a run had real-time guarantees.
#pragma once

#include <pthread.h>

#include <cstddef>
#include <cstdint>
#include <future>
#include <string>
#include <thread>
#include <type_traits>
#include <utility>

namespace kestrel::rt {

struct ThreadSpec {
  const char* name;        // <= 15 chars shown by top/ps (longer names are cut)
  int priority;            // SCHED_FIFO priority 1..99; 0 = SCHED_OTHER
  int cpu;                 // CPU to pin to; -1 = any
  std::int64_t period_ns;  // nominal period, 0 = event driven (documentation / monitoring)
};

struct ProcessSetupOptions {
  bool lock_memory = true;               // mlockall(MCL_CURRENT | MCL_FUTURE)
  std::size_t prefault_stack_kib = 256;  // touched on the calling thread's stack
  bool keep_heap = true;  // glibc: no heap trimming, no mmap'd chunks (freed memory stays locked)
};

struct ProcessSetupReport {
  bool lock_memory_requested = false;
  bool memory_locked = false;
  int lock_errno = 0;          // errno of a refused mlockall, 0 otherwise
  const char* lock_note = "";  // why it was refused or skipped
  std::size_t stack_prefaulted_kib = 0;
  bool heap_tuned = false;  // mallopt calls accepted
  // What the system allows, for the log (RLIM_INFINITY printed as "unlimited").
  std::uint64_t rlimit_memlock_bytes = 0;
  std::uint64_t rlimit_rtprio = 0;
  bool cap_ipc_lock = false;  // effective capabilities from /proc/self/status
  bool cap_sys_nice = false;
  bool sanitizer_build = false;
};

// Never fails; read the report. Call once at start-up, before spawning threads.
ProcessSetupReport setup_process(const ProcessSetupOptions& opts = {});

// Undoes the memory lock (tests, tools that set up and tear down).
void release_process_memory_lock() noexcept;

struct ThreadSetupReport {
  const char* name = "";
  bool name_set = false;
  int requested_priority = 0;
  int granted_policy = 0;  // SCHED_OTHER / SCHED_FIFO actually in effect
  int granted_priority = 0;
  int sched_errno = 0;  // errno of a refused SCHED_FIFO, 0 otherwise
  const char* sched_note = "";
  int requested_cpu = -1;
  bool pinned = false;
  int affinity_errno = 0;
  const char* affinity_note = "";
  // True when everything requested was granted.
  [[nodiscard]] bool fully_granted() const noexcept {
    return name_set && granted_priority == requested_priority && (requested_cpu < 0 || pinned);
  }
};

// Applies spec to the calling thread: name, SCHED_FIFO (falls back to
// SCHED_OTHER with the reason), CPU pinning. Never fails.
ThreadSetupReport apply_thread_spec(const ThreadSpec& spec) noexcept;

// Starts a std::thread that applies spec, then runs fn(). Returns once the
// spec is applied, so *report (if given) is filled when this returns.
template <class Fn>
std::thread start_thread(const ThreadSpec& spec, Fn&& fn, ThreadSetupReport* report = nullptr) {
  std::promise<ThreadSetupReport> applied;
  std::future<ThreadSetupReport> done = applied.get_future();
  // The promise moves into the thread so the shared state outlives set_value.
  std::thread t([spec, p = std::move(applied), f = std::forward<Fn>(fn)]() mutable {
    p.set_value(apply_thread_spec(spec));
    f();
  });
  ThreadSetupReport r = done.get();
  if (report != nullptr) *report = r;
  return t;
}

// The pthread path for threads whose scheduling must be in force from their
// first instruction: PTHREAD_EXPLICIT_SCHED + SCHED_FIFO (priority > 0) and
// the CPU set go in the attributes. If pthread_create refuses with EPERM the
// thread is created again with inherited SCHED_OTHER and the reason reported.
// Returns pthread_create's error (0 on success); *report is always filled.
int create_pthread(const ThreadSpec& spec, void* (*fn)(void*), void* arg, pthread_t* out,
                   ThreadSetupReport* report) noexcept;

// Reads back the calling thread's policy, priority, affinity into a report
// (for tests and for logging what a thread really runs with).
ThreadSetupReport query_thread(pthread_t thread, const ThreadSpec& spec) noexcept;

// Number of CPUs this process may run on (sched_getaffinity), >= 1.
int allowed_cpu_count() noexcept;
// The k-th CPU this process may run on, or -1.
int nth_allowed_cpu(int k) noexcept;

const char* policy_name(int policy) noexcept;
std::string to_string(const ProcessSetupReport& r);
std::string to_string(const ThreadSetupReport& r);

}  // namespace kestrel::rt

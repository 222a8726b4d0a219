#include "kestrel/rt/thread_setup.hpp"

#include <malloc.h>
#include <sched.h>
#include <sys/mman.h>
#include <sys/resource.h>

#include <cerrno>
#include <cinttypes>
#include <cstdio>
#include <cstring>

#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
#define KESTREL_RT_SANITIZED 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer) || __has_feature(thread_sanitizer) || __has_feature(memory_sanitizer)
#define KESTREL_RT_SANITIZED 1
#endif
#endif
#ifndef KESTREL_RT_SANITIZED
#define KESTREL_RT_SANITIZED 0
#endif

namespace kestrel::rt {
namespace {

constexpr std::size_t kStackChunk = 16 * 1024;
constexpr std::size_t kPage = 4096;

// Touches kib KiB of stack below the caller, chunk by chunk, so the pages are
// mapped (and locked, after mlockall) before the real-time loop needs them.
// Recursion keeps each frame small; the addition after the call stops the
// compiler from turning it into a loop that reuses one frame.
__attribute__((noinline)) std::size_t touch_stack(std::size_t kib) noexcept {
  volatile unsigned char buf[kStackChunk];
  for (std::size_t i = 0; i < kStackChunk; i += kPage) buf[i] = 0;
  std::size_t done = kStackChunk / 1024;
  if (kib > done) done += touch_stack(kib - done);
  return done + (buf[0] & 0u);
}

std::uint64_t rlimit_value(int resource) noexcept {
  rlimit rl{};
  if (getrlimit(resource, &rl) != 0) return 0;
  return rl.rlim_cur == RLIM_INFINITY ? UINT64_MAX : static_cast<std::uint64_t>(rl.rlim_cur);
}

// Effective capability bits from /proc (no libcap dependency); 0 if unreadable.
std::uint64_t effective_caps() noexcept {
  std::FILE* f = std::fopen("/proc/self/status", "r");
  if (f == nullptr) return 0;
  char line[256];
  unsigned long long caps = 0;
  while (std::fgets(line, sizeof line, f) != nullptr) {
    if (std::sscanf(line, "CapEff: %llx", &caps) == 1) break;
  }
  std::fclose(f);
  return caps;
}

constexpr int kCapIpcLock = 14;
constexpr int kCapSysNice = 23;

std::string limit_text(std::uint64_t v, bool bytes) {
  if (v == UINT64_MAX) return "unlimited";
  char buf[48];
  if (bytes) {
    std::snprintf(buf, sizeof buf, "%" PRIu64 " KiB", v / 1024);
  } else {
    std::snprintf(buf, sizeof buf, "%" PRIu64, v);
  }
  return buf;
}

bool cpu_allowed(pthread_t thread, int cpu) noexcept {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (pthread_getaffinity_np(thread, sizeof set, &set) != 0) return false;
  return CPU_ISSET(cpu, &set);
}

const char* sched_refusal_note(int e) noexcept {
  if (e == EPERM)
    return "SCHED_FIFO refused (EPERM: needs CAP_SYS_NICE or RLIMIT_RTPRIO >= priority); running SCHED_OTHER";
  if (e == EINVAL) return "SCHED_FIFO refused (EINVAL: priority out of range); running SCHED_OTHER";
  return "SCHED_FIFO refused; running SCHED_OTHER";
}

void set_name(pthread_t thread, const char* name, ThreadSetupReport& r) noexcept {
  r.name = name != nullptr ? name : "";
  char buf[16];  // the kernel keeps 15 chars + NUL
  std::snprintf(buf, sizeof buf, "%s", r.name);
  r.name_set = pthread_setname_np(thread, buf) == 0;
}

}  // namespace

ProcessSetupReport setup_process(const ProcessSetupOptions& opts) {
  ProcessSetupReport r;
  r.rlimit_memlock_bytes = rlimit_value(RLIMIT_MEMLOCK);
  r.rlimit_rtprio = rlimit_value(RLIMIT_RTPRIO);
  const std::uint64_t caps = effective_caps();
  r.cap_ipc_lock = (caps >> kCapIpcLock) & 1u;
  r.cap_sys_nice = (caps >> kCapSysNice) & 1u;
  r.sanitizer_build = KESTREL_RT_SANITIZED != 0;
  r.lock_memory_requested = opts.lock_memory;

  if (!opts.lock_memory) {
    r.lock_note = "not requested";
  } else if (r.sanitizer_build) {
    // The sanitizers reserve terabytes of shadow memory; locking it would
    // exhaust RAM when the privilege is there and fail noisily when not.
    r.lock_note = "skipped: sanitizer build (mlockall would pin the shadow memory)";
  } else if (mlockall(MCL_CURRENT | MCL_FUTURE) == 0) {
    r.memory_locked = true;
    r.lock_note = "granted";
  } else {
    r.lock_errno = errno;
    r.lock_note = r.lock_errno == ENOMEM
                      ? "refused (ENOMEM: RLIMIT_MEMLOCK smaller than the process and no CAP_IPC_LOCK; "
                        "raise `ulimit -l` or grant cap_ipc_lock); pages may fault in real time"
                  : r.lock_errno == EPERM
                      ? "refused (EPERM: needs CAP_IPC_LOCK); pages may fault in real time"
                      : "refused; pages may fault in real time";
  }

  if (opts.keep_heap && !r.sanitizer_build) {
    // Freed memory stays in the (locked) heap instead of going back to the
    // kernel, and big blocks come from the heap rather than fresh mmaps that
    // would fault on first touch.
    r.heap_tuned = mallopt(M_TRIM_THRESHOLD, -1) == 1 && mallopt(M_MMAP_MAX, 0) == 1;
  }
  if (opts.prefault_stack_kib > 0) r.stack_prefaulted_kib = touch_stack(opts.prefault_stack_kib);
  return r;
}

void release_process_memory_lock() noexcept { munlockall(); }

ThreadSetupReport query_thread(pthread_t thread, const ThreadSpec& spec) noexcept {
  ThreadSetupReport r;
  r.name = spec.name != nullptr ? spec.name : "";
  char buf[16] = {};
  r.name_set = pthread_getname_np(thread, buf, sizeof buf) == 0 && std::strncmp(buf, r.name, 15) == 0;
  r.requested_priority = spec.priority;
  r.requested_cpu = spec.cpu;
  int policy = SCHED_OTHER;
  sched_param sp{};
  if (pthread_getschedparam(thread, &policy, &sp) == 0) {
    r.granted_policy = policy;
    r.granted_priority = (policy == SCHED_FIFO || policy == SCHED_RR) ? sp.sched_priority : 0;
  }
  if (spec.cpu >= 0 && spec.cpu < CPU_SETSIZE) {
    cpu_set_t set;
    CPU_ZERO(&set);
    r.pinned = pthread_getaffinity_np(thread, sizeof set, &set) == 0 && CPU_COUNT(&set) == 1 &&
               CPU_ISSET(spec.cpu, &set);
  }
  return r;
}

ThreadSetupReport apply_thread_spec(const ThreadSpec& spec) noexcept {
  const pthread_t self = pthread_self();
  ThreadSetupReport r;
  set_name(self, spec.name, r);
  r.requested_priority = spec.priority;
  r.requested_cpu = spec.cpu;

  sched_param sp{};
  if (spec.priority > 0) {
    sp.sched_priority = spec.priority;
    const int e = pthread_setschedparam(self, SCHED_FIFO, &sp);
    if (e != 0) {
      r.sched_errno = e;
      r.sched_note = sched_refusal_note(e);
      sp.sched_priority = 0;
      pthread_setschedparam(self, SCHED_OTHER, &sp);
    } else {
      r.sched_note = "granted";
    }
  } else {
    // Explicit, because a thread started from a SCHED_FIFO thread inherits it.
    pthread_setschedparam(self, SCHED_OTHER, &sp);
    r.sched_note = "SCHED_OTHER as requested";
  }

  if (spec.cpu < 0) {
    r.affinity_note = "any CPU as requested";
  } else if (spec.cpu >= CPU_SETSIZE || !cpu_allowed(self, spec.cpu)) {
    r.affinity_errno = EINVAL;
    r.affinity_note = "CPU not in this process's allowed set (taskset/cgroup); not pinned";
  } else {
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(spec.cpu, &set);
    const int e = pthread_setaffinity_np(self, sizeof set, &set);
    r.pinned = e == 0;
    r.affinity_errno = e;
    r.affinity_note = e == 0 ? "pinned" : "pthread_setaffinity_np refused; not pinned";
  }

  int policy = SCHED_OTHER;
  sched_param now{};
  if (pthread_getschedparam(self, &policy, &now) == 0) {
    r.granted_policy = policy;
    r.granted_priority = (policy == SCHED_FIFO || policy == SCHED_RR) ? now.sched_priority : 0;
  }
  return r;
}

int create_pthread(const ThreadSpec& spec, void* (*fn)(void*), void* arg, pthread_t* out,
                   ThreadSetupReport* report) noexcept {
  ThreadSetupReport local;
  ThreadSetupReport& r = report != nullptr ? *report : local;
  r = ThreadSetupReport{};
  r.requested_priority = spec.priority;
  r.requested_cpu = spec.cpu;

  const bool want_fifo = spec.priority > 0;
  bool want_pin = spec.cpu >= 0;
  if (want_pin && (spec.cpu >= CPU_SETSIZE || !cpu_allowed(pthread_self(), spec.cpu))) {
    want_pin = false;
    r.affinity_errno = EINVAL;
    r.affinity_note = "CPU not in this process's allowed set (taskset/cgroup); not pinned";
  }

  auto make_attr = [&](pthread_attr_t& attr, bool fifo, bool pin) {
    pthread_attr_init(&attr);
    sched_param sp{};
    if (fifo) {
      pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
      pthread_attr_setschedpolicy(&attr, SCHED_FIFO);
      sp.sched_priority = spec.priority;
      pthread_attr_setschedparam(&attr, &sp);
    } else {
      // Explicit SCHED_OTHER: never inherit a creator's real-time policy.
      pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
      pthread_attr_setschedpolicy(&attr, SCHED_OTHER);
      pthread_attr_setschedparam(&attr, &sp);
    }
    if (pin) {
      cpu_set_t set;
      CPU_ZERO(&set);
      CPU_SET(spec.cpu, &set);
      pthread_attr_setaffinity_np(&attr, sizeof set, &set);
    }
  };

  pthread_attr_t attr;
  make_attr(attr, want_fifo, want_pin);
  int e = pthread_create(out, &attr, fn, arg);
  pthread_attr_destroy(&attr);
  if (e == EPERM && want_fifo) {
    r.sched_errno = e;
    r.sched_note = sched_refusal_note(e);
    make_attr(attr, false, want_pin);
    e = pthread_create(out, &attr, fn, arg);
    pthread_attr_destroy(&attr);
  } else if (e == 0) {
    r.sched_note = want_fifo ? "granted" : "SCHED_OTHER as requested";
  }
  if (e != 0) return e;

  // pthread_create applies explicit scheduling and affinity before the thread
  // runs and fails if it cannot, so success means the attributes are in force.
  // (Querying instead would race a thread that has already exited.)
  set_name(*out, spec.name, r);
  const bool fifo = want_fifo && r.sched_errno == 0;
  r.granted_policy = fifo ? SCHED_FIFO : SCHED_OTHER;
  r.granted_priority = fifo ? spec.priority : 0;
  r.pinned = want_pin;
  if (spec.cpu < 0) {
    r.affinity_note = "any CPU as requested";
  } else if (want_pin) {
    r.affinity_note = "pinned";
  }
  return 0;
}

int allowed_cpu_count() noexcept {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof set, &set) != 0) return 1;
  const int n = CPU_COUNT(&set);
  return n > 0 ? n : 1;
}

int nth_allowed_cpu(int k) noexcept {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (k < 0 || sched_getaffinity(0, sizeof set, &set) != 0) return -1;
  for (int cpu = 0; cpu < CPU_SETSIZE; ++cpu) {
    if (CPU_ISSET(cpu, &set) && k-- == 0) return cpu;
  }
  return -1;
}

const char* policy_name(int policy) noexcept {
  switch (policy) {
    case SCHED_OTHER:
      return "SCHED_OTHER";
    case SCHED_FIFO:
      return "SCHED_FIFO";
    case SCHED_RR:
      return "SCHED_RR";
#ifdef SCHED_BATCH
    case SCHED_BATCH:
      return "SCHED_BATCH";
#endif
#ifdef SCHED_IDLE
    case SCHED_IDLE:
      return "SCHED_IDLE";
#endif
    default:
      return "unknown";
  }
}

std::string to_string(const ProcessSetupReport& r) {
  std::string s = "process setup: memory lock ";
  s += r.memory_locked           ? "GRANTED (mlockall current+future)"
       : r.lock_memory_requested ? "NOT in effect: "
                                 : "";
  if (!r.memory_locked) s += r.lock_note;
  if (r.lock_errno != 0) {
    s += " [errno ";
    s += std::strerror(r.lock_errno);
    s += "]";
  }
  s += "; stack prefaulted " + std::to_string(r.stack_prefaulted_kib) + " KiB";
  s += "; heap trim/mmap disabled: ";
  s += r.heap_tuned ? "yes" : "no";
  s += "; limits memlock=" + limit_text(r.rlimit_memlock_bytes, true) +
       " rtprio=" + limit_text(r.rlimit_rtprio, false);
  s += "; caps ipc_lock=";
  s += r.cap_ipc_lock ? "yes" : "no";
  s += " sys_nice=";
  s += r.cap_sys_nice ? "yes" : "no";
  if (r.sanitizer_build) s += "; sanitizer build";
  return s;
}

std::string to_string(const ThreadSetupReport& r) {
  std::string s = "thread '";
  s += r.name;
  s += "': ";
  s += policy_name(r.granted_policy);
  if (r.granted_policy == SCHED_FIFO || r.granted_policy == SCHED_RR)
    s += " prio " + std::to_string(r.granted_priority);
  if (r.requested_priority > 0)
    s += " (requested SCHED_FIFO prio " + std::to_string(r.requested_priority) + ")";
  s += " - ";
  s += r.sched_note;
  s += "; cpu ";
  s += r.requested_cpu < 0 ? std::string("any") : std::to_string(r.requested_cpu);
  s += " - ";
  s += r.affinity_note;
  if (!r.name_set) s += "; name NOT set";
  s += r.fully_granted() ? "; all granted" : "; FALLBACK in effect";
  return s;
}

}  // namespace kestrel::rt

#include <grp.h>
#include <gtest/gtest.h>
#include <sched.h>
#include <sys/resource.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>

#include "kestrel/rt/thread_setup.hpp"

namespace kestrel::rt {
namespace {

// A report must agree with itself and with what the kernel says.
void expect_coherent(const ThreadSetupReport& r, const ThreadSpec& spec) {
  EXPECT_STREQ(r.name, spec.name);
  EXPECT_EQ(r.requested_priority, spec.priority);
  EXPECT_EQ(r.requested_cpu, spec.cpu);
  if (spec.priority > 0 && r.sched_errno == 0) {
    EXPECT_EQ(r.granted_policy, SCHED_FIFO);
    EXPECT_EQ(r.granted_priority, spec.priority);
  } else {
    EXPECT_EQ(r.granted_policy, SCHED_OTHER);
    EXPECT_EQ(r.granted_priority, 0);
  }
  if (spec.priority > 0 && r.sched_errno != 0) {
    EXPECT_FALSE(r.fully_granted());
    EXPECT_NE(std::string(r.sched_note).find("SCHED_OTHER"), std::string::npos) << r.sched_note;
    EXPECT_NE(to_string(r).find("FALLBACK"), std::string::npos);
  }
  if (spec.cpu >= 0 && !r.pinned) {
    EXPECT_NE(r.affinity_errno, 0);
    EXPECT_FALSE(r.fully_granted());
  }
  EXPECT_STRNE(r.sched_note, "");
  EXPECT_STRNE(r.affinity_note, "");
}

TEST(ThreadSetup, OrdinaryThreadIsFullyGranted) {
  const ThreadSpec spec{"kst-plain", 0, -1, 0};
  ThreadSetupReport inside;
  ThreadSetupReport r;
  std::thread t = start_thread(
      spec, [&] { inside = query_thread(pthread_self(), spec); }, &r);
  t.join();
  expect_coherent(r, spec);
  EXPECT_TRUE(r.fully_granted()) << to_string(r);
  EXPECT_TRUE(inside.name_set) << "the kernel shows the thread name";
  EXPECT_EQ(inside.granted_policy, SCHED_OTHER);
}

TEST(ThreadSetup, RealTimeRequestIsGrantedOrReportedFallback) {
  // Whatever the privileges here, the report must match reality.
  const ThreadSpec spec{"kst-rt-request-long-name", 10, nth_allowed_cpu(0), 5'000'000};
  ThreadSetupReport inside;
  ThreadSetupReport r;
  std::thread t = start_thread(
      spec, [&] { inside = query_thread(pthread_self(), spec); }, &r);
  t.join();
  expect_coherent(r, spec);
  EXPECT_TRUE(r.name_set) << "names are cut to 15 chars, not refused";
  EXPECT_EQ(inside.granted_policy, r.granted_policy);
  EXPECT_EQ(inside.granted_priority, r.granted_priority);
  EXPECT_EQ(inside.pinned, r.pinned);
  std::printf("%s\n", to_string(r).c_str());
}

TEST(ThreadSetup, UnknownCpuIsReportedNotFatal) {
  const ThreadSpec spec{"kst-badcpu", 0, CPU_SETSIZE + 5, 0};
  ThreadSetupReport r;
  std::thread t = start_thread(
      spec, [] {}, &r);
  t.join();
  expect_coherent(r, spec);
  EXPECT_FALSE(r.pinned);
  EXPECT_FALSE(r.fully_granted());
}

struct Seen {
  int policy = -1;
  int priority = -1;
};

// Records the scheduling the thread really runs with, from inside it.
void* record_sched(void* arg) {
  auto* seen = static_cast<Seen*>(arg);
  sched_param sp{};
  pthread_getschedparam(pthread_self(), &seen->policy, &sp);
  seen->priority = sp.sched_priority;
  return nullptr;
}

TEST(ThreadSetup, PthreadPathReportsWhatItGot) {
  for (const ThreadSpec spec :
       {ThreadSpec{"kst-pt-other", 0, -1, 0}, ThreadSpec{"kst-pt-fifo", 5, nth_allowed_cpu(0), 0}}) {
    Seen seen;
    pthread_t th{};
    ThreadSetupReport r;
    ASSERT_EQ(create_pthread(spec, record_sched, &seen, &th, &r), 0);
    pthread_join(th, nullptr);
    expect_coherent(r, spec);
    EXPECT_EQ(seen.policy, r.granted_policy) << to_string(r);
    EXPECT_EQ(seen.priority, r.granted_priority);
  }
}

TEST(ProcessSetup, ReportIsCoherent) {
  ProcessSetupOptions opts;
  opts.lock_memory = true;
  opts.prefault_stack_kib = 128;
  const ProcessSetupReport r = setup_process(opts);
  release_process_memory_lock();
  const std::string text = to_string(r);
  std::printf("%s\n", text.c_str());
  EXPECT_GE(r.stack_prefaulted_kib, 128u);
  EXPECT_TRUE(r.lock_memory_requested);
  if (r.memory_locked) {
    EXPECT_EQ(r.lock_errno, 0);
    EXPECT_NE(text.find("GRANTED"), std::string::npos);
  } else {
    EXPECT_TRUE(r.sanitizer_build || r.lock_errno != 0) << text;
    EXPECT_NE(text.find("NOT in effect"), std::string::npos);
  }
  EXPECT_STRNE(r.lock_note, "");

  const ProcessSetupReport off = setup_process(ProcessSetupOptions{false, 0, false});
  EXPECT_FALSE(off.memory_locked);
  EXPECT_EQ(off.stack_prefaulted_kib, 0u);
}

// Child process without privileges: drop every capability and real-time
// limit, then everything must fall back, be reported, and nothing be fatal.
void run_unprivileged_and_exit() {
  rlimit none{0, 0};
  setrlimit(RLIMIT_RTPRIO, &none);
  rlimit small{64 * 1024, 64 * 1024};
  setrlimit(RLIMIT_MEMLOCK, &small);
  if (geteuid() == 0) {
    // Leaving uid 0 without keep-caps clears every capability.
    if (setgroups(0, nullptr) != 0 || setgid(65534) != 0 || setuid(65534) != 0) {
      std::fprintf(stderr, "could not drop privileges: %s\n", std::strerror(errno));
      std::exit(2);
    }
  }
  const ProcessSetupReport p = setup_process({});
  std::fprintf(stderr, "%s\n", to_string(p).c_str());
  if (p.memory_locked || p.cap_ipc_lock || p.cap_sys_nice) std::exit(3);
  if (!p.sanitizer_build && p.lock_errno == 0) std::exit(4);

  const ThreadSpec spec{"kst-noprivs", 20, -1, 1'000'000};
  const ThreadSetupReport r = apply_thread_spec(spec);
  std::fprintf(stderr, "%s\n", to_string(r).c_str());
  if (r.sched_errno != EPERM || r.granted_policy != SCHED_OTHER || r.fully_granted()) std::exit(5);
  std::exit(0);
}

TEST(ProcessSetupDeathTest, WithoutPrivilegesFallsBackAndSaysSo) {
  // threadsafe re-executes this binary, which an emulated cross build (the
  // aarch64 preset under qemu, no binfmt_misc) cannot do: it forks instead.
  GTEST_FLAG_SET(death_test_style, std::string(KESTREL_RUN_PREFIX).empty() ? "threadsafe" : "fast");
  EXPECT_EXIT(
      run_unprivileged_and_exit(), testing::ExitedWithCode(0),
      "memory lock NOT in effect.*\n.*SCHED_OTHER \\(requested SCHED_FIFO prio 20\\).*EPERM.*FALLBACK");
}

}  // namespace
}  // namespace kestrel::rt

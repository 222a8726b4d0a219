// Heap-allocation counter for tests: "this real-time path allocates nothing".
//
// Design: every function declared here is DEFINED ONLY in src/alloc_hook.cpp,
// which also replaces the global operator new/delete (all C++17 forms) with
// counting versions that forward to malloc/free (posix_memalign for aligned
// forms). That file is the object library kestrel_alloc_hook, not part of
// kestrel_rt, so:
//  - production binaries keep the standard operator new (nothing linked in);
//  - code that calls this API without linking kestrel_alloc_hook fails at link
//    time (undefined reference), instead of silently counting nothing;
//  - tests get it with kestrel_add_test(... ALLOC_HOOK).
// alloc_hook_linked() goes further and checks at run time that operator new
// really reaches the counting replacement (not, say, a sanitizer's own).
//
// Works under ASan/UBSan/TSan: the sanitizers intercept malloc/free, which is
// where the replacement ends up, so their checks still apply.
//
// Counts are of calls to operator new (all forms) and, outside sanitizer
// builds, of malloc/calloc/realloc/memalign/aligned_alloc/posix_memalign too
// (Eigen's dynamic matrices allocate with malloc): alloc_hook_counts_malloc().
#pragma once

#include <cstdint>

namespace kestrel::rt {

// All threads, since program start.
std::uint64_t alloc_count_total() noexcept;
// Calling thread only, since it started.
std::uint64_t alloc_count_this_thread() noexcept;
std::uint64_t alloc_bytes_this_thread() noexcept;
std::uint64_t dealloc_count_this_thread() noexcept;

// True when malloc & co. are counted as well (not under ASan/TSan).
bool alloc_hook_counts_malloc() noexcept;

// True when the counting operator new is in effect (checked by allocating).
bool alloc_hook_linked() noexcept;

// Counts the calling thread's allocations from construction on.
class AllocCountScope {
 public:
  AllocCountScope() noexcept : start_(alloc_count_this_thread()), start_bytes_(alloc_bytes_this_thread()) {}
  [[nodiscard]] std::uint64_t count() const noexcept { return alloc_count_this_thread() - start_; }
  [[nodiscard]] std::uint64_t bytes() const noexcept { return alloc_bytes_this_thread() - start_bytes_; }

 private:
  std::uint64_t start_;
  std::uint64_t start_bytes_;
};

}  // namespace kestrel::rt

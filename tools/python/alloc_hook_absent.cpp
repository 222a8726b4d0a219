// The allocation counter's API without the counting operator new/malloc
// (rt/src/alloc_hook.cpp). The replay harness asks alloc_hook_linked() and
// reports "counting: false" when it is not; it links the API either way. A
// Python extension must not replace malloc and operator new for the whole
// interpreter, so here the hook is honestly absent: nothing is counted and
// replay(report=True) says so (docs/python.md).
#include "kestrel/rt/alloc_counter.hpp"

namespace kestrel::rt {

std::uint64_t alloc_count_total() noexcept { return 0; }
std::uint64_t alloc_count_this_thread() noexcept { return 0; }
std::uint64_t alloc_bytes_this_thread() noexcept { return 0; }
std::uint64_t dealloc_count_this_thread() noexcept { return 0; }
bool alloc_hook_counts_malloc() noexcept { return false; }
bool alloc_hook_linked() noexcept { return false; }

}  // namespace kestrel::rt

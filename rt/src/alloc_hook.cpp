// Replacement of the global allocation functions, counting per thread and in
// total. Linked only into test executables (object library kestrel_alloc_hook).
#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <new>

#include "kestrel/rt/alloc_counter.hpp"

// Eigen's dynamic matrices (and C libraries) allocate with malloc, not
// operator new; a zero-allocation claim that cannot see them proves little.
// So malloc & co. are interposed too, forwarding to glibc's __libc_* entry
// points. Sanitizer builds bring their own malloc: there only operator new
// is counted (alloc_hook_counts_malloc() says which).
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
#define KESTREL_COUNT_MALLOC 0
#elif defined(__has_feature)
#if __has_feature(address_sanitizer) || __has_feature(thread_sanitizer) || __has_feature(memory_sanitizer)
#define KESTREL_COUNT_MALLOC 0
#endif
#endif
#ifndef KESTREL_COUNT_MALLOC
#define KESTREL_COUNT_MALLOC 1
#endif

namespace {

// Trivial thread_locals: no TLS init wrapper, safe to touch from operator new
// during thread start-up and exit.
thread_local std::uint64_t t_allocs = 0;
thread_local std::uint64_t t_bytes = 0;
thread_local std::uint64_t t_deallocs = 0;
std::atomic<std::uint64_t> g_allocs{0};

void count(std::size_t n) noexcept {
  ++t_allocs;
  t_bytes += n;
  g_allocs.fetch_add(1, std::memory_order_relaxed);
}

void* alloc_plain(std::size_t n) noexcept {
  // With malloc interposed, the malloc below counts; never count twice.
  if (!KESTREL_COUNT_MALLOC) count(n);
  return std::malloc(n == 0 ? 1 : n);
}

void* alloc_aligned(std::size_t n, std::align_val_t al) noexcept {
  if (!KESTREL_COUNT_MALLOC) count(n);
  std::size_t a = static_cast<std::size_t>(al);
  if (a < sizeof(void*)) a = sizeof(void*);  // posix_memalign's minimum
  void* p = nullptr;
  return posix_memalign(&p, a, n == 0 ? 1 : n) == 0 ? p : nullptr;
}

// The throwing forms follow [new.delete.single]: call the new-handler and
// retry, throw bad_alloc when there is none.
template <class Alloc>
void* alloc_or_throw(Alloc alloc) {
  for (;;) {
    if (void* p = alloc()) return p;
    std::new_handler h = std::get_new_handler();
    if (h == nullptr) throw std::bad_alloc();
    h();
  }
}

void release(void* p) noexcept {
  if (p == nullptr) return;
  ++t_deallocs;
  std::free(p);
}

}  // namespace

#if KESTREL_COUNT_MALLOC
extern "C" {
// glibc's own entry points, under glibc's names.
// NOLINTBEGIN(bugprone-reserved-identifier,readability-identifier-naming)
void* __libc_malloc(std::size_t);
void* __libc_calloc(std::size_t, std::size_t);
void* __libc_realloc(void*, std::size_t);
void* __libc_memalign(std::size_t, std::size_t);
void __libc_free(void*);
// NOLINTEND(bugprone-reserved-identifier,readability-identifier-naming)

void* malloc(std::size_t n) {
  count(n);
  return __libc_malloc(n);
}
void* calloc(std::size_t a, std::size_t b) {
  count(a * b);
  return __libc_calloc(a, b);
}
void* realloc(void* p, std::size_t n) {
  count(n);
  return __libc_realloc(p, n);
}
void* memalign(std::size_t a, std::size_t n) {
  count(n);
  return __libc_memalign(a, n);
}
void* aligned_alloc(std::size_t a, std::size_t n) {
  count(n);
  return __libc_memalign(a, n);
}
int posix_memalign(void** out, std::size_t a, std::size_t n) {
  count(n);
  void* p = __libc_memalign(a, n);
  if (p == nullptr) return 12;  // ENOMEM
  *out = p;
  return 0;
}
void free(void* p) { __libc_free(p); }
}
#endif

// ---- replaceable allocation functions ([new.delete], C++17) -----------------
void* operator new(std::size_t n) {
  return alloc_or_throw([n] { return alloc_plain(n); });
}
void* operator new[](std::size_t n) {
  return alloc_or_throw([n] { return alloc_plain(n); });
}
void* operator new(std::size_t n, const std::nothrow_t&) noexcept { return alloc_plain(n); }
void* operator new[](std::size_t n, const std::nothrow_t&) noexcept { return alloc_plain(n); }
void* operator new(std::size_t n, std::align_val_t al) {
  return alloc_or_throw([n, al] { return alloc_aligned(n, al); });
}
void* operator new[](std::size_t n, std::align_val_t al) {
  return alloc_or_throw([n, al] { return alloc_aligned(n, al); });
}
void* operator new(std::size_t n, std::align_val_t al, const std::nothrow_t&) noexcept {
  return alloc_aligned(n, al);
}
void* operator new[](std::size_t n, std::align_val_t al, const std::nothrow_t&) noexcept {
  return alloc_aligned(n, al);
}

void operator delete(void* p) noexcept { release(p); }
void operator delete[](void* p) noexcept { release(p); }
void operator delete(void* p, std::size_t) noexcept { release(p); }
void operator delete[](void* p, std::size_t) noexcept { release(p); }
void operator delete(void* p, const std::nothrow_t&) noexcept { release(p); }
void operator delete[](void* p, const std::nothrow_t&) noexcept { release(p); }
void operator delete(void* p, std::align_val_t) noexcept { release(p); }
void operator delete[](void* p, std::align_val_t) noexcept { release(p); }
void operator delete(void* p, std::size_t, std::align_val_t) noexcept { release(p); }
void operator delete[](void* p, std::size_t, std::align_val_t) noexcept { release(p); }
void operator delete(void* p, std::align_val_t, const std::nothrow_t&) noexcept { release(p); }
void operator delete[](void* p, std::align_val_t, const std::nothrow_t&) noexcept { release(p); }

namespace kestrel::rt {

std::uint64_t alloc_count_total() noexcept { return g_allocs.load(std::memory_order_relaxed); }
std::uint64_t alloc_count_this_thread() noexcept { return t_allocs; }
std::uint64_t alloc_bytes_this_thread() noexcept { return t_bytes; }
std::uint64_t dealloc_count_this_thread() noexcept { return t_deallocs; }

bool alloc_hook_counts_malloc() noexcept { return KESTREL_COUNT_MALLOC != 0; }

bool alloc_hook_linked() noexcept {
  // Through a volatile function pointer so the compiler can neither inline
  // our own definition nor elide the allocation: this measures what a call
  // to ::operator new really reaches in this executable.
  void* (*volatile op_new)(std::size_t, const std::nothrow_t&) noexcept = &::operator new;
  void (*volatile op_delete)(void*) noexcept = &::operator delete;
  const std::uint64_t before = t_allocs;
  void* p = op_new(16, std::nothrow);
  const bool counted = t_allocs == before + 1;
  op_delete(p);
  return counted;
}

}  // namespace kestrel::rt

// Latest-value mailbox: one writer publishes, any number of readers on other
// threads copy the newest complete value (optimizer -> tracker state hand-off).
//
// Full policy: none needed: a new value replaces the old one; readers that
// care whether they missed values compare version() (the publish count).
//
// A seqlock: the writer is wait-free (never waits for readers); a reader
// retries while a publish is in flight, which for a payload of a few KiB
// published at optimizer rate is rare and short.
//
// Why the payload is stored as std::atomic<uint64_t> words: a plain memcpy
// racing the writer is a data race (UB, and ThreadSanitizer says so) even if
// the sequence check throws the torn copy away. Payload words are stored with
// release and loaded with acquire (one of the correct variants in H.-J. Boehm,
// "Can seqlocks get along with programming language memory models?", MSPC
// 2012). That variant needs no standalone fences, which ThreadSanitizer does
// not model (g++ refuses atomic_thread_fence under -fsanitize=thread), so TSan
// checks the real orderings. On x86-64 every one of these is a plain mov.
//
// Thread contract: publish() from ONE thread only; read()/version() from any.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <type_traits>

namespace kestrel::rt {

template <class T>
class Mailbox {
  static_assert(std::is_trivially_copyable_v<T>,
                "Mailbox<T> copies T as raw words: T must be trivially copyable");
  static_assert(std::is_default_constructible_v<T>, "Mailbox<T> needs a default-constructible T");
  static constexpr std::size_t kWords = (sizeof(T) + sizeof(std::uint64_t) - 1) / sizeof(std::uint64_t);

 public:
  Mailbox() = default;
  Mailbox(const Mailbox&) = delete;
  Mailbox& operator=(const Mailbox&) = delete;

  // Wait-free. Single writer.
  void publish(const T& v) noexcept {
    std::uint64_t buf[kWords] = {};
    std::memcpy(buf, &v, sizeof(T));
    const std::uint64_t s = seq_.load(std::memory_order_relaxed);
    seq_.store(s + 1, std::memory_order_relaxed);  // odd: write in progress
    // Release per word: a reader whose acquire load sees any new word also
    // sees the odd sequence above, so its re-check fails and it retries.
    for (std::size_t i = 0; i < kWords; ++i) words_[i].store(buf[i], std::memory_order_release);
    seq_.store(s + 2, std::memory_order_release);  // even: complete
  }

  // Copies the newest complete value into out. Returns false (out untouched)
  // if nothing was ever published. If version_out is given, it receives the
  // version of the value copied (1 for the first publish).
  bool read(T& out, std::uint64_t* version_out = nullptr) const noexcept {
    std::uint64_t buf[kWords];
    std::uint64_t s0 = 0;
    for (;;) {
      s0 = seq_.load(std::memory_order_acquire);
      if (s0 == 0) return false;
      if (s0 & 1u) {
        cpu_relax();
        continue;
      }
      // Acquire per word: pairs with the writer's release stores, and keeps the
      // re-check of the sequence below from moving above the payload loads.
      for (std::size_t i = 0; i < kWords; ++i) buf[i] = words_[i].load(std::memory_order_acquire);
      if (seq_.load(std::memory_order_relaxed) == s0) break;
      cpu_relax();
    }
    std::memcpy(&out, buf, sizeof(T));
    if (version_out != nullptr) *version_out = s0 / 2;
    return true;
  }

  // Number of completed publishes (0 = never written).
  [[nodiscard]] std::uint64_t version() const noexcept { return seq_.load(std::memory_order_acquire) / 2; }

 private:
  static void cpu_relax() noexcept {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_ia32_pause();
#elif defined(__aarch64__)
    asm volatile("yield" ::: "memory");
#endif
  }

  alignas(64) std::atomic<std::uint64_t> seq_{0};
  alignas(64) std::atomic<std::uint64_t> words_[kWords] = {};
};

}  // namespace kestrel::rt

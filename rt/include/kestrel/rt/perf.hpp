// Perf counters instead of prints (PX4 style): registered at start-up by name,
// updated in O(1) without allocation or locks, dumped by tools.
//
// Kinds:
//  - kCount:    events (frames dropped, retries): inc(n).
//  - kElapsed:  accumulated duration of a section: start()/stop(),
//               add_elapsed(ns) or a ScopedTimer; keeps count/min/max/mean.
//  - kInterval: time between successive tick() calls (jitter of a periodic
//               loop or sensor stream); keeps count/min/max/mean.
//
// Thread contract: each counter has ONE updating thread (the one that owns the
// code path it measures). Any thread may read or dump at any time: fields are
// relaxed atomics, written with plain load+store (no RMW), so a reader sees
// each field untorn but the fields of one counter are not a single snapshot.
// register_counter() takes a mutex: start-up only, never on a real-time path.
//
// Names are paths, "module.counter" ("window.solves_ok", "input.frames_missing"):
// the metrics JSON, the status line and the viewer read them by path.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <mutex>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace kestrel::rt {

enum class PerfKind : std::uint8_t { kCount, kElapsed, kInterval };
const char* to_string(PerfKind k) noexcept;

class PerfCounter {
 public:
  static constexpr std::size_t kMaxName = 47;

  struct Snapshot {
    const char* name;
    PerfKind kind;
    std::uint64_t count;  // events, or samples for elapsed/interval
    std::int64_t total_ns;
    std::int64_t min_ns;  // 0 when count == 0
    std::int64_t max_ns;
    [[nodiscard]] double mean_ns() const noexcept {
      return count > 0 ? static_cast<double>(total_ns) / static_cast<double>(count) : 0.0;
    }
  };

  PerfCounter() = default;
  PerfCounter(const PerfCounter&) = delete;
  PerfCounter& operator=(const PerfCounter&) = delete;

  // kCount
  void inc(std::uint64_t n = 1) noexcept { bump(count_, n); }
  // kCount whose source of truth is a count kept elsewhere by the updating
  // thread (a ring's refused pushes, a backend's own counters): mirrored here
  // so every reader finds it by path.
  void set(std::uint64_t n) noexcept { count_.store(n, std::memory_order_relaxed); }

  // kElapsed
  void start() noexcept;
  void stop() noexcept;
  void add_elapsed(std::int64_t dt_ns) noexcept { add_sample(dt_ns); }

  // kInterval: records the time since the previous tick (the first tick only
  // arms it). tick(now) for callers that already have a timestamp.
  void tick() noexcept;
  void tick(std::int64_t now_ns) noexcept {
    const std::int64_t last = last_ns_.load(std::memory_order_relaxed);
    last_ns_.store(now_ns, std::memory_order_relaxed);
    if (last != kUnset) add_sample(now_ns - last);
  }

  void reset() noexcept;

  [[nodiscard]] Snapshot snapshot() const noexcept;
  [[nodiscard]] const char* name() const noexcept { return name_; }
  [[nodiscard]] PerfKind kind() const noexcept { return kind_; }

 private:
  friend class PerfRegistry;
  static constexpr std::int64_t kUnset = INT64_MIN;

  template <class A, class V>
  static void bump(A& a, V n) noexcept {
    a.store(a.load(std::memory_order_relaxed) + n, std::memory_order_relaxed);
  }
  void add_sample(std::int64_t dt_ns) noexcept {
    const std::uint64_t c = count_.load(std::memory_order_relaxed);
    if (c == 0 || dt_ns < min_ns_.load(std::memory_order_relaxed))
      min_ns_.store(dt_ns, std::memory_order_relaxed);
    if (c == 0 || dt_ns > max_ns_.load(std::memory_order_relaxed))
      max_ns_.store(dt_ns, std::memory_order_relaxed);
    bump(total_ns_, dt_ns);
    count_.store(c + 1, std::memory_order_relaxed);
  }

  char name_[kMaxName + 1] = {};
  PerfKind kind_ = PerfKind::kCount;
  std::atomic<std::uint64_t> count_{0};
  std::atomic<std::int64_t> total_ns_{0};
  std::atomic<std::int64_t> min_ns_{0};
  std::atomic<std::int64_t> max_ns_{0};
  std::atomic<std::int64_t> last_ns_{kUnset};  // start() time or previous tick()
};

// Times the enclosing scope into a kElapsed counter (nullptr-tolerant).
class ScopedTimer {
 public:
  explicit ScopedTimer(PerfCounter* c) noexcept;
  ~ScopedTimer();
  ScopedTimer(const ScopedTimer&) = delete;
  ScopedTimer& operator=(const ScopedTimer&) = delete;

 private:
  PerfCounter* c_;
  std::int64_t t0_ns_;
};

// A copy of one counter that outlives its registry (reports, JSON).
struct PerfValue {
  std::string name;
  PerfKind kind = PerfKind::kCount;
  std::uint64_t count = 0;
  std::int64_t total_ns = 0, min_ns = 0, max_ns = 0;
};

// Every counter of a registry at one moment, in registration order.
class PerfValues {
 public:
  PerfValues() = default;
  explicit PerfValues(std::vector<PerfValue> v) : values_(std::move(v)) {}
  [[nodiscard]] const std::vector<PerfValue>& all() const noexcept { return values_; }
  // nullptr if absent.
  [[nodiscard]] const PerfValue* find(std::string_view name) const noexcept;
  // The count of the counter called name; std::out_of_range naming it when
  // there is none, so a misspelt path fails instead of reading zero.
  [[nodiscard]] std::uint64_t count(std::string_view name) const;

 private:
  std::vector<PerfValue> values_;
};

class PerfRegistry {
 public:
  static constexpr std::size_t kCapacity = 128;

  PerfRegistry() = default;
  PerfRegistry(const PerfRegistry&) = delete;
  PerfRegistry& operator=(const PerfRegistry&) = delete;

  // Returns the counter called name, creating it if needed (same name + kind
  // returns the same counter, so modules can register independently). Never
  // nullptr: when the registry is full, or the name exists with another kind,
  // a shared overflow counter is returned and refused() goes up, which dump()
  // reports. Names longer than PerfCounter::kMaxName are cut.
  PerfCounter* register_counter(const char* name, PerfKind kind);

  [[nodiscard]] std::size_t size() const noexcept { return size_.load(std::memory_order_acquire); }
  [[nodiscard]] std::uint64_t refused() const noexcept { return refused_.load(std::memory_order_relaxed); }
  // nullptr if absent. Not for real-time paths (linear search).
  [[nodiscard]] const PerfCounter* find(const char* name) const noexcept;
  [[nodiscard]] const PerfCounter& at(std::size_t i) const noexcept { return counters_[i]; }
  // A copy of every counter (allocates: not for real-time paths).
  [[nodiscard]] PerfValues values() const;

  // One line per counter: name, kind, count, and for elapsed/interval the
  // mean/min/max in microseconds.
  void dump(std::FILE* out) const;
  [[nodiscard]] std::string to_string() const;
  void reset_all() noexcept;

 private:
  std::mutex register_mutex_;
  std::atomic<std::size_t> size_{0};  // release-published after a counter's name/kind are set
  std::atomic<std::uint64_t> refused_{0};
  PerfCounter counters_[kCapacity];
  PerfCounter overflow_;
};

// The process-wide registry tools dump.
PerfRegistry& perf_registry();

}  // namespace kestrel::rt

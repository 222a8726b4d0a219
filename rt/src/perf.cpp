#include "kestrel/rt/perf.hpp"

#include <cinttypes>
#include <cstring>
#include <stdexcept>

#include "kestrel/rt/clock.hpp"

namespace kestrel::rt {

const char* to_string(PerfKind k) noexcept {
  switch (k) {
    case PerfKind::kCount:
      return "count";
    case PerfKind::kElapsed:
      return "elapsed";
    case PerfKind::kInterval:
      return "interval";
  }
  return "?";
}

void PerfCounter::start() noexcept { last_ns_.store(now_ns(), std::memory_order_relaxed); }

void PerfCounter::stop() noexcept {
  const std::int64_t t0 = last_ns_.load(std::memory_order_relaxed);
  if (t0 == kUnset) return;  // stop without start: ignored rather than a bogus sample
  add_sample(now_ns() - t0);
  last_ns_.store(kUnset, std::memory_order_relaxed);
}

void PerfCounter::tick() noexcept { tick(now_ns()); }

void PerfCounter::reset() noexcept {
  count_.store(0, std::memory_order_relaxed);
  total_ns_.store(0, std::memory_order_relaxed);
  min_ns_.store(0, std::memory_order_relaxed);
  max_ns_.store(0, std::memory_order_relaxed);
  last_ns_.store(kUnset, std::memory_order_relaxed);
}

PerfCounter::Snapshot PerfCounter::snapshot() const noexcept {
  Snapshot s{name_,
             kind_,
             count_.load(std::memory_order_relaxed),
             total_ns_.load(std::memory_order_relaxed),
             min_ns_.load(std::memory_order_relaxed),
             max_ns_.load(std::memory_order_relaxed)};
  return s;
}

ScopedTimer::ScopedTimer(PerfCounter* c) noexcept : c_(c), t0_ns_(c != nullptr ? now_ns() : 0) {}
ScopedTimer::~ScopedTimer() {
  if (c_ != nullptr) c_->add_elapsed(now_ns() - t0_ns_);
}

PerfCounter* PerfRegistry::register_counter(const char* name, PerfKind kind) {
  const char* n = name != nullptr ? name : "";
  std::lock_guard<std::mutex> lock(register_mutex_);
  const std::size_t count = size_.load(std::memory_order_relaxed);
  for (std::size_t i = 0; i < count; ++i) {
    if (std::strncmp(counters_[i].name_, n, PerfCounter::kMaxName) == 0) {
      if (counters_[i].kind_ == kind) return &counters_[i];
      refused_.fetch_add(1, std::memory_order_relaxed);
      return &overflow_;
    }
  }
  if (count == kCapacity) {
    refused_.fetch_add(1, std::memory_order_relaxed);
    return &overflow_;
  }
  PerfCounter& c = counters_[count];
  std::snprintf(c.name_, sizeof c.name_, "%s", n);
  c.kind_ = kind;
  c.reset();
  // Readers iterate up to size(): publish the name and kind before the slot.
  size_.store(count + 1, std::memory_order_release);
  return &c;
}

const PerfCounter* PerfRegistry::find(const char* name) const noexcept {
  const std::size_t count = size();
  for (std::size_t i = 0; i < count; ++i) {
    if (std::strncmp(counters_[i].name_, name, PerfCounter::kMaxName) == 0) return &counters_[i];
  }
  return nullptr;
}

const PerfValue* PerfValues::find(std::string_view name) const noexcept {
  for (const PerfValue& v : values_)
    if (v.name == name) return &v;
  return nullptr;
}

std::uint64_t PerfValues::count(std::string_view name) const {
  const PerfValue* v = find(name);
  if (v == nullptr) throw std::out_of_range("no perf counter called '" + std::string(name) + "'");
  return v->count;
}

PerfValues PerfRegistry::values() const {
  std::vector<PerfValue> out;
  const std::size_t count = size();
  out.reserve(count);
  for (std::size_t i = 0; i < count; ++i) {
    const PerfCounter::Snapshot s = counters_[i].snapshot();
    out.push_back({s.name, s.kind, s.count, s.total_ns, s.min_ns, s.max_ns});
  }
  return PerfValues(std::move(out));
}

std::string PerfRegistry::to_string() const {
  std::string out;
  char line[192];
  const std::size_t count = size();
  for (std::size_t i = 0; i < count; ++i) {
    const PerfCounter::Snapshot s = counters_[i].snapshot();
    if (s.kind == PerfKind::kCount) {
      std::snprintf(line, sizeof line, "%-40s %-8s %12" PRIu64 "\n", s.name, kestrel::rt::to_string(s.kind),
                    s.count);
    } else {
      std::snprintf(line, sizeof line,
                    "%-40s %-8s %12" PRIu64 "  mean %10.1f us  min %10.1f us  max %10.1f us\n", s.name,
                    kestrel::rt::to_string(s.kind), s.count, s.mean_ns() / 1e3,
                    static_cast<double>(s.min_ns) / 1e3, static_cast<double>(s.max_ns) / 1e3);
    }
    out += line;
  }
  if (refused() > 0) {
    std::snprintf(line, sizeof line, "(%" PRIu64 " registrations refused: registry full or kind mismatch)\n",
                  refused());
    out += line;
  }
  return out;
}

void PerfRegistry::dump(std::FILE* out) const {
  const std::string s = to_string();
  std::fputs(s.c_str(), out);
}

void PerfRegistry::reset_all() noexcept {
  const std::size_t count = size();
  for (std::size_t i = 0; i < count; ++i) counters_[i].reset();
}

PerfRegistry& perf_registry() {
  static PerfRegistry r;
  return r;
}

}  // namespace kestrel::rt

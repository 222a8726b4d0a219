// Random numbers for the simulator, identical on every platform.
//
// std::normal_distribution (and the other std distributions) may differ
// between standard libraries, which would break "same seed, same bytes"
// across machines; std::mt19937_64 itself is fully specified. So the engine
// is std's and every distribution is ours.
#pragma once

#include <cmath>
#include <cstdint>
#include <random>

namespace kestrel::tools {

// SplitMix64 finaliser: a cheap, well-mixed 64-bit hash, used both to derive
// independent seeds and as a counter-based generator for per-pixel noise
// (which must not depend on how rows are split between threads).
inline uint64_t splitmix64(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

inline uint64_t hash_combine(uint64_t a, uint64_t b) {
  return splitmix64(a ^ splitmix64(b + 0x632BE59BD9B4E019ull));
}

// Independent streams from one user seed, so that e.g. switching IMU noise
// off does not move the clutter in the scene.
enum class RngStream : uint64_t { kScene = 1, kImu = 2, kCamera = 3, kPixels = 4 };

class SimRng {
 public:
  explicit SimRng(uint64_t seed, RngStream stream = RngStream::kScene)
      : engine_(hash_combine(seed, static_cast<uint64_t>(stream))) {}

  uint64_t next_u64() { return engine_(); }
  // [0, 1) with 53 random bits.
  double uniform() { return static_cast<double>(engine_() >> 11) * 0x1.0p-53; }
  double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }
  // Integer in [0, n), n > 0 (modulo bias is below 2^-40 for the n we use).
  uint64_t below(uint64_t n) { return engine_() % n; }
  bool bernoulli(double p) { return uniform() < p; }

  // Standard normal by Box-Muller; the second value of each pair is kept.
  double normal() {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    const double u1 = 1.0 - uniform();  // (0, 1]: log is finite
    const double u2 = uniform();
    const double r = std::sqrt(-2.0 * std::log(u1));
    const double a = 6.283185307179586476925 * u2;
    spare_ = r * std::sin(a);
    has_spare_ = true;
    return r * std::cos(a);
  }

 private:
  std::mt19937_64 engine_;
  bool has_spare_ = false;
  double spare_ = 0.0;
};

}  // namespace kestrel::tools

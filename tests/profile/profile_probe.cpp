// A program with a known call structure for tests/profile: leaf() is called
// 1000 times from work(), work() 10 times from main(), and recurse() calls
// itself 5 deep once.
#include <cstdint>

namespace probe {
volatile std::uint64_t sink = 0;

[[gnu::noinline]] std::uint64_t leaf(std::uint64_t x) {
  for (int i = 0; i < 100; ++i) x = x * 6364136223846793005ULL + 1442695040888963407ULL;
  return x;
}

[[gnu::noinline]] void work(int n) {
  for (int i = 0; i < n; ++i) sink = sink + leaf(static_cast<std::uint64_t>(i));
}

[[gnu::noinline]] int recurse(int depth) {
  return depth == 0 ? static_cast<int>(sink & 1) : 1 + recurse(depth - 1);
}
}  // namespace probe

int main() {
  for (int k = 0; k < 10; ++k) probe::work(100);
  return probe::recurse(5) > 100 ? 1 : 0;
}

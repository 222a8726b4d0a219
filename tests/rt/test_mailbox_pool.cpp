#include <gtest/gtest.h>

#include <array>
#include <cstdint>
#include <vector>

#include "kestrel/rt/mailbox.hpp"
#include "kestrel/rt/object_pool.hpp"

namespace kestrel::rt {
namespace {

struct Odd {  // 12 bytes: not a whole number of 64-bit words
  std::uint32_t a, b, c;
};

TEST(Mailbox, EmptyUntilFirstPublish) {
  Mailbox<Odd> m;
  Odd out{7, 7, 7};
  EXPECT_FALSE(m.read(out));
  EXPECT_EQ(out.a, 7u) << "a failed read leaves out untouched";
  EXPECT_EQ(m.version(), 0u);
  m.publish({1, 2, 3});
  std::uint64_t v = 0;
  ASSERT_TRUE(m.read(out, &v));
  EXPECT_EQ(v, 1u);
  EXPECT_EQ(out.a, 1u);
  EXPECT_EQ(out.b, 2u);
  EXPECT_EQ(out.c, 3u);
  m.publish({4, 5, 6});
  m.publish({7, 8, 9});
  ASSERT_TRUE(m.read(out, &v));
  EXPECT_EQ(v, 3u) << "latest value wins";
  EXPECT_EQ(out.c, 9u);
  EXPECT_EQ(m.version(), 3u);
}

TEST(Mailbox, LargePayload) {
  struct State {
    double x[15 * 15 + 16];
    std::int64_t t_ns;
  };
  static Mailbox<State> m;  // ~2 KiB payload
  State s{};
  for (int i = 0; i < 241; ++i) s.x[i] = i * 0.5;
  s.t_ns = 42;
  m.publish(s);
  State out{};
  ASSERT_TRUE(m.read(out));
  EXPECT_EQ(out.t_ns, 42);
  EXPECT_DOUBLE_EQ(out.x[240], 120.0);
}

struct Image {
  std::vector<std::uint8_t> pixels;
};

TEST(ObjectPool, AcquireUntilEmptyThenRelease) {
  int inits = 0;
  ObjectPool<Image, 3> pool([&](Image& im) {
    im.pixels.resize(640 * 480);
    ++inits;
  });
  EXPECT_EQ(inits, 3) << "all storage is made at construction";
  std::array<PoolHandle, 3> h{};
  for (auto& x : h) {
    x = pool.acquire();
    ASSERT_NE(x, kInvalidHandle);
    ASSERT_NE(pool.get(x), nullptr);
    EXPECT_EQ(pool.get(x)->pixels.size(), 640u * 480u);
  }
  EXPECT_NE(pool.get(h[0]), pool.get(h[1]));
  EXPECT_EQ(pool.in_use(), 3u);
  EXPECT_EQ(pool.acquire(), kInvalidHandle) << "exhausted pool refuses";
  EXPECT_EQ(pool.failed_acquires(), 1u);

  EXPECT_TRUE(pool.release(h[1]));
  EXPECT_EQ(pool.get(h[1]), nullptr) << "released handle is stale";
  EXPECT_FALSE(pool.release(h[1])) << "double release refused";
  EXPECT_EQ(pool.bad_releases(), 1u);

  const PoolHandle again = pool.acquire();
  ASSERT_NE(again, kInvalidHandle);
  EXPECT_NE(again, h[1]) << "same slot, new generation";
  EXPECT_EQ(again & 0xFFFFu, h[1] & 0xFFFFu);
  EXPECT_EQ(pool.get(h[1]), nullptr);
  EXPECT_NE(pool.get(again), nullptr);
}

TEST(ObjectPool, InvalidHandlesAreRefused) {
  ObjectPool<int, 4> pool;
  EXPECT_EQ(pool.get(kInvalidHandle), nullptr);
  EXPECT_FALSE(pool.release(kInvalidHandle));
  EXPECT_EQ(pool.get(0x0001'0009u), nullptr) << "index out of range";
  EXPECT_FALSE(pool.release(0x0001'0009u));
  const PoolHandle h = pool.acquire();
  EXPECT_EQ(pool.get(h ^ 0x0001'0000u), nullptr) << "wrong generation";
  EXPECT_EQ(pool.bad_releases(), 2u);
}

TEST(ObjectPool, GenerationWrapsButNeverZero) {
  ObjectPool<int, 1> pool;
  PoolHandle prev = kInvalidHandle;
  for (int i = 0; i < 70000; ++i) {
    const PoolHandle h = pool.acquire();
    ASSERT_NE(h, kInvalidHandle);
    ASSERT_NE(h >> 16, 0u);
    ASSERT_NE(h, prev);
    ASSERT_TRUE(pool.release(h));
    prev = h;
  }
}

}  // namespace
}  // namespace kestrel::rt

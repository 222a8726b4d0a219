// Place recognition (core/place): the vocabulary trains deterministically,
// round-trips through its file format and refuses damaged bytes; BoW
// retrieval through the inverted index agrees with brute-force descriptor
// matching, on synthetic places and on the real 7-Scenes images.
#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <random>

#include "kestrel/core/bytes.hpp"
#include "kestrel/core/vocabulary.hpp"
#include "test_data.hpp"

namespace kestrel::place_test {
namespace {

using core::BowEntry;
using core::KeyframeDatabase;
using core::OrbDescriptor;
using core::Vocabulary;

OrbDescriptor random_desc(std::mt19937_64& rng) { return {rng(), rng(), rng(), rng()}; }

OrbDescriptor flip_bits(OrbDescriptor d, int n, std::mt19937_64& rng) {
  for (int i = 0; i < n; ++i) {
    const int b = static_cast<int>(rng() % 256);
    d[b / 64] ^= 1ULL << (b % 64);
  }
  return d;
}

// Places: 300 descriptors each, drawn around 40 shared "texture" prototypes
// (so places share words, as real scenes do) plus their own ones.
struct Places {
  std::vector<std::vector<OrbDescriptor>> base;
  explicit Places(int n, uint64_t seed) {
    std::mt19937_64 rng(seed);
    std::vector<OrbDescriptor> proto;
    for (int i = 0; i < 40; ++i) proto.push_back(random_desc(rng));
    for (int p = 0; p < n; ++p) {
      std::vector<OrbDescriptor> d;
      for (int i = 0; i < 300; ++i)
        d.push_back(i % 3 == 0 ? flip_bits(proto[rng() % proto.size()], 30, rng) : random_desc(rng));
      base.push_back(d);
    }
  }
  // Seen again: 70 % of the features, each with some bits flipped, plus new clutter.
  std::vector<OrbDescriptor> view(int p, std::mt19937_64& rng) const {
    std::vector<OrbDescriptor> d;
    for (const OrbDescriptor& b : base[p])
      if (rng() % 10 < 7) d.push_back(flip_bits(b, 12, rng));
    for (int i = 0; i < 60; ++i) d.push_back(random_desc(rng));
    return d;
  }
};

Vocabulary train(const std::vector<std::vector<OrbDescriptor>>& images, int k, int levels, uint64_t seed) {
  Vocabulary::TrainOptions o;
  o.k = k;
  o.levels = levels;
  o.seed = seed;
  return Vocabulary::train(images, o);
}

// The place brute-force matching likes best: most descriptors with a
// neighbour within 64 bits that passes the 0.8 ratio test.
int brute_force_best(const std::vector<OrbDescriptor>& q, const std::vector<std::vector<OrbDescriptor>>& db) {
  int best = -1, best_n = -1;
  for (size_t p = 0; p < db.size(); ++p) {
    int n = 0;
    for (const OrbDescriptor& a : q) {
      core::BestTwoMatches bt;
      for (size_t j = 0; j < db[p].size(); ++j)
        bt.offer(core::hamming_distance(a, db[p][j]), static_cast<int>(j));
      n += bt.best_index >= 0 && bt.best <= 64 && bt.passes_ratio(0.8f);
    }
    if (n > best_n) {
      best_n = n;
      best = static_cast<int>(p);
    }
  }
  return best;
}

std::vector<BowEntry> bow(const Vocabulary& v, const std::vector<OrbDescriptor>& d) {
  std::vector<BowEntry> b(d.size());
  b.resize(static_cast<size_t>(v.transform(d.data(), static_cast<int>(d.size()), b.data())));
  return b;
}

TEST(Vocabulary, TrainsDeterministicallyAndRoundTrips) {
  Places places(30, 1);
  const Vocabulary a = train(places.base, 6, 3, 7), b = train(places.base, 6, 3, 7),
                   c = train(places.base, 6, 3, 8);
  EXPECT_GT(a.words(), 100);
  EXPECT_LE(a.words(), 216);
  EXPECT_EQ(a.serialise(), b.serialise()) << "same data and seed: same bytes";
  EXPECT_NE(a.serialise(), c.serialise());
  const std::vector<uint8_t> bytes = a.serialise();
  std::string err;
  const Vocabulary r = Vocabulary::deserialise(bytes.data(), bytes.size(), &err);
  ASSERT_EQ(err, "");
  EXPECT_EQ(r.checksum(), a.checksum());
  std::mt19937_64 rng(3);
  for (int i = 0; i < 200; ++i) {
    const OrbDescriptor d = random_desc(rng);
    ASSERT_EQ(r.word_of(d), a.word_of(d));
  }
  // A BoW vector is L1-normalised and sorted; a vector scores 1 with itself.
  const auto q = bow(a, places.base[0]);
  double sum = 0;
  for (size_t i = 0; i < q.size(); ++i) {
    sum += q[i].weight;
    if (i > 0) {
      EXPECT_LT(q[i - 1].word, q[i].word);
    }
  }
  EXPECT_NEAR(sum, 1.0, 1e-5);
  EXPECT_NEAR(core::bow_score(q.data(), static_cast<int>(q.size()), q.data(), static_cast<int>(q.size())),
              1.0, 1e-5);
}

TEST(Vocabulary, DamagedTruncatedOrForeignBytesAreRefused) {
  Places places(10, 2);
  const std::vector<uint8_t> good = train(places.base, 5, 2, 1).serialise();
  std::string err;
  std::vector<uint8_t> bad = good;
  bad[good.size() / 2] ^= 0x10;
  EXPECT_TRUE(Vocabulary::deserialise(bad.data(), bad.size(), &err).empty());
  EXPECT_NE(err.find("checksum"), std::string::npos) << err;
  EXPECT_TRUE(Vocabulary::deserialise(good.data(), good.size() - 7, &err).empty());
  EXPECT_NE(err.find("truncated"), std::string::npos) << err;
  bad = good;
  bad[0] = 'X';
  EXPECT_TRUE(Vocabulary::deserialise(bad.data(), bad.size(), &err).empty());
  EXPECT_NE(err.find("magic"), std::string::npos) << err;
  bad = good;
  bad[4] = 99;
  EXPECT_TRUE(Vocabulary::deserialise(bad.data(), bad.size(), &err).empty());
  EXPECT_NE(err.find("version"), std::string::npos) << err;
  EXPECT_TRUE(Vocabulary::deserialise(good.data(), 3, &err).empty());
  // Every truncation fails cleanly (never a crash, never a vocabulary).
  for (size_t n = 0; n < good.size(); n += 97)
    EXPECT_TRUE(Vocabulary::deserialise(good.data(), n, &err).empty());
}

// Retrieval through the inverted index finds the place brute-force matching
// finds, and the database forgets erased keyframes.
TEST(KeyframeDatabase, AgreesWithBruteForceMatchingOnSyntheticPlaces) {
  Places places(40, 4);
  const Vocabulary v = train(places.base, 10, 3, 1);
  KeyframeDatabase db(v.words(), 64, 64 * 300);
  std::vector<std::vector<BowEntry>> bows;
  for (size_t p = 0; p < places.base.size(); ++p) {
    bows.push_back(bow(v, places.base[p]));
    ASSERT_TRUE(db.add(static_cast<int>(p), bows.back().data(), static_cast<int>(bows.back().size())));
  }
  std::mt19937_64 rng(9);
  int agree = 0, n = 0;
  for (int p = 0; p < 40; ++p) {
    const std::vector<OrbDescriptor> q = places.view(p, rng);
    const auto qb = bow(v, q);
    KeyframeDatabase::Match m[3];
    const int got = db.query(qb.data(), static_cast<int>(qb.size()), {}, 0.0f, 0.0, 3, m);
    ASSERT_GT(got, 0);
    const int bf = brute_force_best(q, places.base);
    EXPECT_EQ(bf, p);
    agree += m[0].keyframe == bf;
    ++n;
  }
  std::printf("BoW top-1 agrees with brute-force matching on %d of %d queries\n", agree, n);
  EXPECT_GE(agree, 38);
  // Erased keyframes are not found; skip() leaves keyframes out.
  db.erase(5, bows[5].data(), static_cast<int>(bows[5].size()));
  KeyframeDatabase::Match m[40];
  const auto qb = bow(v, places.base[5]);
  const int got = db.query(
      qb.data(), static_cast<int>(qb.size()), [](int k) { return k == 6; }, 0.0f, 0.0, 40, m);
  for (int i = 0; i < got; ++i) {
    EXPECT_NE(m[i].keyframe, 5);
    EXPECT_NE(m[i].keyframe, 6);
  }
  EXPECT_EQ(db.size(), 39);
}

// Real images (7-Scenes, a hand-held Kinect): a vocabulary trained on every
// 7th frame, a database of every 20th frame, queries 4 frames after each:
// BoW's best keyframe is brute-force matching's best.
TEST(KeyframeDatabase, AgreesWithBruteForceMatchingOnRealImages) {
  const std::string dir = std::string(KESTREL_SHARED_DATA) + "/real-rgbd/7scenes_first500";
  if (!std::filesystem::exists(dir)) GTEST_SKIP() << "SKIPPED: ../shared/data not found (" << dir << ")";
  core::OrbOptions oo;
  oo.n_features = 500;
  core::OrbExtractor ex(oo, 640, 480);
  core::OrbFeatures f(500);
  auto desc_of = [&](int i) {
    char name[64];
    std::snprintf(name, sizeof name, "/frame-%06d.color.jpg", i);
    const cv::Mat img = cv::imread(dir + name, cv::IMREAD_GRAYSCALE);
    std::vector<OrbDescriptor> d;
    if (img.empty()) return d;
    const ImageView view{img.cols, img.rows, static_cast<int>(img.step[0]), PixelFormat::kGray8, img.data};
    if (ex.extract(view, f) != core::OrbStatus::kOk) return d;
    for (int j = 0; j < f.size(); ++j) d.push_back(f.descriptor(j));
    return d;
  };
  std::vector<std::vector<OrbDescriptor>> train_set;
  for (int i = 0; i < 500; i += 7) train_set.push_back(desc_of(i));
  const Vocabulary v = train(train_set, 10, 3, 1);
  std::vector<std::vector<OrbDescriptor>> db_desc;
  KeyframeDatabase db(v.words(), 64, 64 * 500);
  for (int i = 3, k = 0; i < 500; i += 20, ++k) {
    db_desc.push_back(desc_of(i));
    const auto b = bow(v, db_desc.back());
    ASSERT_TRUE(db.add(k, b.data(), static_cast<int>(b.size())));
  }
  int agree = 0, n = 0;
  for (int i = 7; i < 500; i += 20) {
    const auto q = desc_of(i);
    const auto qb = bow(v, q);
    KeyframeDatabase::Match m[1];
    if (db.query(qb.data(), static_cast<int>(qb.size()), {}, 0.0f, 0.0, 1, m) < 1) continue;
    const int bf = brute_force_best(q, db_desc);
    agree += m[0].keyframe == bf;
    ++n;
  }
  std::printf("7-Scenes: BoW top-1 agrees with brute-force matching on %d of %d queries (%d words)\n", agree,
              n, v.words());
  EXPECT_GE(agree, n * 8 / 10);
}

TEST(Bytes, Crc32IsZlibs) {
  const char* s = "123456789";
  EXPECT_EQ(core::crc32(reinterpret_cast<const uint8_t*>(s), 9), 0xCBF43926u);
}

}  // namespace
}  // namespace kestrel::place_test

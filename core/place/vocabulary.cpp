#include "kestrel/core/vocabulary.hpp"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>

#include "kestrel/core/bytes.hpp"

namespace kestrel::core {

double bow_score(const BowEntry* a, int na, const BowEntry* b, int nb) {
  double s = 0.0;
  int i = 0, j = 0;
  while (i < na && j < nb) {
    if (a[i].word < b[j].word) {
      ++i;
    } else if (b[j].word < a[i].word) {
      ++j;
    } else {
      const double x = a[i].weight, y = b[j].weight;
      s += std::abs(x) + std::abs(y) - std::abs(x - y);
      ++i;
      ++j;
    }
  }
  return 0.5 * s;
}

namespace {

// Bitwise majority of a set of descriptors (ties: 0).
OrbDescriptor majority(const std::vector<const OrbDescriptor*>& set) {
  OrbDescriptor out{};
  const size_t half = set.size() / 2;
  for (int w = 0; w < 4; ++w) {
    for (int b = 0; b < 64; ++b) {
      size_t ones = 0;
      const uint64_t bit = 1ULL << b;
      for (const OrbDescriptor* d : set) ones += ((*d)[w] & bit) != 0;
      if (ones > half) out[w] |= bit;
    }
  }
  return out;
}

double uniform01(std::mt19937_64& rng) { return static_cast<double>(rng() >> 11) * 0x1.0p-53; }

struct Builder {
  const Vocabulary::TrainOptions& opt;
  std::mt19937_64 rng;
  struct BuildNode {
    OrbDescriptor desc{};
    int32_t first_child = -1, n_children = 0;
  };
  std::vector<BuildNode> nodes;

  // Clusters `set` under node `parent` at `level` (the root is level 0).
  void build(int parent, std::vector<const OrbDescriptor*>& set, int level) {
    if (level >= opt.levels || set.size() <= 1) return;
    std::vector<OrbDescriptor> centers;
    std::vector<int> assign(set.size(), 0);
    if (static_cast<int>(set.size()) <= opt.k) {
      for (const OrbDescriptor* d : set) centers.push_back(*d);
      std::iota(assign.begin(), assign.end(), 0);
    } else {
      // k-means++ seeding under the Hamming distance.
      std::vector<double> d2(set.size(), 0.0);
      centers.push_back(*set[rng() % set.size()]);
      while (static_cast<int>(centers.size()) < opt.k) {
        double total = 0;
        for (size_t i = 0; i < set.size(); ++i) {
          int best = 257;
          for (const OrbDescriptor& c : centers) best = std::min(best, hamming_distance(*set[i], c));
          d2[i] = static_cast<double>(best) * best;
          total += d2[i];
        }
        if (total <= 0) break;  // fewer distinct descriptors than k
        double r = uniform01(rng) * total;
        size_t pick = 0;
        for (; pick + 1 < set.size(); ++pick) {
          r -= d2[pick];
          if (r <= 0) break;
        }
        centers.push_back(*set[pick]);
      }
      // k-majority iterations.
      for (int it = 0; it < opt.max_iterations; ++it) {
        bool changed = it == 0;
        for (size_t i = 0; i < set.size(); ++i) {
          int best = 257, arg = 0;
          for (size_t c = 0; c < centers.size(); ++c) {
            const int h = hamming_distance(*set[i], centers[c]);
            if (h < best) {
              best = h;
              arg = static_cast<int>(c);
            }
          }
          if (assign[i] != arg) changed = true;
          assign[i] = arg;
        }
        if (!changed) break;
        std::vector<std::vector<const OrbDescriptor*>> members(centers.size());
        for (size_t i = 0; i < set.size(); ++i) members[assign[i]].push_back(set[i]);
        for (size_t c = 0; c < centers.size(); ++c)
          if (!members[c].empty()) centers[c] = majority(members[c]);
      }
    }
    std::vector<std::vector<const OrbDescriptor*>> members(centers.size());
    for (size_t i = 0; i < set.size(); ++i) members[assign[i]].push_back(set[i]);
    const int first = static_cast<int>(nodes.size());
    int n = 0;
    std::vector<int> child_of(centers.size(), -1);
    for (size_t c = 0; c < centers.size(); ++c) {
      if (members[c].empty()) continue;
      BuildNode b;
      b.desc = centers[c];
      nodes.push_back(b);
      child_of[c] = first + n++;
    }
    nodes[parent].first_child = first;
    nodes[parent].n_children = n;
    for (size_t c = 0; c < centers.size(); ++c)
      if (child_of[c] >= 0) build(child_of[c], members[c], level + 1);
  }
};

}  // namespace

Vocabulary Vocabulary::train(const std::vector<std::vector<OrbDescriptor>>& images, const TrainOptions& opt) {
  Builder b{opt, std::mt19937_64(opt.seed), {}};
  std::vector<const OrbDescriptor*> all;
  for (const auto& im : images)
    for (const OrbDescriptor& d : im) all.push_back(&d);
  b.nodes.push_back(Builder::BuildNode{});
  b.build(0, all, 0);
  Vocabulary v;
  v.k_ = opt.k;
  v.levels_ = opt.levels;
  v.pattern_seed_ = opt.pattern_seed;
  v.nodes_.resize(b.nodes.size());
  for (size_t i = 0; i < b.nodes.size(); ++i) {
    v.nodes_[i].desc = b.nodes[i].desc;
    v.nodes_[i].first_child = b.nodes[i].first_child;
    v.nodes_[i].n_children = b.nodes[i].n_children;
  }
  v.finish();
  // Inverse document frequency over the training images.
  std::vector<int> docs(static_cast<size_t>(v.words_), 0);
  std::vector<int32_t> last(static_cast<size_t>(v.words_), -1);
  for (size_t im = 0; im < images.size(); ++im) {
    for (const OrbDescriptor& d : images[im]) {
      const uint32_t w = v.word_of(d);
      if (last[w] != static_cast<int32_t>(im)) {
        last[w] = static_cast<int32_t>(im);
        ++docs[w];
      }
    }
  }
  const double N = static_cast<double>(std::max<size_t>(1, images.size()));
  for (int w = 0; w < v.words_; ++w)
    v.idf_[w] = docs[w] > 0 ? static_cast<float>(std::log(N / docs[w])) : 0.0f;
  v.finish();
  return v;
}

void Vocabulary::finish() {
  words_ = 0;
  for (Node& n : nodes_) n.word = n.n_children == 0 && (&n != &nodes_[0]) ? words_++ : -1;
  idf_.resize(static_cast<size_t>(words_), 0.0f);
  // The CRC of everything but the file's own trailing CRC: a CRC over a
  // message followed by its CRC is the same for every message of a length,
  // so the whole image's would not tell two vocabularies of one size apart.
  std::vector<uint8_t> b = serialise();
  checksum_ = crc32(b.data(), b.size() - 4);
}

uint32_t Vocabulary::word_of(const OrbDescriptor& d) const {
  int node = 0;
  while (nodes_[node].n_children > 0) {
    const Node& n = nodes_[node];
    int best = 257, arg = n.first_child;
    for (int c = n.first_child; c < n.first_child + n.n_children; ++c) {
      const int h = hamming_distance(d, nodes_[c].desc);
      if (h < best) {
        best = h;
        arg = c;
      }
    }
    node = arg;
  }
  return nodes_[node].word >= 0 ? static_cast<uint32_t>(nodes_[node].word) : 0u;
}

int Vocabulary::transform(const OrbDescriptor* d, int n, BowEntry* out, uint32_t* word_of_feature) const {
  if (words_ == 0 || n <= 0) return 0;
  for (int i = 0; i < n; ++i) {
    const uint32_t w = word_of(d[i]);
    if (word_of_feature != nullptr) word_of_feature[i] = w;
    out[i] = BowEntry{w, 1.0f};
  }
  std::sort(out, out + n, [](const BowEntry& a, const BowEntry& b) { return a.word < b.word; });
  int m = 0;
  for (int i = 0; i < n; ++i) {
    if (m > 0 && out[m - 1].word == out[i].word) {
      out[m - 1].weight += 1.0f;
    } else {
      out[m++] = out[i];
    }
  }
  // tf-idf, L1 normalised; words in every training image carry nothing.
  double sum = 0;
  int k = 0;
  for (int i = 0; i < m; ++i) {
    const float v = out[i].weight / static_cast<float>(n) * idf_[out[i].word];
    if (v <= 0) continue;
    out[k++] = BowEntry{out[i].word, v};
    sum += v;
  }
  if (sum > 0)
    for (int i = 0; i < k; ++i) out[i].weight = static_cast<float>(out[i].weight / sum);
  return k;
}

std::vector<uint8_t> Vocabulary::serialise() const {
  std::vector<uint8_t> p;
  ByteWriter w(p);
  w.u32(static_cast<uint32_t>(k_));
  w.u32(static_cast<uint32_t>(levels_));
  w.u64(pattern_seed_);
  w.u32(static_cast<uint32_t>(nodes_.size()));
  for (const Node& n : nodes_) {
    for (uint64_t x : n.desc) w.u64(x);
    w.i32(n.first_child);
    w.i32(n.n_children);
  }
  w.u32(static_cast<uint32_t>(idf_.size()));
  for (float f : idf_) w.f32(f);
  return seal(kMagic, kVersion, p);
}

Vocabulary Vocabulary::deserialise(const uint8_t* data, size_t n, std::string* error) {
  const uint8_t* p = nullptr;
  size_t pn = 0;
  std::string e = open_sealed(data, n, kMagic, kVersion, &p, &pn);
  Vocabulary v;
  auto fail = [&](const std::string& why) {
    if (error != nullptr) *error = why;
    return Vocabulary{};
  };
  if (!e.empty()) return fail(e);
  ByteReader r(p, pn);
  v.k_ = static_cast<int>(r.u32());
  v.levels_ = static_cast<int>(r.u32());
  v.pattern_seed_ = r.u64();
  const uint32_t n_nodes = r.u32();
  if (!r.ok() || n_nodes == 0 || n_nodes > r.remaining() / 40)
    return fail("bad node count " + std::to_string(n_nodes));
  v.nodes_.resize(n_nodes);
  for (Node& nd : v.nodes_) {
    for (uint64_t& x : nd.desc) x = r.u64();
    nd.first_child = r.i32();
    nd.n_children = r.i32();
  }
  const uint32_t n_words = r.u32();
  if (!r.ok() || n_words > r.remaining() / 4) return fail("bad word count");
  std::vector<float> idf(n_words);
  for (float& f : idf) f = r.f32();
  if (!r.ok() || r.remaining() != 0) return fail("payload size does not match its contents");
  // The tree must be a tree: children after their parent, inside the array,
  // and the leaves as many as the words.
  for (uint32_t i = 0; i < n_nodes; ++i) {
    const Node& nd = v.nodes_[i];
    if (nd.n_children < 0 ||
        (nd.n_children > 0 && (nd.first_child <= static_cast<int32_t>(i) ||
                               static_cast<int64_t>(nd.first_child) + nd.n_children > n_nodes)))
      return fail("node " + std::to_string(i) + ": children out of range");
  }
  v.finish();
  // A root without children has no leaves: every descriptor would map to no
  // word, and the idf table would be read out of range (found by fuzzing).
  if (v.words_ == 0) return fail("the tree has no words (the root has no children)");
  if (static_cast<uint32_t>(v.words_) != n_words) {
    return fail("the tree has " + std::to_string(v.words_) + " leaves but " + std::to_string(n_words) +
                " word weights");
  }
  v.idf_ = idf;
  v.finish();
  return v;
}

// ---- inverted index ----------------------------------------------------------------

KeyframeDatabase::KeyframeDatabase(int n_words, int max_keyframes, int max_entries)
    : head_(static_cast<size_t>(std::max(n_words, 1)), -1),
      pool_(static_cast<size_t>(std::max(max_entries, 1))),
      in_(static_cast<size_t>(max_keyframes), 0),
      acc_(static_cast<size_t>(max_keyframes), 0.0f),
      common_(static_cast<size_t>(max_keyframes), 0) {
  for (size_t i = 0; i < pool_.size(); ++i)
    pool_[i].next = i + 1 < pool_.size() ? static_cast<int32_t>(i + 1) : -1;
  free_ = 0;
  touched_.reserve(static_cast<size_t>(max_keyframes));
}

bool KeyframeDatabase::add(int kf, const BowEntry* bow, int n) {
  if (kf < 0 || kf >= static_cast<int>(in_.size()) || in_[kf]) return false;
  int avail = 0;
  for (int32_t e = free_; e >= 0 && avail < n; e = pool_[e].next) ++avail;
  if (avail < n) return false;
  for (int i = 0; i < n; ++i) {
    if (bow[i].word >= head_.size()) continue;
    const int32_t e = free_;
    free_ = pool_[e].next;
    pool_[e] = Entry{kf, bow[i].weight, head_[bow[i].word]};
    head_[bow[i].word] = e;
  }
  in_[kf] = 1;
  ++n_kf_;
  return true;
}

void KeyframeDatabase::erase(int kf, const BowEntry* bow, int n) {
  if (!contains(kf)) return;
  for (int i = 0; i < n; ++i) {
    if (bow[i].word >= head_.size()) continue;
    int32_t* link = &head_[bow[i].word];
    while (*link >= 0) {
      if (pool_[*link].kf == kf) {
        const int32_t e = *link;
        *link = pool_[e].next;
        pool_[e].next = free_;
        free_ = e;
        break;
      }
      link = &pool_[*link].next;
    }
  }
  in_[kf] = 0;
  --n_kf_;
}

int KeyframeDatabase::query(const BowEntry* q, int nq, const std::function<bool(int)>& skip, float min_score,
                            double min_common_share, int max_out, Match* out) const {
  touched_.clear();
  for (int i = 0; i < nq; ++i) {
    if (q[i].word >= head_.size()) continue;
    for (int32_t e = head_[q[i].word]; e >= 0; e = pool_[e].next) {
      const Entry& en = pool_[e];
      if (common_[en.kf] == 0) touched_.push_back(en.kf);
      ++common_[en.kf];
      const float x = q[i].weight, y = en.weight;
      acc_[en.kf] += std::abs(x) + std::abs(y) - std::abs(x - y);
    }
  }
  int max_common = 0;
  for (int32_t kf : touched_)
    if (!(skip && skip(kf))) max_common = std::max(max_common, common_[kf]);
  std::vector<Match> all;
  for (int32_t kf : touched_) {
    const float s = 0.5f * acc_[kf];
    if (!(skip && skip(kf)) && common_[kf] >= min_common_share * max_common && s >= min_score)
      all.push_back(Match{kf, s, common_[kf]});
    common_[kf] = 0;
    acc_[kf] = 0.0f;
  }
  std::sort(all.begin(), all.end(), [](const Match& a, const Match& b) {
    return a.score != b.score ? a.score > b.score : a.keyframe < b.keyframe;
  });
  const int n = std::min(max_out, static_cast<int>(all.size()));
  std::copy(all.begin(), all.begin() + n, out);
  return n;
}

}  // namespace kestrel::core

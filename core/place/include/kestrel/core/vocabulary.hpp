// Place recognition over our own 256-bit ORB descriptors: a bag of binary
// words (Galvez-Lopez and Tardos, "Bags of Binary Words for Fast Place
// Recognition in Image Sequences", TRO 2012, the DBoW2 of ORB-SLAM) written
// small for Kestrel, since Debian has no DBoW2/3:
//
//  - Vocabulary: a tree of k-majority clusters, k children per node, `levels`
//    deep; its leaves are the words. Trained by hierarchical k-majority
//    (k-means++ seeding under the Hamming distance, cluster centres by
//    bitwise majority), words weighted by their inverse document frequency
//    log(N / N_w) over the N training images.
//  - BoW vector of an image: per word tf-idf (count / features x idf), L1
//    normalised, sorted by word; the L1 score of two such vectors,
//    s = 1 - |a - b|_1 / 2 in [0, 1].
//  - KeyframeDatabase: the inverted index (word -> keyframes that contain it)
//    answering "which keyframes look like this" without visiting the others.
//
// A vocabulary belongs to a BRIEF test pattern (OrbOptions::pattern_seed):
// descriptors of another pattern are other words. docs/map.md.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "kestrel/core/orb.hpp"

namespace kestrel::core {

struct BowEntry {
  uint32_t word = 0;
  float weight = 0.0f;
};

// L1 score of two L1-normalised BoW vectors sorted by word, in [0, 1].
double bow_score(const BowEntry* a, int na, const BowEntry* b, int nb);

class Vocabulary {
 public:
  struct TrainOptions {
    int k = 10;               // branching factor
    int levels = 4;           // depth: up to k^levels words
    int max_iterations = 10;  // k-majority iterations per node
    uint64_t seed = 1;
    uint64_t pattern_seed = OrbOptions{}.pattern_seed;  // of the descriptors trained on (recorded)
  };
  static constexpr char kMagic[4] = {'K', 'V', 'O', 'C'};
  static constexpr uint32_t kVersion = 1;

  Vocabulary() = default;
  // images: the descriptors of each training image (the documents of the idf).
  static Vocabulary train(const std::vector<std::vector<OrbDescriptor>>& images, const TrainOptions& opt);

  bool empty() const { return words_ == 0; }
  int words() const { return words_; }
  int nodes() const { return static_cast<int>(nodes_.size()); }
  int k() const { return k_; }
  int levels() const { return levels_; }
  uint64_t pattern_seed() const { return pattern_seed_; }
  // A fingerprint of the tree and weights: a map records the vocabulary its
  // BoW vectors came from.
  uint32_t checksum() const { return checksum_; }
  float idf(uint32_t word) const { return idf_[word]; }

  // The word of one descriptor (descending the tree by Hamming distance).
  uint32_t word_of(const OrbDescriptor& d) const;
  // The BoW vector of n descriptors into out (capacity >= n): returns the
  // number of entries. word_of_feature (optional, n entries) gets each
  // descriptor's word. Allocation-free.
  int transform(const OrbDescriptor* d, int n, BowEntry* out, uint32_t* word_of_feature = nullptr) const;

  // The vocabulary file's bytes (bytes.hpp: magic KVOC, version, CRC-32).
  std::vector<uint8_t> serialise() const;
  // From those bytes; on failure an empty vocabulary and *error says why.
  static Vocabulary deserialise(const uint8_t* data, size_t n, std::string* error);

 private:
  struct Node {
    OrbDescriptor desc{};
    int32_t first_child = -1;  // children are contiguous
    int32_t n_children = 0;
    int32_t word = -1;  // leaves only
  };
  void finish();  // word table and checksum
  std::vector<Node> nodes_;
  std::vector<float> idf_;
  int words_ = 0, k_ = 0, levels_ = 0;
  uint64_t pattern_seed_ = 0;
  uint32_t checksum_ = 0;
};

// The inverted index: for every word, the keyframes whose BoW vector has it
// (with its weight). Sized once: max_entries (keyframes x features) entries
// in a pool, freed when a keyframe is erased. Not real time (the loop thread).
class KeyframeDatabase {
 public:
  struct Match {
    int32_t keyframe = -1;
    float score = 0.0f;  // L1 score with the query
    int common_words = 0;
  };
  KeyframeDatabase(int n_words, int max_keyframes, int max_entries);
  // False when the pool is full (the keyframe is then not searchable).
  bool add(int kf, const BowEntry* bow, int n);
  void erase(int kf, const BowEntry* bow, int n);
  bool contains(int kf) const { return kf >= 0 && kf < static_cast<int>(in_.size()) && in_[kf]; }
  // Keyframes sharing at least min_common_share x (the best one's common
  // words) with the query and scoring at least min_score, best first, at
  // most max_out; those with skip(kf) are left out. Returns how many.
  int query(const BowEntry* q, int nq, const std::function<bool(int)>& skip, float min_score,
            double min_common_share, int max_out, Match* out) const;
  int size() const { return n_kf_; }

 private:
  struct Entry {
    int32_t kf;
    float weight;
    int32_t next;
  };
  std::vector<int32_t> head_;
  std::vector<Entry> pool_;
  int32_t free_ = -1;
  std::vector<uint8_t> in_;
  int n_kf_ = 0;
  mutable std::vector<float> acc_;
  mutable std::vector<int32_t> common_, touched_;
};

}  // namespace kestrel::core

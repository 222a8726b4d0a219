// ORB features (FAST-9 corners + steered BRIEF) in fixed memory, for the
// tracking thread (paper 000, "IMU accelerated pose calculation": re-mapping,
// FAST scoring, smoothing, non-maximal suppression, BRIEF).
//
// Every buffer is sized in the OrbExtractor constructor from the largest image
// it will see; extract() then performs no heap allocation, takes no lock and
// does no I/O, so the tracker may call it per frame. Design, memory sizing and
// the measured comparison with cv::ORB: docs/orb.md.
//
// Coordinates: pixel centres at integer positions, x right, y down (level 0 =
// the input image). Angles are in the same axes, so a positive angle turns x
// towards y (clockwise on screen), in [0, 2*pi).
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/msgs.hpp"

namespace kestrel::core {

struct OrbOptions {
  int n_features = 300;       // total budget over all levels
  int n_levels = 4;           // pyramid levels (1 = no pyramid), at most kMaxLevels
  float scale_factor = 1.2f;  // linear size ratio between consecutive levels, in (1, 2]
  int fast_threshold = 20;    // FAST intensity threshold [grey levels]
  // Used only inside grid cells that have no corner at fast_threshold
  // (ORB-SLAM's idea): keeps features in low-contrast parts of the image.
  int fast_threshold_min = 7;
  // Keypoints keep this far from the border of their level [level pixels].
  // At least kMinEdgeMargin: the orientation patch (radius 15) must fit.
  int edge_margin = 16;
  int cell_size = 40;                              // bucketing grid cell side [level pixels]
  uint64_t pattern_seed = 0x4b657374'72656c31ULL;  // BRIEF test pattern seed

  static constexpr int kMaxLevels = 8;
  static constexpr int kMinEdgeMargin = 16;

  // Empty when usable, else one line per bad field ("field: reason").
  [[nodiscard]] std::string validate() const;
  // Every effective setting, one "key: value" per line.
  [[nodiscard]] std::string to_string() const;
};

// 256 BRIEF tests, bit i of word i/64 = I(a_i) < I(b_i).
using OrbDescriptor = std::array<uint64_t, 4>;

struct OrbKeypoint {
  float x = 0;  // level-0 pixels
  float y = 0;
  float angle_rad = 0;  // intensity-centroid orientation, [0, 2*pi)
  float response = 0;   // FAST score: largest threshold at which it is still a corner
  float size = 0;       // patch diameter in level-0 pixels (31 * level scale)
  int16_t level = 0;
  int16_t x_level = 0;  // integer position in its own level
  int16_t y_level = 0;
};

// Output of one extract(): keypoints and descriptors side by side, in two
// arrays allocated once (by the constructor or reserve()). Keypoints come
// level by level, strongest first within a level.
class OrbFeatures {
 public:
  OrbFeatures() = default;
  explicit OrbFeatures(int capacity) { reserve(capacity); }
  OrbFeatures(const OrbFeatures& o);
  OrbFeatures& operator=(const OrbFeatures& o);
  OrbFeatures(OrbFeatures&&) noexcept = default;
  OrbFeatures& operator=(OrbFeatures&&) noexcept = default;

  // Allocates (start-up only); drops the current content.
  void reserve(int capacity);
  void clear() noexcept { size_ = 0; }
  // False when full: capacity is a start-up decision.
  bool push_back(const OrbKeypoint& kp, const OrbDescriptor& d) noexcept;

  [[nodiscard]] int size() const noexcept { return size_; }
  [[nodiscard]] int capacity() const noexcept { return capacity_; }
  [[nodiscard]] bool empty() const noexcept { return size_ == 0; }
  [[nodiscard]] const OrbKeypoint& keypoint(int i) const noexcept { return kp_[i]; }
  [[nodiscard]] const OrbDescriptor& descriptor(int i) const noexcept { return desc_[i]; }
  [[nodiscard]] const OrbKeypoint* keypoints() const noexcept { return kp_.get(); }
  [[nodiscard]] const OrbDescriptor* descriptors() const noexcept { return desc_.get(); }

 private:
  std::unique_ptr<OrbKeypoint[]> kp_;
  std::unique_ptr<OrbDescriptor[]> desc_;
  int size_ = 0;
  int capacity_ = 0;
};

enum class OrbStatus : uint8_t {
  kOk = 0,
  kNullImage,          // data == nullptr, or width/height/stride not positive or inconsistent
  kUnsupportedFormat,  // only Gray8, Rgb8, Bgr8
  kImageTooLarge,      // larger than the size given to the constructor
  kOutputTooSmall,     // out.capacity() < n_features
};
const char* to_string(OrbStatus s);

// What the last extract() did, per level, for counters and tuning.
struct OrbExtractStats {
  int n_levels_used = 0;                                 // levels large enough to search
  std::array<int, OrbOptions::kMaxLevels> budget{};      // target after carry-over
  std::array<int, OrbOptions::kMaxLevels> corners{};     // FAST corners at fast_threshold_min, before NMS
  std::array<int, OrbOptions::kMaxLevels> candidates{};  // after 3x3 non-maximal suppression
  std::array<int, OrbOptions::kMaxLevels> selected{};
  std::array<int, OrbOptions::kMaxLevels> weak_cells{};  // cells served at fast_threshold_min
  std::array<int, OrbOptions::kMaxLevels>
      candidate_overflow{};  // dropped: candidate buffer full (never, by sizing)
};

class OrbExtractor {
 public:
  // Allocates everything extract() will need for images up to
  // max_width x max_height. Throws std::invalid_argument on bad options/sizes.
  OrbExtractor(const OrbOptions& opt, int max_width, int max_height);
  ~OrbExtractor();
  OrbExtractor(const OrbExtractor&) = delete;
  OrbExtractor& operator=(const OrbExtractor&) = delete;

  // Real-time: no heap allocation. Accepts Gray8, Rgb8, Bgr8 of any size up to
  // the maximum (any stride). On error `out` is left empty and the status says
  // why; a blank or tiny image is not an error (zero features).
  OrbStatus extract(const ImageView& image, OrbFeatures& out) noexcept;

  [[nodiscard]] const OrbOptions& options() const noexcept { return opt_; }
  [[nodiscard]] const OrbExtractStats& last_stats() const noexcept { return stats_; }
  [[nodiscard]] int max_width() const noexcept { return max_w_; }
  [[nodiscard]] int max_height() const noexcept { return max_h_; }
  // Bytes held by the extractor's preallocated buffers (docs/orb.md, sizing).
  [[nodiscard]] std::size_t buffer_bytes() const noexcept;
  // Scale of `level` relative to level 0 (scale_factor^level, nominal).
  [[nodiscard]] float level_scale(int level) const noexcept { return level_scale_[level]; }
  // Budget per level before carry-over: geometric in 1/scale_factor.
  [[nodiscard]] int level_budget(int level) const noexcept { return level_budget_[level]; }

 private:
  struct Impl;
  OrbOptions opt_;
  int max_w_ = 0;
  int max_h_ = 0;
  std::array<float, OrbOptions::kMaxLevels> level_scale_{};
  std::array<int, OrbOptions::kMaxLevels> level_budget_{};
  OrbExtractStats stats_;
  std::unique_ptr<Impl> impl_;
};

// Bits set in a 64-bit word. Where the target has a population-count
// instruction (x86 with POPCNT, which the portable x86-64 baseline lacks, and
// every AArch64) the builtin is one instruction; elsewhere GCC turns the builtin
// into a call into libgcc, and the branch-free bit-slicing sum stays inline.
inline int popcount64(std::uint64_t x) noexcept {
#if defined(__POPCNT__) || defined(__aarch64__)
  return __builtin_popcountll(x);
#else
  x -= (x >> 1) & 0x5555555555555555ULL;
  x = (x & 0x3333333333333333ULL) + ((x >> 2) & 0x3333333333333333ULL);
  x = (x + (x >> 4)) & 0x0f0f0f0f0f0f0f0fULL;
  return static_cast<int>((x * 0x0101010101010101ULL) >> 56);
#endif
}

// Hamming distance between two descriptors (0..256).
inline int hamming_distance(const OrbDescriptor& a, const OrbDescriptor& b) noexcept {
  return popcount64(a[0] ^ b[0]) + popcount64(a[1] ^ b[1]) + popcount64(a[2] ^ b[2]) +
         popcount64(a[3] ^ b[3]);
}

// The nearest and second-nearest descriptor distance seen so far, for
// Lowe's ratio test.
struct BestTwoMatches {
  static constexpr int kNone = 1 << 30;
  int best = kNone;
  int second = kNone;
  int best_index = -1;
  void offer(int distance, int index) noexcept {
    if (distance < best) {
      second = best;
      best = distance;
      best_index = index;
    } else if (distance < second) {
      second = distance;
    }
  }
  bool passes_ratio(float ratio) const noexcept { return second == kNone || best < ratio * second; }
};

struct OrbMatch {
  int query = 0;     // index into the first set
  int train = 0;     // index into the second set
  int distance = 0;  // Hamming
};

// Brute-force nearest neighbour with Lowe's ratio test (best < ratio * second
// best) and an absolute distance cap. For tests, benchmarks and tools: it
// allocates and is O(n*m), so the tracking thread does not use it.
std::vector<OrbMatch> match_brute_force(const OrbDescriptor* query, int n_query, const OrbDescriptor* train,
                                        int n_train, float ratio = 0.8f, int max_distance = 256);
inline std::vector<OrbMatch> match_brute_force(const OrbFeatures& query, const OrbFeatures& train,
                                               float ratio = 0.8f, int max_distance = 256) {
  return match_brute_force(query.descriptors(), query.size(), train.descriptors(), train.size(), ratio,
                           max_distance);
}

}  // namespace kestrel::core

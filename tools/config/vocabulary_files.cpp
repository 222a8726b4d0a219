#include "kestrel/tools/vocabulary_files.hpp"

#include <cstdio>
#include <fstream>
#include <iterator>
#include <stdexcept>
#include <vector>

namespace kestrel::tools {
namespace detail {
extern const unsigned char kDefaultVocabulary[];
extern const unsigned long kDefaultVocabularySize;
}  // namespace detail

namespace {
std::shared_ptr<const core::Vocabulary> from_bytes(const uint8_t* p, size_t n, const std::string& where,
                                                   uint64_t pattern_seed) {
  std::string err;
  auto v = std::make_shared<core::Vocabulary>(core::Vocabulary::deserialise(p, n, &err));
  if (!err.empty()) throw std::runtime_error(where + ": not a usable vocabulary: " + err);
  if (v->pattern_seed() != pattern_seed) {
    throw std::runtime_error(where + ": trained on ORB descriptors of BRIEF pattern seed " +
                             std::to_string(v->pattern_seed()) + ", the tracker uses " +
                             std::to_string(pattern_seed) +
                             " (frontend.orb.pattern_seed): retrain it with kestrel vocab");
  }
  return v;
}
}  // namespace

std::shared_ptr<const core::Vocabulary> load_vocabulary(const std::string& path, uint64_t pattern_seed) {
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error(path + ": cannot open vocabulary file");
  const std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  return from_bytes(bytes.data(), bytes.size(), path, pattern_seed);
}

std::shared_ptr<const core::Vocabulary> default_vocabulary() {
  static const std::shared_ptr<const core::Vocabulary> v = []() -> std::shared_ptr<const core::Vocabulary> {
    if (detail::kDefaultVocabularySize == 0) return nullptr;
    return from_bytes(detail::kDefaultVocabulary, detail::kDefaultVocabularySize,
                      "the built-in vocabulary (configs/vocabulary/kestrel_orb_k10l4.kvoc)",
                      core::OrbOptions{}.pattern_seed);
  }();
  return v;
}

void resolve_vocabulary(core::EstimatorConfig& c) {
  core::MapSystemOptions& m = c.window.map;
  // "auto" is window on any log with an IMU: without this the default
  // `kestrel replay LOG` ran its map without loop closing or relocalisation.
  const bool windowed = c.backend == "auto" || c.backend.rfind("window", 0) == 0;
  if (!(windowed || (c.backend == "ekf" && c.ekf.mapping)) || !m.mapping || !m.loop || m.vocabulary) return;
  if (!m.vocabulary_path.empty()) {
    m.vocabulary = load_vocabulary(m.vocabulary_path, c.tracker.orb.pattern_seed);
    return;
  }
  if (c.tracker.orb.pattern_seed == core::OrbOptions{}.pattern_seed) m.vocabulary = default_vocabulary();
  if (!m.vocabulary) {
    std::fprintf(
        stderr,
        "WARNING: no place-recognition vocabulary (kestrel was built without one, or the BRIEF pattern is "
        "not the default): the map runs WITHOUT loop closing and relocalisation; set map.vocabulary to a "
        "file made by `kestrel vocab` (docs/map.md)\n");
    m.loop = false;
  }
}

}  // namespace kestrel::tools

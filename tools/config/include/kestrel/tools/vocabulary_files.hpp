// The place-recognition vocabulary as files: core turns a vocabulary into
// bytes and back (core/place), this reads and writes them, and holds the
// default one compiled into `kestrel` (configs/vocabulary/, docs/map.md).
#pragma once

#include <memory>
#include <string>

#include "kestrel/core/estimator_config.hpp"
#include "kestrel/core/vocabulary.hpp"

namespace kestrel::tools {

// Throws std::runtime_error naming the file and the problem (missing,
// truncated, damaged, foreign, another BRIEF pattern than `pattern_seed`).
std::shared_ptr<const core::Vocabulary> load_vocabulary(const std::string& path, uint64_t pattern_seed);
// The vocabulary compiled into kestrel; nullptr when it was built without one.
std::shared_ptr<const core::Vocabulary> default_vocabulary();
// Gives a window (or auto) backend with the map and the loop its vocabulary
// (map.vocabulary, or the default). Without any it says so on stderr and
// turns the loop off: the map still runs, without loop closing.
void resolve_vocabulary(core::EstimatorConfig& c);

}  // namespace kestrel::tools

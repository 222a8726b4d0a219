// Shared by the map's whole-pipeline tests (kidnap, map reuse, soak): the
// simulated figure-8 they fly and the window backend with the map, loop
// closing and relocalisation on (the built-in vocabulary).
#pragma once

#include <gtest/gtest.h>

#include <cstdint>
#include <string>

#include "kestrel/core/estimator_config.hpp"
#include "kestrel/tools/simulator.hpp"
#include "kestrel/tools/vocabulary_files.hpp"

namespace kestrel::map_test {

inline tools::SimOptions figure8(double duration_s, uint64_t seed, int width, int height) {
  tools::SimOptions so;
  so.scenario = "figure8";
  so.duration_s = duration_s;
  so.seed = seed;
  so.width = width;
  so.height = height;
  so.threads = 2;
  return so;
}

// `backend` "ekf": the filter with the same map (ekf.mapping).
inline core::EstimatorConfig map_config(const std::string& backend = "window") {
  core::EstimatorConfig c = core::EstimatorConfig::defaults(backend);
  c.window.map.mapping = true;
  c.window.map.loop = true;
  c.ekf.mapping = backend == "ekf";
  tools::resolve_vocabulary(c);
  EXPECT_TRUE(c.window.map.vocabulary) << "kestrel built without its vocabulary: nothing can relocalise";
  return c;
}

}  // namespace kestrel::map_test

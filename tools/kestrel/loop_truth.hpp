// The loops a flight should have closed, from its ground truth, set against
// what the loop closer did (`kestrel replay --loop-log`, the metrics JSON's
// `loop_truth`, the bench's loop columns; docs/map.md, "Loops against the
// ground truth").
//
// Two keyframes are a revisit when they are at least min_gap_s apart and at
// least min_overlap of one's depth points, moved by the true poses, land in
// the other's image within the depth range and on the surface that image
// sees there (not behind it): the views share that much of the scene, so a
// loop closer could find one from the other. Not real time: it re-reads the
// log's depth at the keyframes' times after the flight.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/core/loop_closer.hpp"
#include "kestrel/drivers/log_source.hpp"

namespace kestrel::cli {

struct LoopTruthOptions {
  double min_gap_s = 10.0;      // the loop closer's own loop_min_age_s default
  double min_overlap = 0.3;     // share of one keyframe's depth points the other sees
  int sample_stride_px = 32;    // depth points of the keyframe that is projected
  int lookup_stride_px = 8;     // depth kept of the keyframe projected into
  double surface_tol_m = 0.10;  // + 3 sigma of the depth: "on the surface it sees there"
  // A closed loop is false when its correction misses the one the ground
  // truth implies (at the query keyframe) by more than this: a right loop
  // reproduces it to the map's own error at the candidate (1-2 cm on the
  // bench), a look-alike is off by the distance between the copies.
  double false_m = 0.05;
  double false_rad = 0.03;
  int link_min_shared = 15;  // ORB-SLAM's covisibility edge
};

struct LoopTruthCandidate {
  double overlap = -1;                  // of the pair, -1: a keyframe without depth or ground truth
  double error_m = -1, error_rad = -1;  // verified ones: correction against the truth
  double surface_error_m = -1;          // the surface alignment's correction against the truth (tried ones)
};

struct LoopTruth {
  bool available = false;
  std::string why_not;                  // when not available
  int keyframes = 0;                    // queried by the loop closer, with depth and ground truth
  int revisit_pairs = 0;                // keyframe pairs that are revisits
  int revisit_keyframes = 0;            // keyframes with an older revisit partner
  int candidates = 0;                   // from place recognition
  int candidates_true = 0;              // ... that are revisits
  int revisit_keyframes_candidate = 0;  // revisit keyframes with a true candidate
  int verified = 0;                     // passed every check: a loop to close
  int verified_true = 0;
  // Recognised: the geometry verified the place (verified, or a correction
  // within its own uncertainty: the same place with nothing to correct).
  int recognised = 0;
  int recognised_true = 0;
  int revisit_keyframes_recognised = 0;  // ... with a recognised true candidate
  // Linked: the local mapper's fusing already joined the revisit to the old
  // place (a keyframe it truly overlaps, min_age_s older, sharing at least
  // link_min_shared points): the map is one there without a loop.
  int revisit_keyframes_linked = 0;
  int revisit_keyframes_found = 0;  // recognised or linked
  int closed = 0;
  int closed_false = 0;                           // closed, correction disagreeing with the truth
  double loop_recall = 0;                         // revisit_keyframes_recognised / revisit_keyframes
  double map_recall = 0;                          // revisit_keyframes_found / revisit_keyframes
  std::vector<LoopTruthCandidate> per_candidate;  // parallel to LoopLog::candidates
};

// log: rewound and read to the end; T_BC and the colour camera's intrinsics
// (depth is registered to it) come from log.rig().
LoopTruth evaluate_loops(drivers::LogSource& log, const core::LoopLog& loop_log,
                         const LoopTruthOptions& opt = {});

// The loop log as CSV, one candidate a row, with the truth's columns when available.
void write_loop_log(const std::string& path, const core::LoopLog& loop_log, const LoopTruth& truth);

// One line for the replay summary.
std::string loop_truth_summary(const LoopTruth& t);

}  // namespace kestrel::cli

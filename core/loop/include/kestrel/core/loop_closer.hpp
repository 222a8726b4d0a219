// Loop closing (paper 001's third thread, for RGB-D + IMU): for each new
// keyframe of the map,
//  1. candidates by place recognition (the inverted index), leaving out the
//     keyframe's covisible neighbours and everything younger than min_age_s,
//     and scoring at least what its covisible neighbours score with it;
//  2. geometric verification: the keyframe's depth-backed features matched to
//     the points of the candidate and its covisible neighbours, then a
//     4-DoF RANSAC (yaw + translation: both frames see gravity, so a
//     correction that tilts is not a loop) on the 3D-3D matches; enough
//     inliers, and a correction the odometry could have drifted by the path
//     flown since the candidate (a far jump is an alias, not drift);
//  3. consistency: consecutive keyframes must verify the same correction;
//  4. correction: the 4-DoF pose graph (pose_graph.hpp) over the map's
//     keyframes (spanning tree, strong covisibility and earlier loop edges,
//     the new loop edge), the candidate and the map's first keyframe held;
//     points move with their reference keyframe; the matched points are merged.
//  5. (MapSystem, after process()) the global bundle adjustment of the
//     whole map: global_bundle_adjustment.hpp.
// Not real time: the loop thread. docs/map.md.
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/core/local_mapper.hpp"
#include "kestrel/core/map.hpp"
#include "kestrel/core/surface_alignment.hpp"

namespace kestrel::core {

struct LoopOptions {
  double min_age_s = 10.0;  // candidates at least this much older than the query
  // Keyframes sharing at least this many points are connected: the query's
  // connected keyframes are not loop candidates, and a candidate's are
  // matched with it. 1 (any shared point) by default; ORB-SLAM's 15 closes
  // weakly linked revisits but let bad loops through on two Vicon flights
  // (docs/map.md, "Weakly linked revisits").
  int connected_min_shared = 1;
  int max_candidates = 3;        // best BoW candidates verified per keyframe
  double min_score = 0.01;       // BoW score floor
  int candidate_neighbours = 5;  // connected keyframes of a candidate whose points are matched too
  int match_max_hamming = 50;
  double match_ratio = 0.8;
  int ransac_iterations = 300;
  double inlier_m = 0.05;  // 3D-3D inlier: this + 3 sigma of the depth
  int min_inliers = 40;
  double min_inlier_share = 0.3;  // of the matches
  // Two-stage verification (docs/map.md, "Loops on natural flights"): the
  // descriptor matches need only this many 3D inliers to seed a correction;
  // the place's targets are then projected into the query with it and
  // matched within guided_radius_px (x the level's scale) at a consistent
  // depth, and min_inliers / min_inlier_share apply to all of them.
  // guided_radius_px 0: no guided search (the seed must carry min_inliers).
  int min_seed_inliers = 15;
  double guided_radius_px = 10.0;
  // The candidate keyframe's depth-backed features without a map point are
  // targets too (most of a keyframe; the map keeps only points seen again).
  bool place_features = true;
  // When the descriptors seed nothing, the odometry's own pose is the seed
  // (a loop's correction is drift, a few cm): the place is projected with no
  // correction and matched within this radius (0: off; relocalisation, which
  // has no pose to trust, never uses it).
  double prior_seed_radius_px = 20.0;
  // Candidates from the map's geometry beside place recognition's: the old
  // keyframes (min_age_s, not connected) that the query's depth points,
  // placed by the map, land in front of within geometric_max_range_m, at
  // least geometric_min_overlap of them; the best geometric_candidates. A
  // loop's correction is bounded drift, so the place it closes on is where
  // the map already puts it; a look-alike elsewhere is never such a candidate.
  int geometric_candidates = 2;
  double geometric_min_overlap = 0.3;
  double geometric_max_range_m = 6.0;
  // Surface verification (surface_alignment.hpp): a candidate the
  // descriptors refuse is aligned by its depth grid to the query's, seeded by
  // the map's poses; what it verifies then meets the same drift, consistency
  // and significance gates. Needs depth grids (map.depth_grid_cols).
  bool surface_verify = true;
  SurfaceAlignOptions surface;
  // After the 3D fit: refit on pixels and depths, inliers below this chi2 (3 DoF); 0: off
  double refine_chi2 = 7.815;
  // The correction must be drift: at most base + per_m x path flown since the candidate.
  double max_correction_m = 0.3;
  double max_correction_per_m = 0.05;
  double max_yaw_rad = 0.1;
  double max_yaw_per_m = 0.005;
  // The inliers must not all lie on one plane: on a single wall, translation
  // along the wall is fixed by the descriptor matches alone, and a repeated
  // texture shifts them all alike - a consistent, bounded, false correction
  // the drift bound lets through. RMS distance of the inliers' map points from
  // their best-fit plane (sqrt of the scatter's smallest eigenvalue).
  double min_out_of_plane_m = 0.10;
  // A verified correction no larger than its own uncertainty is not closed:
  // applied as a stiff edge it moves the map by the fit's noise, not by drift.
  // The squared Mahalanobis length of (yaw, position at the query) under the
  // refit's covariance plus the loop edge's floor (4 DoF); 0: close every
  // verified loop. 9.488 is chi2(4) at 95 %.
  double min_correction_chi2 = 9.488;
  int consistent_keyframes = 2;  // consecutive keyframes verifying the same correction
  double consistency_m = 0.1;    // their corrections agree within (at the keyframe's position)
  double consistency_rad = 0.05;
  int pose_graph_iterations = 30;
  int covis_edge_min_shared = 50;  // covisibility edges of the pose graph
  int cooldown_keyframes = 10;     // no new loop this soon after one
  // Relocalisation (relocaliser.hpp): no drift bound to lean on after a loss,
  // so stronger evidence, and a place that fits two poses is no evidence.
  int reloc_max_candidates = 8;  // best BoW candidates verified per lost keyframe
  int reloc_min_inliers = 50;
  double reloc_min_inlier_share = 0.4;
  int reloc_consistent_keyframes = 2;  // consecutive lost keyframes giving the same T_map_odom
  // Lost mid-flight and not found again within this: the map goes on in the
  // odometry's current alignment (a loop can still correct it). A loaded map
  // is waited for however long it takes.
  double reloc_timeout_s = 10.0;

  [[nodiscard]] std::string validate() const;
};

struct LoopStats {
  uint64_t queries = 0;
  uint64_t candidates = 0;            // from the inverted index and the map's geometry
  uint64_t geometric_candidates = 0;  // ... of which from the geometry
  uint64_t verified = 0;              // passed geometry and the drift bound
  uint64_t surface_tried = 0;         // refused by the descriptors, aligned by the depth grids
  uint64_t surface_aligned = 0;       // ... and the alignment held (then the same gates)
  uint64_t rejected_inliers = 0;      // too few 3D-3D inliers
  uint64_t rejected_drift = 0;        // a correction the odometry could not have drifted (an alias)
  uint64_t rejected_planar = 0;       // every inlier on one plane: the correction along it is appearance only
  uint64_t rejected_consistency = 0;
  uint64_t skipped_insignificant = 0;  // verified, but the correction is within its own uncertainty
  uint64_t closures = 0;
  uint64_t pose_graph_failures = 0;
  uint64_t points_merged = 0;
};

// What became of one candidate: the stage that refused it, or verified. In
// stage order, so "how far it got" compares.
enum class LoopVerdict : uint8_t {
  kFewPoints,        // the place holds fewer points than min_inliers
  kFewMatches,       // fewer descriptor matches than min_inliers
  kFewInliers,       // the 3D RANSAC: fewer than min_inliers, or below min_inlier_share
  kFewRefitInliers,  // the refit on pixels and depths kept too few
  kPlanar,
  kDrift,
  kInsignificant,  // verified, but within its own uncertainty
  kVerified,
};
const char* loop_verdict_name(LoopVerdict v);

// A keyframe's features matched to a place of the map: T_MC_true =
// correction * T_MC (4 DoF) and the inliers behind it.
struct PlaceFit {
  Eigen::Isometry3d correction = Eigen::Isometry3d::Identity();
  // Filled as far as the verification got, also when it fails (the loop log):
  // targets of the place (points and the candidate's features), descriptor
  // matches, the seed RANSAC's inliers, matches the guided search added, the
  // final inliers; and the stage that refused it (kVerified: none did).
  int place_points = 0, matches = 0, ransac_inliers = 0, guided_matches = 0, inliers = 0;
  LoopVerdict failed = LoopVerdict::kFewPoints;
  bool prior_seeded = false;  // the descriptors seeded nothing; the odometry's pose did
  double out_of_plane_m = 0;  // RMS distance of the inliers' map points from their best-fit plane
  // Covariance of (yaw [rad], t [m]) of the correction from the refit's pixels
  // and depths; zero without the refit (refine_chi2 = 0).
  Eigen::Matrix4d cov = Eigen::Matrix4d::Zero();
  std::vector<std::pair<int, int>> inlier_pairs;  // (feature, map point)
};

// Geometric verification, shared by loop closing and relocalisation: the
// depth-backed features (seen from T_MC) matched by descriptor to the points
// of a candidate keyframe and its closest covisible keyframes, then the 4-DoF
// RANSAC on the 3D-3D matches and a closed-form refit on the inliers.
// Thresholds: LoopOptions' match_*, ransac_iterations, inlier_m, min_inliers,
// min_inlier_share, candidate_neighbours.
class PlaceMatcher {
 public:
  enum Result { kOk, kFewInliers };
  PlaceMatcher(Map& map, const MapCamera& cam);
  Result match(const KeyframeFeature* f, int n, const Eigen::Isometry3d& T_MC, int candidate,
               const LoopOptions& opt, uint64_t seed, PlaceFit* out);

 private:
  using Pairs = std::vector<std::pair<int, int>>;
  // The 4-DoF correction that best explains the chosen pairs' pixels and
  // depths, from T (Huber at sqrt(chi2), Ceres).
  Eigen::Isometry3d refine_4dof(const Eigen::Isometry3d& T, const Eigen::Isometry3d& T_MC,
                                const KeyframeFeature* f, const Pairs& pairs, const std::vector<int>& idx,
                                double chi2) const;
  // Inverse of the Gauss-Newton information of the refit at T over the chosen
  // pairs: (yaw, t)'s covariance if the pairs' noise is independent.
  Eigen::Matrix4d refit_covariance(const Eigen::Isometry3d& T, const Eigen::Isometry3d& T_MC,
                                   const KeyframeFeature* f, const Pairs& pairs,
                                   const std::vector<int>& idx) const;
  // The pairs whose whitened pixel and depth error under T is below chi2.
  void chi2_inliers(const Eigen::Isometry3d& T, const Eigen::Isometry3d& T_MC, const KeyframeFeature* f,
                    const Pairs& pairs, double chi2, std::vector<int>& out) const;
  // A pair's pixel and depth noise, the target's own included.
  void pair_sigmas(const KeyframeFeature& f, int target, double* sigma_px, double* sigma_z_m) const;

  // What a query feature can match in the place: a map point, or one of the
  // candidate keyframe's own depth-backed features.
  struct Target {
    Eigen::Vector3d p_M;
    const OrbDescriptor* desc;
    int32_t point;   // map point, -1: a feature of the candidate
    double sigma_m;  // 1-sigma of p_M
    int16_t level;
  };
  // Targets closer than this are one place seen twice (a point and the
  // feature it was made from): no ambiguity for the ratio test.
  static constexpr double kSamePlace_m = 0.05;

  Map& map_;
  MapCamera cam_;
  std::vector<int32_t> kf_scratch_, shared_scratch_;
  std::vector<Target> targets_;
  std::vector<int> dist_;
};

// Yaw of a rotation about W's (or M's) z axis [rad].
double yaw_of(const Eigen::Matrix3d& R);

// The loop log (LoopCloser::set_logging): every query and every candidate
// with what verification made of it, so a flight's misses can be explained
// against its ground truth (tools: `--loop-log`, docs/map.md).
struct LoopQueryRecord {
  uint32_t id = 0;
  int64_t t_ns = 0;
  bool cooldown = false;                                   // not searched: too soon after a closure
  Eigen::Isometry3d T_MC = Eigen::Isometry3d::Identity();  // at the query
  // Keyframes at least min_age_s older that the map already links it to
  // (shared points, most first, at most 8): a revisit the local mapper's
  // fusing has joined to the old place needs no loop.
  std::vector<std::pair<uint32_t, int>> old_links;  // (keyframe id, shared points)
};
struct LoopCandidateRecord {
  uint32_t query_id = 0, candidate_id = 0;
  int64_t query_t_ns = 0, candidate_t_ns = 0;
  double score = 0;
  int place_points = 0, matches = 0, ransac_inliers = 0, guided_matches = 0, inliers = 0;
  double out_of_plane_m = 0;
  double correction_m = 0, correction_rad = 0;  // at the query keyframe
  double path_m = 0;                            // flown between the two
  LoopVerdict verdict = LoopVerdict::kFewPoints;
  bool geometric = false;     // from the map's geometry, not place recognition
  bool prior_seeded = false;  // PlaceFit::prior_seeded
  bool chosen = false;        // the query's best verified candidate
  bool inconsistent = false;  // chosen, refused by the consistency check
  bool closed = false;        // chosen, and the loop closed on it
  // Surface verification, when the descriptors refused it: tried, held, why
  // not (SurfaceFit::failed), paired cells' share, inliers' share and RMS, the
  // weakest direction's share of the constraint.
  bool surface_tried = false, surface_ok = false;
  const char* surface_failed = "";
  double surface_overlap = 0, surface_inlier_share = 0, surface_rms_m = 0, surface_observability = 0;
  // The alignment's correction, also when a gate refused it (the loop log
  // scores it against the ground truth); identity when it never converged.
  Eigen::Isometry3d surface_correction = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d T_MC_query = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d T_MC_candidate = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d correction = Eigen::Isometry3d::Identity();
};
struct LoopLog {
  std::vector<LoopQueryRecord> queries;
  std::vector<LoopCandidateRecord> candidates;
};

// A verified match of a keyframe against an older place.
struct LoopMatch {
  int query = -1, candidate = -1;  // keyframe slots
  uint32_t query_id = 0, candidate_id = 0;
  // T_MC_true = correction * T_MC (4 DoF): where the query keyframe really is.
  Eigen::Isometry3d correction = Eigen::Isometry3d::Identity();
  int matches = 0, inliers = 0;
  bool surface = false;  // verified by the depth grids (no point pairs to merge)
  double score = 0.0;
  // The loop edge's sigmas: the fit's, with the stiff floor under them.
  double sigma_m = 0.0, sigma_rad = 0.0;
  std::vector<std::pair<int, int>> inlier_pairs;  // (query feature, map point)
};

struct LoopClosure {
  bool closed = false;
  LoopMatch match;
  // Correction of the newest keyframe (T_new = delta * T_old), for T_map_odom.
  Eigen::Isometry3d newest_delta = Eigen::Isometry3d::Identity();
  int newest = -1;
};

class LoopCloser {
 public:
  LoopCloser(Map& map, const MapCamera& cam, const LoopOptions& opt);

  // Looks at keyframe kf (just mapped): detection, verification,
  // consistency, and when a loop is accepted its correction of the map.
  LoopClosure process(int kf);

  // Steps 1-2 alone for one keyframe: the best verified match, or false.
  bool detect(int kf, LoopMatch* out);
  // Step 4 for a verified match.
  bool close(const LoopMatch& m, LoopClosure* out);

  const LoopStats& stats() const { return stats_; }
  const LoopOptions& options() const { return opt_; }
  // Keyframes carry depth grids of this shape (MapSystem::enable_depth_grid):
  // surface verification is on (with LoopOptions::surface_verify).
  void set_depth_grid(const DepthGridShape& shape);

  // A closed loop, kept for later pose graphs and the global bundle
  // adjustment: b seen from a (camera frames).
  struct LoopEdge {
    uint32_t id_a, id_b;
    Eigen::Vector3d t_ab;
    Eigen::Matrix3d R_ab;
    double sigma_m, sigma_rad;
  };
  const std::vector<LoopEdge>& loop_edges() const { return loop_edges_; }
  // Keep the loop log (off by default: it grows with the flight; the loop
  // thread is not real time, so it may).
  void set_logging(bool on) { logging_ = on; }
  const LoopLog& log() const { return log_; }

 private:
  bool verify(int kf, int candidate, double score, bool geometric, LoopMatch* out);
  // Old keyframes whose view the query's depth points land in (their share),
  // best first, at most max; skip(k) leaves one out.
  template <class Skip>
  int geometric_candidates(int kf, const Skip& skip, int max, int32_t* out_kf, float* out_share);
  LoopCandidateRecord* log_candidate();

  Map& map_;
  MapCamera cam_;
  LoopOptions opt_;
  PlaceMatcher matcher_;
  // kf's depth grid and those of its most covisible keyframes (not other),
  // up to opt_.surface.neighbours more: the views a surface verification aligns.
  int surface_views(int kf, int other, SurfaceView* out);
  static constexpr int kMaxSurfaceNeighbourPool = 30;
  SurfaceAligner aligner_;
  LoopStats stats_;
  std::vector<LoopEdge> loop_edges_;
  // Consistency: the last verified match and how many consecutive keyframes agree.
  LoopMatch pending_;
  int pending_count_ = 0;
  uint32_t last_closure_kf_id_ = 0;
  std::vector<int32_t> kf_scratch_, shared_scratch_;
  bool logging_ = false;
  LoopLog log_;
  int64_t chosen_record_ = -1;  // the record detect() chose, or -1
};

}  // namespace kestrel::core

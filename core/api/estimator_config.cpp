#include "kestrel/core/estimator_config.hpp"

#include <sstream>
#include <stdexcept>

#include "kestrel/core/estimator_factory.hpp"

namespace kestrel::core {

namespace {

// Enums travel through the visitor as an index into their names.
template <typename E>
void enum_choice(OptionVisitor& v, const char* key, E& e, const std::vector<const char*>& names,
                 const char* doc) {
  int i = static_cast<int>(e);
  v.choice(key, i, names, doc);
  e = static_cast<E>(i);
}

void visit_orb(OrbOptions& o, OptionVisitor& v) {
  v.begin_section("orb", "ORB extraction (core/features, docs/orb.md)");
  v.value("n_features", o.n_features, "feature budget per frame over all pyramid levels");
  v.value("n_levels", o.n_levels, "pyramid levels (1 = no pyramid), at most 8");
  v.value("scale_factor", o.scale_factor, "linear size ratio between consecutive levels, in (1, 2]");
  v.value("fast_threshold", o.fast_threshold, "FAST intensity threshold [grey levels]");
  v.value("fast_threshold_min", o.fast_threshold_min,
          "FAST threshold [grey levels] used inside grid cells with no corner at fast_threshold");
  v.value("edge_margin_px", o.edge_margin, "keypoints keep this far from the border of their level, >= 16");
  v.value("cell_size_px", o.cell_size, "bucketing grid cell side [level pixels]");
  v.value("pattern_seed", o.pattern_seed, "seed of the BRIEF test pattern (a vocabulary is tied to it)");
  v.end_section();
}

void visit_lonsc(LonscOptions& o, OptionVisitor& v) {
  v.begin_section("lonsc",
                  "LONSC outlier rejection (core/tracking, docs/lonsc.md); lonsc_variant sets the defaults");
  v.value("threshold_px", o.consistency.threshold_px, "reprojection error bound of the consistency test");
  v.value("scale_by_sigma", o.consistency.scale_by_sigma, "scale the bound with the keypoint's sigma");
  v.value("reference_sigma_px", o.consistency.reference_sigma_px, "sigma at which the bound is threshold_px");
  v.value("min_depth_m", o.consistency.min_depth_m, "a point closer than this counts as behind the camera");
  v.value("min_run_length", o.min_run_length, "shorter runs are not trusted");
  v.value("verify_seed_pair", o.verify_seed_pair, "a new pair must agree with its own model (paper: false)");
  v.value("grow_model", o.grow_model, "re-solve the run's model as it grows (paper: false)");
  v.value("candidate_runs", o.candidate_runs, "longest runs that each propose t_hat, at most 8 (paper: 1)");
  v.value("min_pair_separation_px", o.min_pair_separation_px, "closer pixel pairs leave t_z unobservable");
  v.value("weighted_least_squares", o.weighted_least_squares, "depth-normalised (ML) weights (paper: false)");
  v.value("refine_passes", o.refine_passes, "extra collect-and-resolve passes (paper: 0)");
  int min_inliers = static_cast<int>(o.min_inliers);
  v.value("min_inliers", min_inliers, "fewer inliers: no motion");
  o.min_inliers = static_cast<std::size_t>(min_inliers < 0 ? 0 : min_inliers);
  v.end_section();
}

void visit_tracker(TrackerOptions& o, OptionVisitor& v) {
  v.value("search_radius_min_px", o.search_radius_min_px, "circle search window radius, lower bound");
  v.value("search_radius_max_px", o.search_radius_max_px, "circle search window radius, upper bound");
  v.value("search_k_sigma", o.search_k_sigma, "search radius = this x the predicted pixel uncertainty");
  v.value("match_ratio", o.match_ratio, "best < ratio x second best Hamming distance within the window");
  v.value("match_max_hamming", o.match_max_hamming, "largest accepted Hamming distance [bits of 256]");
  v.value("match_max_level_diff", o.match_max_level_diff,
          "pyramid levels between keyframe and current keypoint");
  enum_choice(v, "correspondence_order", o.order, {"as_given", "by_match_cost", "hilbert", "shuffled"},
              "order of the correspondences LONSC walks");
  v.value("keypoint_sigma_px", o.keypoint_sigma_px,
          "keypoint noise at pyramid level 0 (scales with the level)");
  v.value("min_inliers", o.min_inliers, "fewer LONSC inliers: the frame is not tracked");
  v.value("motion_model_min_inliers", o.motion_model_min_inliers,
          "no IMU rotation and no rigid consensus: inliers the motion-model fallback needs (0: off)");
  v.value("keyframe_area_ratio", o.keyframe_area_ratio,
          "matched / detected area below this: new keyframe (paper 000: 50-60 %)");
  v.value("keyframe_min_inliers", o.keyframe_min_inliers, "fewer inliers than this: new keyframe");
  v.value("keyframe_max_interval_s", o.keyframe_max_interval_s, "a keyframe at least this often");
  v.value("area_grid_cols", o.area_grid_cols, "columns of the grid the area ratio counts");
  v.value("area_grid_rows", o.area_grid_rows, "rows of the grid the area ratio counts");
  v.value("depth_edge_rel", o.depth_edge_rel, "3x3 depth spread above this share of the depth: a depth edge");
  v.value("map_capacity", o.map_capacity, "points of past keyframes kept for the local map search (0: off)");
  v.value("map_search_radius_px", o.map_search_radius_px, "local map search radius");
  v.value("map_match_max_hamming", o.map_match_max_hamming, "largest Hamming distance for a map match");
  v.value("map_match_ratio", o.map_match_ratio, "best < ratio x second best for a map match");
  v.value("map_depth_tol_rel", o.map_depth_tol_rel, "measured vs map depth within rel x z + 3 cm");
  v.value("map_min_inliers", o.map_min_inliers, "fewer PnP inliers: the keyframe keeps its chained pose");
  v.value("map_max_correction_m", o.map_max_correction_m,
          "a larger map correction is taken for false matches");
  v.value("map_max_correction_rad", o.map_max_correction_rad,
          "a larger map correction is taken for false matches");
  v.value("map_max_sigma_m", o.map_max_sigma_m, "a less certain map pose is not reported");
  v.value("far_tracks", o.far_tracks,
          "follow keyframe features without depth along their epipolar segment beyond the depth range");
  v.value("far_search_radius_px", o.far_search_radius_px, "far tracks: distance from the segment at level 0");
  v.value("far_max_segment_px", o.far_max_segment_px,
          "far tracks: a longer epipolar segment is not searched");
  visit_orb(o.orb, v);
  visit_lonsc(o.lonsc, v);
  v.begin_section("rigid",
                  "6-DoF tracking without an IMU rotation (rgbd backend, IMU outage; docs/real-imagery.md)");
  enum_choice(v, "method", o.rigid_method, {"lonsc", "ransac"},
              "how the 3-point rigid model is found: LONSC's ordered runs, or RANSAC");
  v.value("threshold_px", o.rigid.consistency.threshold_px,
          "reprojection error bound of the consistency test");
  v.value("depth_tol_rel", o.rigid.depth_tol_rel, "3D distance bound: this share of the current depth...");
  v.value("depth_tol_m", o.rigid.depth_tol_m, "...plus this");
  v.value("min_run_length", o.rigid.min_run_length, "lonsc: shorter runs are not trusted");
  v.value("candidate_runs", o.rigid.candidate_runs,
          "lonsc: longest runs that each propose a motion, at most 8");
  v.value("min_sample_spread_m", o.rigid.min_sample_spread_m,
          "points of a model closer than this: degenerate");
  int rigid_min_inliers = static_cast<int>(o.rigid.min_inliers);
  v.value("min_inliers", rigid_min_inliers, "fewer inliers: no motion");
  o.rigid.min_inliers = static_cast<std::size_t>(rigid_min_inliers < 0 ? 0 : rigid_min_inliers);
  v.value("confidence", o.rigid.confidence,
          "ransac: stop when an all-inlier triple was drawn with this probability");
  v.value("max_iterations", o.rigid.max_iterations, "ransac: hypotheses at most");
  v.value("seed", o.rigid.seed, "ransac: random seed (re-seeded every frame: replays are deterministic)");
  v.end_section();
  v.begin_section(
      "stereo",
      "stereo rigs: feature depth from the row search in the rectified right image (docs/stereo.md)");
  v.value("min_disparity_px", o.stereo.min_disparity_px,
          "smallest disparity searched: farthest depth f b / this");
  v.value("max_disparity_px", o.stereo.max_disparity_px,
          "largest disparity searched: nearest depth f b / this");
  v.value("patch_half_rows_px", o.stereo.patch_half_rows_px, "SAD patch: 16 columns by 2 x this + 1 rows");
  v.value("uniqueness_ratio", o.stereo.uniqueness_ratio,
          "best SAD < this x the best more than 1 px away, else no match");
  v.value("max_mean_abs_diff", o.stereo.max_mean_abs_diff,
          "best match's mean absolute difference per pixel [grey levels]");
  v.value("disparity_sigma_px", o.stereo.disparity_sigma_px,
          "1-sigma of a matched disparity: depth sigma = z^2 x this / (f b)");
  v.end_section();
  v.begin_section("pose_refine", "6-DoF Gauss-Newton on the LONSC inliers (docs/lonsc.md)");
  v.value("max_iterations", o.refine.max_iterations, "Gauss-Newton iterations");
  v.value("huber_px", o.refine.huber_px, "Huber threshold on the whitened error (<= 0: least squares)");
  v.value("rotation_prior_sigma_rad", o.refine.rotation_prior_sigma_rad,
          "> 0: keep R near the gyro's (0: off)");
  v.value("min_step", o.refine.min_step, "stop when the step falls below this [rad, m]");
  v.end_section();
}

void visit_vo(FrontendOdometryOptions& o, OptionVisitor& v) {
  v.value("accel_noise_mps2_sqrthz", o.accel_noise_mps2_sqrthz, "vo fusion: white acceleration error");
  v.value("position_sigma_m", o.position_sigma_m, "vo fusion: tracked position noise");
  v.value("initial_velocity_sigma_mps", o.initial_velocity_sigma_mps,
          "vo fusion: velocity sigma at the start");
  v.value("attitude_gain", o.attitude_gain, "share of the way to the tracked attitude per tracked frame");
  v.value("gyro_bias_gain", o.gyro_bias_gain, "integral share of the gyro bias per tracked frame");
  v.value("gate_sigma", o.gate_sigma, "innovations beyond this many sigma are not believed");
  v.value("max_lost_frames", o.max_lost_frames, "untracked frames before a new keyframe at the IMU pose");
  v.value("moving_start_after_ns", o.moving_start_after_ns,
          "vo/imu: no still window by then: start moving (the window backend: window.moving_start_after_ns)");
  v.value("pred_sigma_px_per_s", o.pred_sigma_px_per_s,
          "search window growth per second since the last track");
  v.value("pred_sigma_min_px", o.pred_sigma_min_px, "search window pixel uncertainty, lower bound");
  v.value("imu_outage_after_ns", o.imu_outage_after_ns,
          "a frame this long after the last IMU sample: IMU lost, track on the camera alone (0: never)");
  v.value("vision_only_pred_sigma_px", o.vision_only_pred_sigma_px,
          "IMU lost: the constant-velocity prediction's pixel uncertainty at one frame");
}

void visit_window(EstimatorConfig& c, OptionVisitor& v) {
  WindowEstimatorOptions& e = c.window;
  WindowOptions& w = e.window;
  v.begin_section("window",
                  "the sliding-window optimizer and the window backend (core/window, docs/optimizer.md)");
  v.value("recent_frames", w.S, "S: most recent frames in the window");
  v.value("keyframes", w.N, "N: keyframes outside the recent frames; S + N <= 10");
  v.value("max_landmarks", w.max_landmarks, "landmark budget, fixed at start-up");
  v.value("max_obs_per_frame", w.max_obs_per_frame, "observations kept per frame");
  enum_choice(v, "solver", w.solver, {"ours", "ceres"}, "our Schur + Cholesky solver, or Ceres (reference)");
  v.value("max_iterations", w.max_iterations, "iterations per solve");
  v.value("time_budget_ms", w.time_budget_ms, "wall-clock bound of one solve (checked after each iteration)");
  v.value("huber_px", w.huber_px, "Huber threshold on the whitened residual norm (<= 0: least squares)");
  v.value("use_depth", w.use_depth, "RGB-D depth as a third row of the visual residual");
  v.value("marginalize", w.marginalize, "marginalise dropped states into a prior (false: discard)");
  v.value("pixel_sigma_px", w.pixel_sigma, "pixel noise of an observation that gives none");
  enum_choice(v, "acc_bias_model", w.acc_bias_model, {"random_walk", "bounded_random_walk"},
              "accelerometer bias: Forster's random walk, or paper 000 eq. 6 (db/dt = -b/tau + w)");
  v.value("acc_bias_tau_s", w.acc_bias_tau_s, "tau of the bounded random walk");
  v.value("prior_gyro_bias_sigma_rps", w.prior_gyro_bias_sigma_rps, "prior on the first state's gyro bias");
  v.value("prior_acc_bias_sigma_mps2", w.prior_acc_bias_sigma_mps2, "prior on the first state's accel bias");
  v.value("gauge_sigma", w.gauge_sigma, "stiff prior on the oldest state's position and yaw [m, rad]");
  v.value("zero_velocity_sigma_mps", w.zero_velocity_sigma_mps, "zero-velocity factor on still frames");
  v.value("function_tolerance", w.function_tolerance, "stop when the relative cost decrease falls below");
  v.value("step_tolerance", w.step_tolerance, "stop when the step's max-norm falls below");
  v.value(
      "estimate_time_offset", w.estimate_time_offset,
      "estimate the camera-IMU time offset online on top of the rig's time_offset_cam_imu_ns: a t_d state "
      "(VINS-Mono's) measured by correlating vision-only rotations with the gyro (docs/optimizer.md)");
  v.value("time_offset_prior_sigma_ms", w.time_offset_prior_sigma_ms,
          "prior on the estimated offset around the rig's value, until the correlation has a measurement");
  TimeOffsetCalibratorOptions& to = e.time_offset;
  v.value("time_offset_search_ms", to.search_ms, "offsets the correlation tries: +- this");
  v.value("time_offset_step_ms", to.step_ms, "grid of the correlation's search (refined by a parabola)");
  v.value("time_offset_memory_s", to.memory_s, "the correlation's evidence fades with this time constant");
  v.value("time_offset_min_intervals", to.min_intervals, "frame intervals before the first measurement");
  v.value("time_offset_max_sigma_ms", to.max_sigma_ms, "a measurement less certain than this is not used");
  v.value("time_offset_sigma_floor_ms", to.sigma_floor_ms, "the measurement's 1-sigma is at least this");
  v.value("time_offset_gate_rad", to.gate_rad,
          "a frame interval no offset explains within this is an outlier");
  v.value("time_offset_max_interval_s", to.max_interval_s,
          "a frame further than this from its keyframe is not used");
  v.value("time_offset_gyro_capacity", to.gyro_capacity,
          "gyro samples kept by the correlation (fixed memory)");
  v.value("time_offset_min_matches", e.time_offset_min_matches,
          "depth-backed matches a frame pair needs for its vision-only rotation");
  v.value("keyframes_only", e.keyframes_only, "only keyframes enter the window (cheaper, less accurate)");
  v.value("imu_noise_inflation", e.imu_noise_inflation,
          "every IMU noise density of the rig is multiplied by this (docs/optimizer.md)");
  v.value("min_observations", e.min_observations, "a frame with fewer observations stays out of the window");
  v.value("max_correction_m", e.max_correction_m, "optimized vs propagated position beyond this: a failure");
  v.value("max_speed_mps", e.max_speed_mps, "an optimized speed beyond this: a failure");
  v.value("max_consecutive_failures", e.max_consecutive_failures, "then the window restarts");
  v.value("max_imu_gap_ns", e.max_imu_gap_ns,
          "a longer IMU gap cannot be preintegrated (continue_without_imu)");
  v.value(
      "continue_without_imu", e.continue_without_imu,
      "IMU lost in flight: frames go on as vision-only states (false: the window restarts after the gap)");
  v.value("hold_velocity_sigma_mps", e.window.hold_velocity_sigma_mps,
          "vision-only states: velocity held at the guess");
  v.value("hold_gyro_bias_sigma_rps", e.window.hold_gyro_bias_sigma_rps,
          "vision-only states: gyro bias held");
  v.value("hold_acc_bias_sigma_mps2", e.window.hold_acc_bias_sigma_mps2,
          "vision-only states: accel bias held");
  v.value("zero_velocity_when_still", e.zero_velocity_when_still, "zero-velocity factor on still frames");
  v.value("still_max_speed_mps", e.still_max_speed_mps,
          "a frame is still only if the speed is below this too");
  v.value("use_map_pose", e.use_map_pose,
          "keyframes re-located on the local map carry that pose as a factor");
  v.value("map_pose_sigma_m", e.map_pose_sigma_m, "map pose factor sigma, lower bound");
  v.value("map_pose_sigma_rad", e.map_pose_sigma_rad, "map pose factor sigma, lower bound");
  v.value("moving_start_after_ns", c.window_moving_start_after_ns,
          "no still window by then: the dynamic start (the optimizer fixes attitude and velocity)");
  v.value("use_map_points", w.use_map_points,
          "map points hold their window landmarks by a prior (docs/map.md)");
  v.value("map_anchor_min_landmarks", w.map_anchor_min_landmarks,
          "with this many map-point landmarks the map fixes the gauge");
  v.end_section();
}

void visit_map(MapSystemOptions& m, OptionVisitor& v) {
  MapOptions& o = m.map;
  v.begin_section("map",
                  "the map beside the window backend: local mapping, loop closing (core/map, docs/map.md)");
  v.value("mapping", m.mapping,
          "build a map on the kst-mapping thread and track against it (--mapping on|off)");
  v.value("loop", m.loop, "loop closing and relocalisation on the kst-loop thread (--loop on|off)");
  v.value("vocabulary", m.vocabulary_path,
          "place recognition vocabulary file (kestrel vocab); empty: the one built into kestrel");
  v.value("max_keyframes", o.max_keyframes, "keyframes the map holds, fixed at start-up");
  v.value("max_points", o.max_points, "map points the map holds, fixed at start-up");
  v.value("ba_keyframes", o.ba_keyframes, "covisible keyframes bundle-adjusted with each new one");
  v.value("ba_fixed_keyframes", o.ba_fixed_keyframes, "other keyframes seeing the same points, held fixed");
  v.value("ba_iterations", o.ba_iterations, "Levenberg-Marquardt iterations per round (two rounds)");
  enum_choice(v, "ba_solver", o.ba_solver, {"ours", "ceres"},
              "our Schur + analytic-Jacobian solver, or Ceres (the reference it is tested against)");
  v.value("ba_huber", o.ba_huber, "Huber threshold on the whitened observation error");
  v.value("ba_outlier_chi2", o.ba_outlier_chi2, "observations above this whitened squared error are dropped");
  v.value("ba_gravity_sigma_rad", o.ba_gravity_sigma_rad,
          "the odometry's gravity direction holds each keyframe's roll and pitch (0: off)");
  v.value("fuse_radius_px", o.fuse_radius_px, "search radius when fusing covisible points (level 0)");
  v.value("fuse_max_hamming", o.fuse_max_hamming, "largest Hamming distance for a fused match");
  v.value("fuse_depth_tol_rel", o.fuse_depth_tol_rel, "measured vs projected depth within rel x z + 3 cm");
  v.value("cull_keyframe_redundancy", o.cull_keyframe_redundancy,
          "a keyframe whose points are this share seen by 3 others is culled");
  v.value("cull_point_min_keyframes", o.cull_point_min_keyframes,
          "a point seen by fewer keyframes 3 keyframes after it was made is culled");
  v.value("cull_point_min_found_ratio", o.cull_point_min_found_ratio,
          "a point found in fewer than this share of the keyframes it should be seen in is culled");
  v.value("update_max_points", o.update_max_points, "refined points handed to the tracker per keyframe");
  v.value("neighbour_radius_m", o.neighbour_radius_m, "keyframes this close count as the neighbourhood");
  v.value("neighbour_max_angle_rad", o.neighbour_max_angle_rad, "... when their optical axes are this close");
  v.value("point_sigma_floor_m", o.point_sigma_floor_m,
          "a map point's prior in the window: at least this sigma");
  v.value("point_min_keyframes_for_prior", o.point_min_keyframes_for_prior,
          "points seen by fewer keyframes are not handed to the tracker");
  v.value("min_keyframe_interval_s", o.min_keyframe_interval_s, "keyframes closer in time are not mapped");
  v.value(
      "depth_grid_cols", o.depth_grid_cols,
      "each keyframe keeps its depth on a grid this many cells wide (rows keep the aspect; 2 bytes a cell) "
      "for the loop's surface verification (0: none)");
  v.value("depth_grid_edge_rel", o.depth_grid_edge_rel,
          "a grid cell whose 3x3 pixels spread more than this x z is a depth edge and stays empty");
  GlobalBaOptions& g = m.global_ba;
  v.value("global_ba", g.enabled,
          "after each closed loop, a bundle adjustment of the whole map on the loop thread (docs/map.md)");
  v.value("global_ba_max_keyframes", g.max_keyframes,
          "the global BA's free keyframes, newest first (older ones seeing the same points are held)");
  v.value("global_ba_max_points", g.max_points, "the global BA's points, the most observed first");
  v.value("global_ba_iterations", g.iterations,
          "Levenberg-Marquardt iterations per round of the global BA (two rounds)");
  v.value(
      "global_ba_odometry_sigma_m", g.odometry_sigma_m,
      "the global BA holds each keyframe to its parent by the odometry's relative pose, this loose (0: off)");
  v.value("global_ba_odometry_sigma_rad", g.odometry_sigma_rad, "... and this loose in rotation");
  LoopOptions& l = m.closing;
  v.value("loop_min_age_s", l.min_age_s, "loop candidates are at least this much older than the keyframe");
  v.value(
      "loop_connected_min_shared", l.connected_min_shared,
      "keyframes sharing at least this many points are connected: a keyframe's connected ones are not its "
      "loop candidates, and a candidate's are matched with it (1: any shared point; docs/map.md)");
  v.value("loop_max_candidates", l.max_candidates, "best place-recognition candidates verified per keyframe");
  v.value("loop_min_score", l.min_score, "BoW score floor of a candidate");
  v.value("loop_candidate_neighbours", l.candidate_neighbours,
          "connected keyframes of a candidate whose points are matched too");
  v.value("loop_match_max_hamming", l.match_max_hamming, "largest Hamming distance of a loop match");
  v.value("loop_match_ratio", l.match_ratio, "best / second-best Hamming ratio of a loop match");
  v.value("loop_ransac_iterations", l.ransac_iterations, "4-DoF RANSAC iterations on the 3D-3D matches");
  v.value("loop_inlier_m", l.inlier_m, "3D-3D inlier distance, plus 3 sigma of the depth");
  v.value("loop_min_inliers", l.min_inliers, "inliers a loop needs");
  v.value("loop_min_inlier_share", l.min_inlier_share, "... and this share of the matches");
  v.value("loop_min_seed_inliers", l.min_seed_inliers,
          "descriptor matches need this many 3D inliers to seed a correction, which the guided search then "
          "extends (docs/map.md)");
  v.value("loop_guided_radius_px", l.guided_radius_px,
          "guided search: the place projected with the seed's correction, matched within this x the level's "
          "scale (0: off; the seed must carry loop_min_inliers)");
  v.value("loop_place_features", l.place_features,
          "the candidate keyframe's depth-backed features without a map point are matched too");
  v.value("loop_prior_seed_radius_px", l.prior_seed_radius_px,
          "no seed from the descriptors: the odometry's pose seeds the guided search within this radius (0: "
          "off)");
  v.value("loop_geometric_candidates", l.geometric_candidates,
          "candidates from the map's geometry beside place recognition's: old keyframes the query's depth "
          "points land in view of (0: none)");
  v.value("loop_geometric_min_overlap", l.geometric_min_overlap, "... at least this share of them");
  v.value("loop_geometric_max_range_m", l.geometric_max_range_m, "... within this range");
  v.value("loop_surface_verify", l.surface_verify,
          "a candidate the descriptors refuse is aligned by its depth grid to the keyframe's (4-DoF "
          "point-to-plane ICP from the map's poses), then meets the same gates (docs/map.md)");
  SurfaceAlignOptions& sa = l.surface;
  v.value("loop_surface_iterations", sa.iterations, "ICP iterations of the surface verification");
  v.value("loop_surface_max_pair_m", sa.max_pair_m, "its first iteration pairs cells this far apart");
  v.value("loop_surface_min_pair_m", sa.min_pair_m, "... shrinking to this by the last (+ a cell's width)");
  v.value("loop_surface_max_normal_angle_rad", sa.max_normal_angle_rad,
          "paired cells' normals agree within this");
  v.value("loop_surface_normal_max_step_rel", sa.normal_max_step_rel,
          "a cell has a normal when its neighbours' depths are within this x z (+ 2 cm) of its own");
  v.value("loop_surface_inlier_floor_m", sa.inlier_floor_m,
          "a paired cell is an inlier within this + 3 sigma of both depths (point to plane)");
  v.value("loop_surface_min_overlap", sa.min_overlap,
          "the keyframe's cells that land on the candidate's surface (not hidden behind it), of those with "
          "depth, at least this share");
  v.value("loop_surface_min_inlier_share", sa.min_inlier_share,
          "of the landed cells, inliers at least this share (occlusion and cells without a normal keep a "
          "true revisit below 1)");
  v.value("loop_surface_min_observability", sa.min_observability,
          "the weakest direction of (yaw x range, translation) carries at least this share of the pairs' "
          "constraint: one wall, or a floor and a wall, leave a direction free");
  v.value(
      "loop_surface_neighbours", sa.neighbours,
      "views beside each side's own keyframe in a surface verification: covisible keyframes flown within "
      "loop_min_age_s of it, those looking most unlike the views chosen (one view may see only a floor and "
      "a wall, or overlap the other too little)");
  v.value("loop_surface_independent_pairs", sa.independent_pairs,
          "the alignment's covariance counts this many independent pairs (neighbouring cells share surface "
          "and depth bias)");
  v.value(
      "loop_refine_chi2", l.refine_chi2,
      "after the 3D fit, a 4-DoF refit on pixels and depths with their noise; its inliers (whitened error "
      "below this, 3 DoF) must meet the two bounds above (0: no refit; relocalisation too)");
  v.value(
      "loop_max_correction_m", l.max_correction_m,
      "a loop's correction is drift: at most this + loop_max_correction_per_m x path since the candidate");
  v.value("loop_max_correction_per_m", l.max_correction_per_m, "drift per metre flown (beyond: an alias)");
  v.value("loop_max_yaw_rad", l.max_yaw_rad, "yaw correction at most this + loop_max_yaw_per_m x path");
  v.value("loop_max_yaw_per_m", l.max_yaw_per_m, "yaw drift per metre flown [rad/m]");
  v.value("loop_min_out_of_plane_m", l.min_out_of_plane_m,
          "a loop's inliers spread at least this far (RMS) off their best-fit plane: one wall fixes the "
          "correction along it by appearance alone");
  v.value(
      "loop_min_correction_chi2", l.min_correction_chi2,
      "a verified loop is closed only if its correction (yaw, position at the keyframe) is at least this far "
      "outside its own uncertainty: squared Mahalanobis length under the refit's covariance plus the loop "
      "edge's floor, 4 DoF (9.488: chi2 95 %; 0: close every verified loop)");
  v.value("loop_consistent_keyframes", l.consistent_keyframes,
          "consecutive keyframes that must verify the same correction");
  v.value("loop_consistency_m", l.consistency_m, "their corrections agree within this at the keyframe");
  v.value("loop_consistency_rad", l.consistency_rad, "... and this in yaw");
  v.value("loop_pose_graph_iterations", l.pose_graph_iterations, "4-DoF pose graph iterations");
  v.value("loop_covis_edge_min_shared", l.covis_edge_min_shared,
          "points shared by a covisibility edge of the pose graph");
  v.value("loop_cooldown_keyframes", l.cooldown_keyframes, "no new loop within this many keyframes of one");
  v.value("reloc_max_candidates", l.reloc_max_candidates,
          "best place-recognition candidates verified per lost keyframe");
  v.value("reloc_min_inliers", l.reloc_min_inliers,
          "inliers a relocalisation needs (no drift bound after a loss)");
  v.value("reloc_min_inlier_share", l.reloc_min_inlier_share, "... and this share of the matches");
  v.value("reloc_consistent_keyframes", l.reloc_consistent_keyframes,
          "consecutive lost keyframes that must give the same alignment");
  v.value("reloc_timeout_s", l.reloc_timeout_s,
          "lost mid-flight and not found again within this: mapping goes on in the odometry's alignment");
  v.end_section();
}

void visit_rgbd(RgbdEstimatorOptions& o, OptionVisitor& v) {
  WindowOptions& w = o.window;
  v.begin_section("rgbd",
                  "the rgbd backend: RGB-D tracking without an IMU (core/rgbd, docs/real-imagery.md)");
  v.value("use_window", o.use_window, "refine with the sliding window (false: the tracker's poses alone)");
  v.value("recent_frames", w.S, "S: most recent frames in its window");
  v.value("keyframes", w.N, "N: keyframes outside the recent frames; S + N <= 10");
  v.value("max_landmarks", w.max_landmarks, "landmark budget of its window, fixed at start-up");
  v.value("max_iterations", w.max_iterations, "iterations per solve (inline: no time budget)");
  v.value("huber_px", w.huber_px, "Huber threshold on the whitened residual norm (<= 0: least squares)");
  v.value("use_depth", w.use_depth, "RGB-D depth as a third row of the visual residual");
  v.value("pixel_sigma_px", w.pixel_sigma, "pixel noise of an observation that gives none");
  v.value("gauge_sigma", w.gauge_sigma, "stiff prior on the oldest state's pose [m, rad]");
  v.value("min_observations", o.min_observations, "a frame with fewer observations stays out of the window");
  v.value("pred_sigma_px", o.pred_sigma_px, "motion model pixel uncertainty at one frame (search window)");
  v.value("pred_sigma_px_per_s", o.pred_sigma_px_per_s, "its growth per second without a tracked frame");
  v.value("max_lost_frames", o.max_lost_frames, "untracked frames before the tracker and the window restart");
  v.value("use_map_pose", o.use_map_pose,
          "keyframes re-located on the local map carry that pose as a factor");
  v.value("map_pose_sigma_m", o.map_pose_sigma_m, "map pose factor sigma, lower bound");
  v.value("map_pose_sigma_rad", o.map_pose_sigma_rad, "map pose factor sigma, lower bound");
  v.value("max_correction_m", o.max_correction_m,
          "window vs tracked pose beyond this: the solve is not taken");
  v.end_section();
}

void visit_ekf(EkfEstimatorOptions& o, OptionVisitor& v) {
  v.begin_section("ekf", "the SE(3) EKF backend (core/ekf, docs/ekf.md)");
  v.value("landmark_capacity", o.landmark_capacity, "active landmarks in the filter; cost ~ (15 + 3C)^2");
  v.value("pixel_sigma_px", o.pixel_sigma_px, "pixel noise of every observation");
  v.value("max_missed_frames", o.max_missed_frames, "then a landmark leaves the filter into the map");
  v.value("spread_grid_cols", o.spread_grid_cols,
          "new tracks take free slots in the emptiest cells of this image grid first (0: tracker's order)");
  v.value("spread_grid_rows", o.spread_grid_rows, "rows of that grid (0 with cols 0)");
  v.value("gate_chi2", o.gate_chi2, "innovation gate (chi2, 4 dof; 13.28 = 99 %)");
  v.value("depthless_observations", o.depthless_observations,
          "a tracked pixel without depth updates its landmark with 2 rows (and brings in a map point)");
  v.value("mono_gate_chi2", o.mono_gate_chi2, "innovation gate for those (chi2, 2 dof; 9.21 = 99 %)");
  v.value("init_position_sigma_m", o.init_position_sigma_m, "start-up covariance");
  v.value("init_attitude_sigma_rad", o.init_attitude_sigma_rad, "start-up covariance");
  v.value("init_velocity_sigma_mps", o.init_velocity_sigma_mps, "start-up covariance");
  v.value("init_gyro_bias_sigma_rps", o.init_gyro_bias_sigma_rps, "start-up covariance");
  v.value("init_acc_bias_sigma_mps2", o.init_acc_bias_sigma_mps2, "start-up covariance");
  v.value("moving_start_after_ns", o.moving_start_after_ns,
          "no still window by then: start moving, tilt from the mean specific force");
  v.value("moving_init_attitude_sigma_rad", o.moving_init_attitude_sigma_rad, "after a moving start");
  v.value("moving_init_velocity_sigma_mps", o.moving_init_velocity_sigma_mps, "after a moving start");
  v.value("restart_position_sigma_m", o.restart_position_sigma_m,
          "position sigma after a re-initialisation (the coasted position is a guess)");
  v.value("default_gyro_noise_density_rad_s_sqrthz", o.default_gyro_noise_density, "when the rig gives none");
  v.value("default_acc_noise_density_mps2_sqrthz", o.default_acc_noise_density, "when the rig gives none");
  v.value("default_gyro_random_walk_rad_s2_sqrthz", o.default_gyro_random_walk, "when the rig gives none");
  v.value("default_acc_random_walk_mps3_sqrthz", o.default_acc_random_walk, "when the rig gives none");
  v.value("imu_noise_inflation", o.imu_noise_inflation,
          "every IMU noise density (the rig's or the defaults) is multiplied by this (docs/ekf.md)");
  v.value("pred_sigma_px_per_s", o.pred_sigma_px_per_s,
          "search window growth per second since the last update");
  v.value("pred_sigma_min_px", o.pred_sigma_min_px, "search window pixel uncertainty, lower bound");
  v.value("use_map_pose", o.use_map_pose,
          "keyframes re-located on the tracker's local map update the filter with that pose");
  v.value("map_pose_sigma_m", o.map_pose_sigma_m, "map pose measurement sigma, lower bound");
  v.value("map_pose_sigma_rad", o.map_pose_sigma_rad, "map pose measurement sigma, lower bound");
  v.value("map_pose_gate_chi2", o.map_pose_gate_chi2, "map pose innovation gate (chi2, 6 dof; 16.81 = 99 %)");
  v.value("map_pose_min_interval_s", o.map_pose_min_interval_s,
          "at most one map pose per this interval (the map is not independent of the filter)");
  v.value("max_lost_frames", o.max_lost_frames, "untracked frames before the tracker takes a new keyframe");
  v.value("min_used_for_tracking", o.min_used_for_tracking,
          "observations used for the frame to count as tracked");
  v.value("min_frame_interval_ms", o.min_frame_interval_ms,
          "a frame closer than this to the last one taken is skipped if that one tracked "
          "(the IMU carries the state; 50: every other frame of a 30 Hz camera; 0: every frame; "
          "negative: 50 with ekf.mapping, 0 without)");
  v.value("mapping", o.mapping,
          "run the map: section's local mapping and loop closing beside the filter "
          "(costs the mapping thread's CPU; set by --mapping on or off)");
  v.value("map_point_landmarks", o.map_point_landmarks,
          "with the map: a new landmark that is a map point starts at the map's position and sigma");
  v.end_section();
}

}  // namespace

LonscOptions lonsc_options(LonscVariant v) {
  return v == LonscVariant::kPaper ? LonscOptions::paper() : LonscOptions{};
}

const char* to_string(LonscVariant v) { return v == LonscVariant::kPaper ? "paper" : "tuned"; }

EstimatorConfig EstimatorConfig::defaults(const std::string& backend, LonscVariant variant) {
  if (!estimator_known(backend)) {
    throw std::invalid_argument("unknown estimator '" + backend + "' (expected one of: " + estimator_names() +
                                ")");
  }
  EstimatorConfig c;
  c.backend = backend;
  c.lonsc_variant = variant;
  c.tracker.lonsc = lonsc_options(variant);
  if (backend == "window-embedded") c.window.window = WindowOptions::embedded();
  if (backend == "window-ceres") c.window.window.solver = WindowOptions::Solver::kCeres;
  return c;
}

FrontendOdometryOptions EstimatorConfig::vo_options() const {
  FrontendOdometryOptions o = vo;
  o.tracker = tracker;
  o.divergence = safety;
  return o;
}

WindowEstimatorOptions EstimatorConfig::window_options() const {
  WindowEstimatorOptions o = window;
  o.frontend = vo_options();
  o.frontend.moving_start_after_ns = window_moving_start_after_ns;
  return o;
}

RgbdEstimatorOptions EstimatorConfig::rgbd_options() const {
  RgbdEstimatorOptions o = rgbd;
  o.tracker = tracker;
  o.divergence = safety;
  return o;
}

std::string resolve_backend(const std::string& backend, const Rig& rig) {
  if (backend != "auto") return backend;
  return rig.imu_rate_hz > 0 ? "window" : "rgbd";
}

EkfEstimatorOptions EstimatorConfig::ekf_options() const {
  EkfEstimatorOptions o = ekf;
  o.tracker = tracker;
  o.divergence = safety;
  // One map: section for every backend that can run it.
  o.map = window.map;
  return o;
}

namespace {

void visit_safety(DivergenceOptions& o, OptionVisitor& v) {
  v.begin_section("safety", "divergence detection in every backend that uses vision (docs/safety.md)");
  v.value("max_coast_s", o.max_coast_s,
          "IMU-only time after the last visual fix before the pose is reported lost (the state is kept)");
  v.value("max_lost_s", o.max_lost_s, "reported lost this long without a fix: the backend re-initialises");
  v.value("max_speed_mps", o.max_speed_mps, "an estimated speed beyond this is a divergence");
  v.value("max_acc_bias_mps2", o.max_acc_bias_mps2,
          "an accelerometer bias estimate beyond this is a divergence");
  v.value("max_gyro_bias_rps", o.max_gyro_bias_rps, "a gyro bias estimate beyond this is a divergence");
  v.value("max_position_sigma_m", o.max_position_sigma_m,
          "a position standard deviation beyond this (ekf, window) is a divergence");
  v.value("max_rejected_fixes", o.max_rejected_fixes,
          "consecutive tracked frames the backend refuses (vision vs IMU beyond the gate) before it "
          "re-initialises; "
          "0: off");
  v.end_section();
}

}  // namespace

void visit_options(EstimatorConfig& c, OptionVisitor& v) {
  {
    v.begin_section("estimator", "which backend runs");
    v.value(
        "backend", c.backend,
        "auto, window, window-embedded, window-ceres, vo, ekf, imu, rgbd (selects the defaults; auto: window "
        "with an IMU, rgbd without)");
    v.end_section();
  }
  {
    v.begin_section("frontend",
                    "the tracker every backend shares, and the vo backend's fusion (core/tracking)");
    enum_choice(v, "lonsc_variant", c.lonsc_variant, {"tuned", "paper"},
                "LONSC defaults: this project's (tuned) or paper 000's Algorithm 1 as printed (paper)");
    visit_vo(c.vo, v);
    visit_tracker(c.tracker, v);
    v.end_section();
  }
  visit_window(c, v);
  visit_map(c.window.map, v);
  visit_rgbd(c.rgbd, v);
  visit_ekf(c.ekf, v);
  visit_safety(c.safety, v);
}

// Every line of a section's errors carries the section, so each names its key.
// The frontend: section's keys reach every backend's options: a bad one is
// named once, under frontend:, not again for the window, ekf and rgbd.
static void add_section_errors(std::ostringstream& e, const char* section, const std::string& errors,
                               const std::string& skip = {}) {
  // Some validators join their messages with "; " instead of newlines.
  std::string text = errors;
  for (size_t at = 0; (at = text.find("; ", at)) != std::string::npos;) text.replace(at, 2, "\n");
  const std::string skip_lines = "\n" + skip;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) {
    // Some validators indent their lines for a message of their own.
    const size_t text_at = line.find_first_not_of(' ');
    if (text_at == std::string::npos || skip_lines.find("\n" + line + "\n") != std::string::npos) continue;
    e << section << ": " << line.substr(text_at) << "\n";
  }
}

std::string validate(const EstimatorConfig& c) {
  std::ostringstream e;
  if (!estimator_known(c.backend)) e << "estimator.backend: unknown '" << c.backend << "'\n";
  // vo's own keys and the tracker's; safety's are named once, below.
  FrontendOdometryOptions vo = c.vo_options();
  vo.divergence = DivergenceOptions{};
  const std::string tracker_errors = c.tracker.validate();
  add_section_errors(e, "frontend", vo.validate());
  if (c.window_moving_start_after_ns < 0) e << "window: moving_start_after_ns: must be >= 0\n";
  // The window's IMU noise comes from the rig at construction: validate the
  // rest with a nominal one.
  WindowEstimatorOptions w = c.window_options();
  ImuNoise nominal;
  nominal.gyro_noise_density_rad_s_sqrthz = 1e-4;
  nominal.acc_noise_density_mps2_sqrthz = 1e-3;
  nominal.gyro_random_walk_rad_s2_sqrthz = 1e-5;
  nominal.acc_random_walk_mps3_sqrthz = 1e-4;
  w.window.imu = ImuNoiseParams::from_imu_noise(nominal, 200.0);
  // The map's keys live in their own section but are validated with the
  // window's options: named once, under map.
  const std::string map_errors = c.window.map.validate();
  add_section_errors(e, "map", map_errors);
  add_section_errors(e, "window", w.validate(), tracker_errors + map_errors);
  add_section_errors(e, "ekf", c.ekf_options().validate(), tracker_errors);
  add_section_errors(e, "safety", c.safety.validate());
  RgbdEstimatorOptions r = c.rgbd_options();
  r.window.imu = w.window.imu;
  add_section_errors(e, "rgbd", r.validate(), tracker_errors);
  return e.str();
}

}  // namespace kestrel::core

#include "kestrel/loop_truth.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <map>
#include <stdexcept>

#include "kestrel/tools/trajectory_eval.hpp"

namespace kestrel::cli {
namespace {

// A keyframe's view for the overlap test: its true camera pose and its depth
// on a coarse grid (metres, 0: no reading).
struct View {
  uint32_t id = 0;
  int64_t t_ns = 0;
  int64_t depth_dt_ns = INT64_MAX;  // how far the depth image kept is from t_ns
  bool has_pose = false;
  Eigen::Isometry3d T_WC = Eigen::Isometry3d::Identity();
  std::vector<float> grid;
};

Eigen::Isometry3d iso_of(const Mat4d& m) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) T.matrix()(r, c) = m[static_cast<size_t>(4 * r + c)];
  return T;
}

class OverlapModel {
 public:
  OverlapModel(const Rig& rig, const LoopTruthOptions& opt) : rig_(rig), opt_(opt) {
    const CameraIntrinsics& c = rig.rgb;
    gw_ = std::max(1, c.width / opt.lookup_stride_px);
    gh_ = std::max(1, c.height / opt.lookup_stride_px);
  }
  int grid_w() const { return gw_; }
  int grid_h() const { return gh_; }

  void fill_grid(const drivers::LogImage& img, std::vector<float>& grid) const {
    grid.assign(static_cast<size_t>(gw_ * gh_), 0.0f);
    if (img.format != PixelFormat::kDepthU16) return;
    const int s = opt_.lookup_stride_px;
    for (int gy = 0; gy < gh_; ++gy) {
      for (int gx = 0; gx < gw_; ++gx) {
        const int u = gx * s, v = gy * s;
        if (u >= img.width || v >= img.height) continue;
        uint16_t raw = 0;
        std::memcpy(&raw, img.pixels.data() + (static_cast<size_t>(v) * img.width + u) * 2, 2);
        const double z = raw * rig_.depth.scale_m_per_unit;
        if (raw != 0 && z >= rig_.depth.min_range_m && z <= rig_.depth.max_range_m)
          grid[static_cast<size_t>(gy * gw_ + gx)] = static_cast<float>(z);
      }
    }
  }

  // Share of a's sampled depth points that b sees on its own surface.
  double share(const View& a, const View& b) const {
    if (a.grid.empty() || b.grid.empty() || !a.has_pose || !b.has_pose) return -1;
    const CameraIntrinsics& c = rig_.rgb;
    const Eigen::Isometry3d T_ba = b.T_WC.inverse() * a.T_WC;
    const int step = std::max(1, opt_.sample_stride_px / opt_.lookup_stride_px);
    const int s = opt_.lookup_stride_px;
    int n = 0, seen = 0;
    for (int gy = step / 2; gy < gh_; gy += step) {
      for (int gx = step / 2; gx < gw_; gx += step) {
        const double z = a.grid[static_cast<size_t>(gy * gw_ + gx)];
        if (z <= 0) continue;
        ++n;
        const Eigen::Vector3d p_a((gx * s - c.cx) * z / c.fx, (gy * s - c.cy) * z / c.fy, z);
        const Eigen::Vector3d p_b = T_ba * p_a;
        if (p_b.z() < rig_.depth.min_range_m || p_b.z() > rig_.depth.max_range_m) continue;
        const double u = c.fx * p_b.x() / p_b.z() + c.cx, v = c.fy * p_b.y() / p_b.z() + c.cy;
        const int bx = static_cast<int>(std::lround(u / s)), by = static_cast<int>(std::lround(v / s));
        if (u < 0 || v < 0 || u >= c.width || v >= c.height || bx >= gw_ || by >= gh_) continue;
        const double zb = b.grid[static_cast<size_t>(by * gw_ + bx)];
        if (zb <= 0) continue;
        const double sigma = rig_.depth.sigma_coeff_per_m * p_b.z() * p_b.z();
        if (std::abs(zb - p_b.z()) < opt_.surface_tol_m + 3.0 * sigma) ++seen;
      }
    }
    return n > 0 ? static_cast<double>(seen) / n : -1;
  }
  double overlap(const View& a, const View& b) const {
    const double max_reach = 2.0 * rig_.depth.max_range_m;
    if (a.has_pose && b.has_pose && (a.T_WC.translation() - b.T_WC.translation()).norm() > max_reach)
      return 0;
    return std::max(share(a, b), share(b, a));
  }

 private:
  const Rig& rig_;
  LoopTruthOptions opt_;
  int gw_ = 1, gh_ = 1;
};

double yaw_of_R(const Eigen::Matrix3d& R) { return std::atan2(R(1, 0), R(0, 0)); }

}  // namespace

LoopTruth evaluate_loops(drivers::LogSource& log, const core::LoopLog& loop_log,
                         const LoopTruthOptions& opt) {
  LoopTruth t;
  const Rig& rig = log.rig();
  if (rig.rgb.width <= 0 || rig.rgb.fx <= 0) {
    t.why_not = "the log's rig has no camera";
    return t;
  }
  // The keyframes the loop closer saw, by id.
  std::map<uint32_t, View> views;
  const auto add = [&views](uint32_t id, int64_t t_ns) {
    View& v = views[id];
    v.id = id;
    v.t_ns = t_ns;
  };
  for (const core::LoopQueryRecord& q : loop_log.queries) add(q.id, q.t_ns);
  for (const core::LoopCandidateRecord& c : loop_log.candidates) {
    if (!views.count(c.query_id)) add(c.query_id, c.query_t_ns);
    if (!views.count(c.candidate_id)) add(c.candidate_id, c.candidate_t_ns);
  }
  if (views.empty()) {
    t.why_not = "the loop closer saw no keyframe";
    return t;
  }
  std::vector<std::pair<int64_t, uint32_t>> by_time;
  by_time.reserve(views.size());

  for (const auto& [id, v] : views) by_time.emplace_back(v.t_ns, id);
  std::sort(by_time.begin(), by_time.end());
  const OverlapModel model(rig, opt);
  // A keyframe's image is the frame stamped at its time (the estimator's
  // clock is the camera's plus the rig's offset): the nearest depth within a
  // third of a frame period.
  const int64_t tol_ns =
      rig.camera_rate_hz > 0 ? static_cast<int64_t>(0.33e9 / rig.camera_rate_hz) : 10'000'000;
  tools::Trajectory gt;
  log.rewind();
  drivers::LogRecord rec;
  while (log.next(rec)) {
    if (rec.type == drivers::RecordType::kGroundTruth) {
      tools::TimedPose p;
      p.t_ns = rec.gt.t_ns;
      p.p = Eigen::Vector3d(rec.gt.p_WB[0], rec.gt.p_WB[1], rec.gt.p_WB[2]);
      p.q = Eigen::Quaterniond(rec.gt.q_WB[0], rec.gt.q_WB[1], rec.gt.q_WB[2], rec.gt.q_WB[3]).normalized();
      gt.push_back(p);
    } else if (rec.type == drivers::RecordType::kDepth) {
      const int64_t t_kf = rec.image.t_ns + rig.time_offset_cam_imu_ns;
      auto it = std::lower_bound(by_time.begin(), by_time.end(), std::make_pair(t_kf - tol_ns, uint32_t{0}));
      for (; it != by_time.end() && it->first <= t_kf + tol_ns; ++it) {
        View& v = views[it->second];
        const int64_t dt = std::abs(v.t_ns - t_kf);
        if (dt >= v.depth_dt_ns) continue;
        v.depth_dt_ns = dt;
        model.fill_grid(rec.image, v.grid);
      }
    }
  }
  log.rewind();
  if (gt.empty()) {
    t.why_not = "the log has no ground truth";
    return t;
  }
  std::sort(gt.begin(), gt.end(),
            [](const tools::TimedPose& a, const tools::TimedPose& b) { return a.t_ns < b.t_ns; });
  const Eigen::Isometry3d T_BC = iso_of(rig.T_BC);
  for (auto& [id, v] : views) {
    const auto p = tools::pose_at(gt, v.t_ns, 50'000'000);
    if (!p) continue;
    Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();
    T_WB.linear() = p->q.toRotationMatrix();
    T_WB.translation() = p->p;
    v.T_WC = T_WB * T_BC;
    v.has_pose = true;
    if (!v.grid.empty()) ++t.keyframes;
  }
  if (t.keyframes == 0) {
    t.why_not = "no keyframe has both depth and ground truth in the log";
    return t;
  }
  t.available = true;
  // Every revisit pair of the flight.
  const int64_t gap_ns = static_cast<int64_t>(opt.min_gap_s * 1e9);
  std::map<uint32_t, bool> revisit;  // later keyframe of a pair
  for (size_t i = 0; i < by_time.size(); ++i) {
    const View& a = views[by_time[i].second];
    if (a.grid.empty() || !a.has_pose) continue;
    for (size_t j = 0; j < i; ++j) {
      const View& b = views[by_time[j].second];
      if (a.t_ns - b.t_ns < gap_ns) break;
      if (b.grid.empty() || !b.has_pose) continue;
      if (model.overlap(a, b) >= opt.min_overlap) {
        ++t.revisit_pairs;
        revisit[a.id] = true;
      }
    }
  }
  t.revisit_keyframes = static_cast<int>(revisit.size());
  // What the loop closer made of them.
  std::map<uint32_t, bool> with_candidate, with_recognised, linked;
  t.per_candidate.resize(loop_log.candidates.size());
  for (size_t i = 0; i < loop_log.candidates.size(); ++i) {
    const core::LoopCandidateRecord& c = loop_log.candidates[i];
    LoopTruthCandidate& out = t.per_candidate[i];
    const View& q = views[c.query_id];
    const View& k = views[c.candidate_id];
    out.overlap = model.overlap(q, k);
    const bool is_true = out.overlap >= opt.min_overlap && std::abs(q.t_ns - k.t_ns) >= gap_ns;
    ++t.candidates;
    if (is_true) {
      ++t.candidates_true;
      with_candidate[c.query_id] = true;
    }
    const bool has_correction = c.verdict >= core::LoopVerdict::kPlanar;
    if (has_correction && q.has_pose && k.has_pose) {
      // Where the query keyframe is, if the candidate's map pose is right.
      const Eigen::Isometry3d T_MC_q_true = c.T_MC_candidate * (k.T_WC.inverse() * q.T_WC);
      const Eigen::Isometry3d corr_true = T_MC_q_true * c.T_MC_query.inverse();
      const Eigen::Vector3d pos = c.T_MC_query.translation();
      out.error_m = (c.correction * pos - corr_true * pos).norm();
      out.error_rad = std::abs(yaw_of_R(corr_true.linear().transpose() * c.correction.linear()));
    }
    if (c.surface_tried && q.has_pose && k.has_pose) {
      const Eigen::Isometry3d T_MC_q_true = c.T_MC_candidate * (k.T_WC.inverse() * q.T_WC);
      const Eigen::Isometry3d corr_true = T_MC_q_true * c.T_MC_query.inverse();
      const Eigen::Vector3d pos = c.T_MC_query.translation();
      out.surface_error_m = (c.surface_correction * pos - corr_true * pos).norm();
    }
    if (c.verdict == core::LoopVerdict::kVerified) {
      ++t.verified;
      if (is_true) ++t.verified_true;
    }
    if (c.verdict == core::LoopVerdict::kVerified || c.verdict == core::LoopVerdict::kInsignificant) {
      ++t.recognised;
      if (is_true) {
        ++t.recognised_true;
        with_recognised[c.query_id] = true;
      }
    }
    if (c.closed) {
      ++t.closed;
      if (out.error_m < 0 || out.error_m > opt.false_m || out.error_rad > opt.false_rad) ++t.closed_false;
    }
  }
  for (const core::LoopQueryRecord& q : loop_log.queries) {
    for (const auto& [old_id, shared] : q.old_links) {
      if (shared < opt.link_min_shared || !views.count(old_id)) continue;
      if (model.overlap(views[q.id], views[old_id]) >= opt.min_overlap) {
        linked[q.id] = true;
        break;
      }
    }
  }
  for (const auto& [id, _] : revisit) {
    if (with_candidate.count(id)) ++t.revisit_keyframes_candidate;
    if (with_recognised.count(id)) ++t.revisit_keyframes_recognised;
    if (linked.count(id)) ++t.revisit_keyframes_linked;
    if (with_recognised.count(id) || linked.count(id)) ++t.revisit_keyframes_found;
  }
  if (t.revisit_keyframes > 0) {
    t.loop_recall = static_cast<double>(t.revisit_keyframes_recognised) / t.revisit_keyframes;
    t.map_recall = static_cast<double>(t.revisit_keyframes_found) / t.revisit_keyframes;
  }
  return t;
}

void write_loop_log(const std::string& path, const core::LoopLog& loop_log, const LoopTruth& truth) {
  std::ofstream f(path);
  if (!f) throw std::runtime_error("--loop-log: cannot write " + path);
  f << "query_id,query_t_s,candidate_id,candidate_t_s,bow_score,place_points,matches,ransac_inliers,guided_"
       "matches,inliers,"
       "out_of_plane_m,correction_m,correction_rad,path_m,verdict,geometric,prior_seeded,chosen,inconsistent,"
       "closed,surface_tried,surface_ok,surface_failed,surface_overlap,surface_inlier_share,surface_rms_m,"
       "surface_observability,"
       "gt_overlap,"
       "gt_error_m,gt_error_rad,gt_surface_error_m\n";
  char line[768];
  for (size_t i = 0; i < loop_log.candidates.size(); ++i) {
    const core::LoopCandidateRecord& c = loop_log.candidates[i];
    const LoopTruthCandidate g =
        truth.available && i < truth.per_candidate.size() ? truth.per_candidate[i] : LoopTruthCandidate{};
    std::snprintf(
        line, sizeof line,
        "%u,%.6f,%u,%.6f,%.4f,%d,%d,%d,%d,%d,%.4f,%.4f,%.5f,%.2f,%s,%d,%d,%d,%d,%d,%d,%d,%s,%.3f,%.3f,%.4f,%."
        "4f,"
        "%.3f,%.4f,%.5f,%.4f\n",
        c.query_id, 1e-9 * static_cast<double>(c.query_t_ns), c.candidate_id,
        1e-9 * static_cast<double>(c.candidate_t_ns), c.score, c.place_points, c.matches, c.ransac_inliers,
        c.guided_matches, c.inliers, c.out_of_plane_m, c.correction_m, c.correction_rad, c.path_m,
        core::loop_verdict_name(c.verdict), c.geometric ? 1 : 0, c.prior_seeded ? 1 : 0, c.chosen ? 1 : 0,
        c.inconsistent ? 1 : 0, c.closed ? 1 : 0, c.surface_tried ? 1 : 0, c.surface_ok ? 1 : 0,
        (c.surface_failed != nullptr && c.surface_failed[0] != 0) ? c.surface_failed : "-", c.surface_overlap,
        c.surface_inlier_share, c.surface_rms_m, c.surface_observability, g.overlap, g.error_m, g.error_rad,
        g.surface_error_m);
    f << line;
  }
  if (!f) throw std::runtime_error("--loop-log: write failed: " + path);
}

std::string loop_truth_summary(const LoopTruth& t) {
  if (!t.available) return "loops against the ground truth: not available (" + t.why_not + ")";
  char s[768];
  std::snprintf(
      s, sizeof s,
      "loops against the ground truth: %d revisit keyframes (%d pairs) of %d; candidates %d (%d true, "
      "reaching %d revisit keyframes); recognised %d (%d true), of which verified %d (%d true); closed "
      "%d, false %d; revisit keyframes recognised by the loop closer %d (recall %.0f %%), linked by "
      "the local map %d, found either way %d (%.0f %%)",
      t.revisit_keyframes, t.revisit_pairs, t.keyframes, t.candidates, t.candidates_true,
      t.revisit_keyframes_candidate, t.recognised, t.recognised_true, t.verified, t.verified_true, t.closed,
      t.closed_false, t.revisit_keyframes_recognised, 100.0 * t.loop_recall, t.revisit_keyframes_linked,
      t.revisit_keyframes_found, 100.0 * t.map_recall);
  return s;
}

}  // namespace kestrel::cli

// The revisits a flight should have closed, from its ground truth, against
// what the loop closer did (tools/kestrel/loop_truth.hpp).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <sstream>
#include <string>

#include "kestrel/loop_truth.hpp"

namespace kestrel::cli {
namespace {

// A log of constant-depth frames (a wall 2 m ahead) and ground-truth poses.
class WallLog : public drivers::LogSource {
 public:
  WallLog() {
    rig_.rgb.width = 64;
    rig_.rgb.height = 48;
    rig_.rgb.fx = rig_.rgb.fy = 50;
    rig_.rgb.cx = 32;
    rig_.rgb.cy = 24;
    rig_.camera_rate_hz = 20;
  }
  void add_view(int64_t t_ns, double yaw_about_camera_y) {
    drivers::LogRecord g;
    g.type = drivers::RecordType::kGroundTruth;
    g.gt.t_ns = t_ns;
    g.gt.q_WB = {std::cos(yaw_about_camera_y / 2), 0, std::sin(yaw_about_camera_y / 2), 0};
    records_.push_back(g);
    drivers::LogRecord d;
    d.type = drivers::RecordType::kDepth;
    d.image.t_ns = t_ns;
    d.image.width = 64;
    d.image.height = 48;
    d.image.format = PixelFormat::kDepthU16;
    d.image.pixels.resize(64 * 48 * 2);
    for (size_t i = 0; i < d.image.pixels.size(); i += 2) {
      const uint16_t mm = 2000;
      std::memcpy(&d.image.pixels[i], &mm, 2);
    }
    records_.push_back(d);
  }
  const Rig& rig() const override { return rig_; }
  bool next(drivers::LogRecord& out) override {
    if (next_ >= records_.size()) return false;
    out = records_[next_++];
    return true;
  }
  void rewind() override { next_ = 0; }
  const std::vector<drivers::LogProblem>& problems() const override { return problems_; }
  std::string format_name() const override { return "wall"; }

 private:
  Rig rig_;
  std::vector<drivers::LogRecord> records_;
  std::vector<drivers::LogProblem> problems_;
  size_t next_ = 0;
};

constexpr int64_t kS = 1'000'000'000;

std::vector<core::LoopQueryRecord> queries(std::initializer_list<std::pair<uint32_t, int64_t>> list) {
  std::vector<core::LoopQueryRecord> out;
  for (const auto& [id, t_ns] : list) {
    core::LoopQueryRecord q;
    q.id = id;
    q.t_ns = t_ns;
    out.push_back(q);
  }
  return out;
}

core::LoopCandidateRecord candidate(uint32_t q, int64_t tq, uint32_t c, int64_t tc, core::LoopVerdict v) {
  core::LoopCandidateRecord r;
  r.query_id = q;
  r.query_t_ns = tq;
  r.candidate_id = c;
  r.candidate_t_ns = tc;
  r.verdict = v;
  return r;
}

TEST(LoopTruth, CountsRevisitsCandidatesAndFalseClosures) {
  WallLog log;
  log.add_view(0, 0.0);         // keyframe 1
  log.add_view(5 * kS, 0.0);    // 2: the same view, too soon to be a loop
  log.add_view(20 * kS, 0.0);   // 3: the same view again, a revisit of 1 and 2
  log.add_view(30 * kS, M_PI);  // 4: turned around: sees nothing 1 saw
  core::LoopLog ll;
  ll.queries = queries({{1, 0}, {2, 5 * kS}, {3, 20 * kS}, {4, 30 * kS}});
  auto right = candidate(3, 20 * kS, 1, 0, core::LoopVerdict::kVerified);
  right.chosen = right.closed = true;  // correction identity = the truth
  auto wrong = candidate(3, 20 * kS, 2, 5 * kS, core::LoopVerdict::kVerified);
  wrong.chosen = wrong.closed = true;
  wrong.correction.translation() = Eigen::Vector3d(0.2, 0, 0);
  const auto alias = candidate(4, 30 * kS, 1, 0, core::LoopVerdict::kFewInliers);
  ll.candidates = {right, wrong, alias};

  const LoopTruth t = evaluate_loops(log, ll);
  ASSERT_TRUE(t.available) << t.why_not;
  EXPECT_EQ(t.keyframes, 4);
  EXPECT_EQ(t.revisit_pairs, 2);
  EXPECT_EQ(t.revisit_keyframes, 1);
  EXPECT_EQ(t.candidates, 3);
  EXPECT_EQ(t.candidates_true, 2);
  EXPECT_EQ(t.revisit_keyframes_candidate, 1);
  EXPECT_EQ(t.verified, 2);
  EXPECT_EQ(t.verified_true, 2);
  EXPECT_EQ(t.recognised, 2);
  EXPECT_EQ(t.closed, 2);
  EXPECT_EQ(t.closed_false, 1);
  EXPECT_DOUBLE_EQ(t.loop_recall, 1.0);
  EXPECT_EQ(t.revisit_keyframes_linked, 0);
  ASSERT_EQ(t.per_candidate.size(), 3u);
  EXPECT_NEAR(t.per_candidate[0].overlap, 1.0, 1e-9);
  EXPECT_NEAR(t.per_candidate[0].error_m, 0.0, 1e-9);
  EXPECT_NEAR(t.per_candidate[1].error_m, 0.2, 1e-9);
  EXPECT_NEAR(t.per_candidate[2].overlap, 0.0, 1e-9);
  EXPECT_LT(t.per_candidate[2].error_m, 0);  // never verified: no correction to score

  const std::string path = ::testing::TempDir() + "loop_log.csv";
  write_loop_log(path, ll, t);
  std::ifstream f(path);
  std::stringstream all;
  all << f.rdbuf();
  const std::string csv = all.str();
  EXPECT_EQ(std::count(csv.begin(), csv.end(), '\n'), 4);
  EXPECT_NE(csv.find("few_inliers"), std::string::npos);
  EXPECT_NE(csv.find("gt_overlap"), std::string::npos);
  EXPECT_NE(loop_truth_summary(t).find("false 1"), std::string::npos);
}

TEST(LoopTruth, ARevisitTheMapAlreadyLinkedIsFoundWithoutALoop) {
  WallLog log;
  log.add_view(0, 0.0);
  log.add_view(20 * kS, 0.0);  // a revisit of 1
  log.add_view(40 * kS, 0.0);  // a revisit of 1 and 2
  core::LoopLog ll;
  ll.queries = queries({{1, 0}, {2, 20 * kS}, {3, 40 * kS}});
  ll.queries[1].old_links = {{1, 40}};  // fused with the old place: linked
  ll.queries[2].old_links = {{1, 3}};   // a few points only: not a link
  const LoopTruth t = evaluate_loops(log, ll);
  ASSERT_TRUE(t.available) << t.why_not;
  EXPECT_EQ(t.revisit_keyframes, 2);
  EXPECT_EQ(t.revisit_keyframes_linked, 1);
  EXPECT_EQ(t.revisit_keyframes_found, 1);
  EXPECT_DOUBLE_EQ(t.map_recall, 0.5);
  EXPECT_DOUBLE_EQ(t.loop_recall, 0.0);
}

TEST(LoopTruth, SaysWhyWithoutGroundTruth) {
  WallLog log;  // no views at all
  core::LoopLog ll;
  ll.queries = queries({{1, 0}});
  const LoopTruth t = evaluate_loops(log, ll);
  EXPECT_FALSE(t.available);
  EXPECT_NE(t.why_not.find("ground truth"), std::string::npos);
  EXPECT_NE(loop_truth_summary(t).find("not available"), std::string::npos);
}

}  // namespace
}  // namespace kestrel::cli

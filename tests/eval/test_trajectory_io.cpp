// Trajectory loaders: TUM, EuRoC CSV, malformed input, repairs, round trip.
#include <gtest/gtest.h>

#include <cmath>

#include "eval_test_util.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "test_data.hpp"

namespace kestrel::tools {
namespace {

bool contains(const std::vector<std::string>& v, const std::string& a, const std::string& b = "") {
  for (const auto& s : v)
    if (s.find(a) != std::string::npos && s.find(b) != std::string::npos) return true;
  return false;
}

std::string joined(const std::vector<std::string>& v) {
  std::string out;
  for (const auto& s : v) out += s + "\n";
  return out;
}

TEST(EvalLoad, TumTextWithCommentsBlankLinesAndCrlf) {
  const std::string dir = test::temp_dir("eval_tum_ok");
  const std::string path = dir + "/traj.txt";
  test::write_text(path,
                   "# ground truth trajectory\n"
                   "# timestamp tx ty tz qx qy qz qw\n"
                   "\n"
                   "1305031098.6659 1.3563 0.6305 1.6380 0.6132 0.5962 -0.3311 -0.3986\r\n"
                   "   1305031098.6758\t1.3543 0.6306 1.6360 0 0 0 1\n"
                   "1305031098.7 1 2 3 0 0 0 2\n");
  std::vector<std::string> w;
  const Trajectory t = load_trajectory(path, &w);
  // Only the (0,0,0,2) quaternion is worth a word: 4-digit files are ~1e-4 off unit norm.
  ASSERT_EQ(w.size(), 1u) << joined(w);
  EXPECT_NE(w[0].find("1 quaternions were more than 1% off unit norm"), std::string::npos) << w[0];
  ASSERT_EQ(t.size(), 3u);
  EXPECT_EQ(t[0].t_ns, 1305031098665900000);  // every decimal digit kept
  EXPECT_EQ(t[1].t_ns, 1305031098675800000);
  EXPECT_EQ(t[2].t_ns, 1305031098700000000);
  EXPECT_DOUBLE_EQ(t[0].p.x(), 1.3563);
  EXPECT_DOUBLE_EQ(t[0].p.z(), 1.6380);
  // TUM stores qx qy qz qw: w comes last.
  const double n0 = std::sqrt(0.6132 * 0.6132 + 0.5962 * 0.5962 + 0.3311 * 0.3311 + 0.3986 * 0.3986);
  EXPECT_NEAR(t[0].q.w(), -0.3986 / n0, 1e-12);
  EXPECT_NEAR(t[0].q.x(), 0.6132 / n0, 1e-12);
  EXPECT_DOUBLE_EQ(t[1].q.w(), 1.0);
  EXPECT_DOUBLE_EQ(t[2].q.w(), 1.0);  // normalised from (0,0,0,2)
}

TEST(EvalLoad, TumMalformedLinesNameFileLineAndField) {
  const std::string dir = test::temp_dir("eval_tum_bad");
  const std::string path = dir + "/traj.txt";
  test::write_text(path,
                   "# t x y z qx qy qz qw\n"
                   "1.0 0 0 0 0 0 0 1\n"
                   "2.0 0 0 0 0 0 1\n"      // line 3: 7 fields
                   "3.0 0 0 0 abc 0 0 1\n"  // line 4: qx not a number
                   "4.0 0 0 nan 0 0 0 1\n"  // line 5: tz non-finite
                   "5.0 0 0 0 0 0 0 0\n"    // line 6: zero quaternion
                   "6.0s 0 0 0 0 0 0 1\n"   // line 7: bad time
                   "7.0 1 1 1 0 0 0 1\n");
  std::vector<std::string> w;
  const Trajectory t = load_trajectory(path, &w);
  EXPECT_EQ(t.size(), 2u);
  EXPECT_EQ(w.size(), 5u) << joined(w);
  EXPECT_TRUE(contains(w, path + ":3:", "7 fields")) << joined(w);
  EXPECT_TRUE(contains(w, path + ":4:", "'qx'")) << joined(w);
  EXPECT_TRUE(contains(w, path + ":5:", "'tz'")) << joined(w);
  EXPECT_TRUE(contains(w, path + ":5:", "non-finite")) << joined(w);
  EXPECT_TRUE(contains(w, path + ":6:", "quaternion")) << joined(w);
  EXPECT_TRUE(contains(w, path + ":7:", "'timestamp'")) << joined(w);

  // No warnings sink: the first loss is an error, never a silent skip.
  try {
    load_trajectory(path, nullptr);
    FAIL() << "expected an exception";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(path + ":3:"), std::string::npos) << e.what();
  }
}

TEST(EvalLoad, EurocCsvBodyAndOfficialLayouts) {
  const std::string dir = test::temp_dir("eval_euroc_ok");
  const std::string body = dir + "/gt_body_20hz.csv";
  test::write_text(
      body,
      "#timestamp [ns],p_WB_x [m],p_WB_y [m],p_WB_z [m],q_WB_w [],q_WB_x [],q_WB_y [],q_WB_z []\n"
      "1403715524912143104,0.5,2.0,0.97,0.7071067811865476,0.7071067811865476,0,0\n"
      "1403715524962142976, 0.6, 2.1, 0.98, 1, 0, 0, 0\n");
  std::vector<std::string> w;
  Trajectory t = load_trajectory(body, &w);
  EXPECT_TRUE(w.empty()) << joined(w);
  ASSERT_EQ(t.size(), 2u);
  EXPECT_EQ(t[0].t_ns, 1403715524912143104);
  EXPECT_EQ(t[1].t_ns, 1403715524962142976);
  // EuRoC stores qw first.
  EXPECT_NEAR(t[0].q.w(), std::sqrt(0.5), 1e-15);
  EXPECT_NEAR(t[0].q.x(), std::sqrt(0.5), 1e-15);
  EXPECT_DOUBLE_EQ(t[1].p.y(), 2.1);

  // state_groundtruth_estimate0/data.csv: 17 columns, a header without '#', no .csv hint needed.
  const std::string official = dir + "/data.txt";
  test::write_text(
      official,
      "timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
      "v_x, v_y, v_z, bw_x, bw_y, bw_z, ba_x, ba_y, ba_z\n"
      "1403715524907143168,0.515356,1.996773,0.971104,0.161996,0.789985,-0.205376,0.554528,-0.002276,"
      "-0.009616,-0.005214,-0.002153,0.020744,0.075806,-0.013337,0.103464,0.093086\n");
  w.clear();
  t = load_trajectory(official, &w);
  EXPECT_TRUE(w.empty()) << joined(w);
  ASSERT_EQ(t.size(), 1u);
  EXPECT_DOUBLE_EQ(t[0].p.x(), 0.515356);
  EXPECT_NEAR(t[0].q.w(), 0.161996, 1e-5);
}

TEST(EvalLoad, EurocCsvMalformedLinesNameFileLineAndField) {
  const std::string dir = test::temp_dir("eval_euroc_bad");
  const std::string path = dir + "/gt.csv";
  test::write_text(path,
                   "#t,px,py,pz,qw,qx,qy,qz\n"
                   "1000,0,0,0,1,0,0,0\n"
                   "1.5e9,0,0,0,1,0,0,0\n"   // line 3: seconds, not ns
                   "3000,0,0,0,1,0,x,0\n"    // line 4: q_y
                   "4000,0,0,0,1,0,0\n"      // line 5: 7 fields
                   "5000,0,inf,0,1,0,0,0\n"  // line 6: p_y
                   "6000,1,1,1,1,0,0,0\n");
  std::vector<std::string> w;
  const Trajectory t = load_trajectory(path, &w);
  EXPECT_EQ(t.size(), 2u);
  EXPECT_EQ(w.size(), 4u) << joined(w);
  EXPECT_TRUE(contains(w, path + ":3:", "'timestamp'")) << joined(w);
  EXPECT_TRUE(contains(w, path + ":4:", "'q_y'")) << joined(w);
  EXPECT_TRUE(contains(w, path + ":5:", "7 fields")) << joined(w);
  EXPECT_TRUE(contains(w, path + ":6:", "'p_y'")) << joined(w);
  EXPECT_THROW(load_trajectory(path, nullptr), std::runtime_error);
}

TEST(EvalLoad, UnsortedAndDuplicateTimestampsAreRepairedAndReported) {
  const std::string dir = test::temp_dir("eval_sort");
  const std::string path = dir + "/traj.txt";
  test::write_text(path,
                   "1.0 1 0 0 0 0 0 1\n"
                   "3.0 3 0 0 0 0 0 1\n"
                   "2.0 2 0 0 0 0 0 1\n"  // line 3: out of order
                   "3.0 3 0 0 0 0 0 1\n"  // line 4: exact duplicate of line 2
                   "4.0 4 0 0 0 0 0 1\n"
                   "4.0 9 0 0 0 0 0 1\n");  // line 6: same time, different pose
  std::vector<std::string> w;
  const Trajectory t = load_trajectory(path, &w);
  ASSERT_EQ(t.size(), 4u);
  for (size_t i = 0; i < t.size(); ++i) {
    EXPECT_EQ(t[i].t_ns, static_cast<int64_t>(i + 1) * 1'000'000'000);
    EXPECT_DOUBLE_EQ(t[i].p.x(), static_cast<double>(i + 1));  // first of a conflicting pair kept
  }
  EXPECT_TRUE(contains(w, path + ":3:", "sorted")) << joined(w);
  EXPECT_TRUE(contains(w, path + ":4:", "1 exact duplicates dropped")) << joined(w);
  EXPECT_TRUE(contains(w, path + ":6:", "different pose")) << joined(w);
  EXPECT_EQ(w.size(), 3u) << joined(w);
}

TEST(EvalLoad, ManyBadLinesAreCountedNotAllListed) {
  const std::string dir = test::temp_dir("eval_many_bad");
  const std::string path = dir + "/traj.txt";
  std::string text = "0.5 0 0 0 0 0 0 1\n";
  for (int i = 0; i < 100; ++i) text += "garbage\n";
  test::write_text(path, text);
  std::vector<std::string> w;
  EXPECT_EQ(load_trajectory(path, &w).size(), 1u);
  ASSERT_EQ(w.size(), 21u);
  EXPECT_NE(w.back().find("80 more"), std::string::npos) << w.back();
}

TEST(EvalLoad, MissingOrEmptyFilesThrowNamingThePath) {
  const std::string dir = test::temp_dir("eval_missing");
  try {
    load_trajectory(dir + "/nope.txt", nullptr);
    FAIL();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(dir + "/nope.txt"), std::string::npos) << e.what();
  }
  test::write_text(dir + "/empty.txt", "# nothing\n\n");
  std::vector<std::string> w;
  try {
    load_trajectory(dir + "/empty.txt", &w);
    FAIL();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("empty.txt"), std::string::npos) << e.what();
  }
}

TEST(EvalLoad, WriteTumRoundTripsExactly) {
  const std::string dir = test::temp_dir("eval_roundtrip");
  Trajectory t = test::lissajous(2.0, 100.0, 1403715524912143104);
  t[3].t_ns += 7;  // odd nanoseconds survive
  write_tum(dir + "/out.txt", t);
  std::vector<std::string> w;
  const Trajectory back = load_trajectory(dir + "/out.txt", &w);
  EXPECT_TRUE(w.empty()) << joined(w);
  ASSERT_EQ(back.size(), t.size());
  for (size_t i = 0; i < t.size(); ++i) {
    EXPECT_EQ(back[i].t_ns, t[i].t_ns);
    EXPECT_LT((back[i].p - t[i].p).norm(), 1e-9);
    EXPECT_LT(back[i].q.angularDistance(t[i].q), 1e-11);
  }
  EXPECT_THROW(write_tum(dir + "/no/such/dir/out.txt", t), std::runtime_error);
}

TEST(EvalRealData, EurocBodyGroundTruthAgreesWithOfficial) {
  KESTREL_REQUIRE_SHARED("euroc/V1_02_medium/gt_official_200hz.csv");
  const std::string body = test::shared_path("euroc/V1_02_medium/gt_body_20hz.csv");
  const std::string official = test::shared_path("euroc/V1_02_medium/gt_official_200hz.csv");
  std::vector<std::string> w;
  const Trajectory gt = load_trajectory(official, &w);
  const Trajectory est = load_trajectory(body, &w);
  EXPECT_TRUE(w.empty()) << joined(w);
  EvalOptions o;
  o.align = Alignment::kNone;
  o.max_gap_ms = 10;
  const EvalResult r = evaluate(gt, est, o);
  EXPECT_EQ(r.unmatched, 0);
  EXPECT_EQ(r.matched, static_cast<int>(est.size()));
  // data/README.md: the converted body file matches the official one to 13 um.
  EXPECT_LT(r.ate_m.max, 1e-4);
  EXPECT_LT(r.ate_rot_deg.max, 0.05);
}

}  // namespace
}  // namespace kestrel::tools

namespace kestrel::tools {
namespace {

// A folder goes through drivers::open_log and yields its ground-truth records.
TEST(EvalRealData, TumRgbdFolderLoadsThroughLogSource) {
  KESTREL_REQUIRE_SHARED("tum-rgbd/rgbd_dataset_freiburg1_xyz/rgb.txt");
  const std::string dir = test::shared_path("tum-rgbd/rgbd_dataset_freiburg1_xyz");
  std::vector<std::string> w_dir, w_file;
  const Trajectory via_log = load_trajectory(dir, &w_dir);
  const Trajectory direct = load_trajectory(dir + "/groundtruth.txt", &w_file);
  EXPECT_TRUE(w_file.empty()) << joined(w_file);
  ASSERT_EQ(via_log.size(), direct.size()) << joined(w_dir);
  for (size_t i = 0; i < direct.size(); ++i) {
    ASSERT_EQ(via_log[i].t_ns, direct[i].t_ns) << i;
    ASSERT_LT((via_log[i].p - direct[i].p).norm(), 1e-9) << i;
    ASSERT_LT(via_log[i].q.angularDistance(direct[i].q), 1e-6) << i;
  }
}

}  // namespace
}  // namespace kestrel::tools

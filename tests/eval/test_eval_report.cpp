// Output contracts: text first line, text/JSON key parity, JSON escaping, SVG,
// the HTML report and the replay metrics it reads.
#include <gtest/gtest.h>

#include <fstream>
#include <regex>
#include <sstream>

#include "eval_test_util.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "test_data.hpp"

namespace kestrel::tools {
namespace {

EvalResult offset_result() {
  const Trajectory gt = test::lissajous(10.0);
  const Trajectory est = test::transformed(gt, 1.0, Eigen::Matrix3d::Identity(), Eigen::Vector3d(0.1, 0, 0));
  EvalOptions o;
  o.align = Alignment::kNone;
  return evaluate(gt, est, o);
}

std::vector<std::string> lines(const std::string& s) {
  std::vector<std::string> out;
  std::istringstream in(s);
  std::string l;
  while (std::getline(in, l)) out.push_back(l);
  return out;
}

TEST(EvalReport, TextFirstLineIsAteRmseAndEveryLineIsKeyValue) {
  const EvalResult r = offset_result();
  const std::string text = to_text(r);
  const auto ls = lines(text);
  ASSERT_FALSE(ls.empty());
  EXPECT_EQ(ls.front(), "ate_rmse_m: 0.1");
  EXPECT_EQ(text.back(), '\n');
  const std::regex kv("^[a-z0-9_.]+: .*$");
  for (const auto& l : ls) EXPECT_TRUE(std::regex_match(l, kv)) << l;
  for (const char* key : {"ate_mean_m: ", "ate_median_m: ", "ate_max_m: ", "ate_rot_rmse_deg: ",
                          "rpe_trans_rmse_m: ", "rpe_trans_m_per_s: ", "rpe_rot_rmse_deg: ", "matched: ",
                          "unmatched: ", "align: none", "scale: 1", "coverage: 1"})
    EXPECT_NE(text.find(std::string("\n") + key), std::string::npos) << key;
}

TEST(EvalReport, JsonHasTheSameKeysInTheSameOrder) {
  const EvalResult r = offset_result();
  const auto text_lines = lines(to_text(r));
  const std::string json = to_json(r);
  const auto json_lines = lines(json);
  ASSERT_GE(json_lines.size(), 3u);
  EXPECT_EQ(json_lines.front(), "{");
  EXPECT_EQ(json_lines.back(), "}");
  ASSERT_EQ(json_lines.size(), text_lines.size() + 2);
  const std::regex member("^  \"([a-z0-9_.]+)\": (.*?)(,?)$");
  for (size_t i = 0; i < text_lines.size(); ++i) {
    std::smatch m;
    const std::string& jl = json_lines[i + 1];
    ASSERT_TRUE(std::regex_match(jl, m, member)) << jl;
    EXPECT_EQ(text_lines[i].substr(0, text_lines[i].find(':')), m[1].str());
    EXPECT_EQ(m[3].str(), i + 1 < text_lines.size() ? "," : "") << jl;
  }
  EXPECT_NE(json.find("\"ate_rmse_m\": 0.1,"), std::string::npos);
  EXPECT_NE(json.find("\"align\": \"none\""), std::string::npos);
}

TEST(EvalReport, NonFiniteIsNullInJsonAndStringsAreEscaped) {
  // Shorter than the RPE step: RPE undefined.
  const Trajectory gt = test::lissajous(0.5);
  EvalOptions o;
  o.align = Alignment::kNone;
  EvalResult r = evaluate(gt, gt, o);
  r.est_file = "dir\\with \"quotes\"\nand\ttab\x01.txt";
  EXPECT_EQ(r.rpe_pairs, 0);
  const std::string json = to_json(r);
  EXPECT_NE(json.find("\"rpe_trans_rmse_m\": null,"), std::string::npos) << json;
  EXPECT_NE(json.find("\"est_file\": \"dir\\\\with \\\"quotes\\\"\\nand\\ttab\\u0001.txt\""),
            std::string::npos)
      << json;
  EXPECT_EQ(json.find(": nan"), std::string::npos);
  EXPECT_EQ(json.find(": inf"), std::string::npos);
  const std::string text = to_text(r);
  EXPECT_NE(text.find("\nrpe_trans_rmse_m: nan\n"), std::string::npos);
  // A newline in a value must not break the one-key-per-line contract.
  for (const auto& l : lines(text)) EXPECT_NE(l.find(": "), std::string::npos) << l;
}

TEST(EvalReport, SvgPlotIsSelfContained) {
  const Trajectory gt = test::lissajous(20.0);
  const Trajectory est = test::transformed(gt, 1.0, Eigen::Matrix3d::Identity(), Eigen::Vector3d(0.05, 0, 0));
  const EvalResult r = evaluate(gt, est, EvalOptions{});
  const std::string dir = test::temp_dir("eval_svg");
  write_svg_plot(dir + "/plot.svg", gt, r, "run <1> & \"2\"");
  std::ifstream f(dir + "/plot.svg");
  std::stringstream ss;
  ss << f.rdbuf();
  const std::string svg = ss.str();
  EXPECT_EQ(svg.rfind("<?xml", 0), 0u);
  EXPECT_NE(svg.find("<svg xmlns='http://www.w3.org/2000/svg'"), std::string::npos);
  EXPECT_NE(svg.find("</svg>\n"), std::string::npos);
  EXPECT_NE(svg.find("x [m]"), std::string::npos);
  EXPECT_NE(svg.find("y [m]"), std::string::npos);
  EXPECT_NE(svg.find("position error [m]"), std::string::npos);
  EXPECT_NE(svg.find("ground truth"), std::string::npos);
  EXPECT_NE(svg.find("run &lt;1&gt; &amp; &quot;2&quot;"), std::string::npos);
  EXPECT_EQ(svg.find("run <1>"), std::string::npos);
  EXPECT_EQ(svg.find("href"), std::string::npos);  // nothing external
  EXPECT_EQ(svg.find("nan"), std::string::npos);
  size_t polylines = 0;
  for (size_t p = svg.find("<polyline"); p != std::string::npos; p = svg.find("<polyline", p + 1))
    ++polylines;
  EXPECT_EQ(polylines, 3u);  // GT, estimate, error curve
  EXPECT_THROW(write_svg_plot(dir + "/no/such/plot.svg", gt, r), std::runtime_error);
}

std::string slurp(const std::string& path) {
  std::ifstream f(path);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

TEST(EvalReport, RpeAtTheEvaluatedStepIsWhatEvaluateReports) {
  const Trajectory gt = test::lissajous(20.0);
  Trajectory est = test::transformed(gt, 1.0, Eigen::Matrix3d::Identity(), Eigen::Vector3d(0.05, 0, 0));
  for (size_t i = 0; i < est.size(); ++i) est[i].p.x() += 0.002 * std::sin(0.37 * static_cast<double>(i));
  EvalOptions o;
  o.rpe_delta_s = 2.0;
  const EvalResult r = evaluate(gt, est, o);
  const RpeStats s = relative_pose_error(r, 2.0, o.max_gap_ms);
  EXPECT_EQ(s.pairs, r.rpe_pairs);
  EXPECT_DOUBLE_EQ(s.trans_rmse_m, r.rpe_trans_rmse_m);
  EXPECT_DOUBLE_EQ(s.rot_rmse_deg, r.rpe_rot_rmse_deg);
  EXPECT_GT(relative_pose_error(r, 0.5, o.max_gap_ms).pairs, s.pairs);  // shorter steps fit more often
  EXPECT_EQ(relative_pose_error(r, 60.0, o.max_gap_ms).pairs, 0);       // longer than the run
  EXPECT_THROW(relative_pose_error(r, 0.0, o.max_gap_ms), std::invalid_argument);
}

TEST(EvalReport, HtmlReportIsSelfContainedAndHasEveryPlot) {
  const Trajectory gt = test::lissajous(20.0);
  const Trajectory est = test::transformed(gt, 1.0, Eigen::Matrix3d::Identity(), Eigen::Vector3d(0.05, 0, 0));
  EvalResult r = evaluate(gt, est, EvalOptions{});
  r.gt_file = "gt <a>.csv";
  const std::string dir = test::temp_dir("eval_html");
  HtmlReportOptions o;
  o.title = "run & co";
  LatencyDistribution d;
  d.name = "tracking";
  d.count = 30;
  d.p50_ms = 5;
  d.p99_ms = 9;
  d.max_ms = 10;
  d.bins = {{4'000'000, 65'536, 10}, {5'000'000, 65'536, 15}, {9'000'000, 131'072, 5}};
  o.latencies = {d};
  write_html_report(dir + "/r.html", gt, r, o);
  const std::string h = slurp(dir + "/r.html");
  EXPECT_EQ(h.rfind("<!doctype html>", 0), 0u);
  for (const char* id : {"summary", "top-view", "side-view", "error-time", "error-rotation", "error-axes",
                         "rpe-table", "rpe", "latency", "latency-tracking"})
    EXPECT_NE(h.find(std::string("id='") + id + "'"), std::string::npos) << id;
  EXPECT_NE(h.find("gt &lt;a&gt;.csv"), std::string::npos);
  EXPECT_NE(h.find("run &amp; co"), std::string::npos);
  // Nothing to fetch: no script, no link, no external reference.
  EXPECT_EQ(h.find("<script"), std::string::npos);
  EXPECT_EQ(h.find("<link"), std::string::npos);
  EXPECT_EQ(h.find("src="), std::string::npos);
  EXPECT_EQ(h.find("href="), std::string::npos);
  EXPECT_EQ(h.find("nan"), std::string::npos);
  size_t bars = 0;
  for (size_t p = h.find("class='bar'"); p != std::string::npos; p = h.find("class='bar'", p + 1)) ++bars;
  EXPECT_EQ(bars, 3u);  // three separate bins, far enough apart on the log axis
  // 20 s of poses: RPE rows for 0.1 ... 20 s, none for 50 s and beyond.
  const size_t table = h.find("id='rpe-table'");
  const std::string rows = h.substr(table, h.find("</table>", table) - table);
  EXPECT_NE(rows.find("<tr><td>10</td>"), std::string::npos);
  EXPECT_EQ(rows.find("<tr><td>50</td>"), std::string::npos);
  // Without metrics there is no latency section.
  write_html_report(dir + "/plain.html", gt, r, HtmlReportOptions{});
  EXPECT_EQ(slurp(dir + "/plain.html").find("id='latency'"), std::string::npos);
  EXPECT_THROW(write_html_report(dir + "/no/such/r.html", gt, r, o), std::runtime_error);
}

TEST(EvalReport, ReplayMetricsAreReadWithTheirBinsAndBadOnesNamed) {
  const std::string dir = test::temp_dir("eval_metrics");
  auto write = [&](const std::string& name, const std::string& text) {
    std::ofstream(dir + "/" + name) << text;
    return dir + "/" + name;
  };
  const auto ok = read_replay_latencies(write(
      "ok.json",
      R"({"latency": {"tracking": {"count": 3, "p50_ms": 1.0, "p90_ms": 2.0, "p99_ms": 2.5, "max_ms": 3.0,
          "bins": [[1000000, 8192, 2], [2500000, 16384, 1]]},
          "optimizer": {"count": 0, "p50_ms": null, "p90_ms": null, "p99_ms": null, "max_ms": null, "bins": []}}})"));
  ASSERT_EQ(ok.size(), 1u);  // the empty one is left out
  EXPECT_EQ(ok[0].name, "tracking");
  ASSERT_EQ(ok[0].bins.size(), 2u);
  EXPECT_EQ(ok[0].bins[1].lower_ns, 2'500'000);
  EXPECT_EQ(ok[0].bins[1].count, 1u);
  struct Bad {
    const char* json;
    const char* names;
  };
  for (const Bad& b : std::vector<Bad>{
           {"not json", "not JSON"},
           {R"({"estimator": "window"})", "no \"latency\""},
           {R"({"latency": {"tracking": {"count": 2, "p50_ms": 1, "p90_ms": 1, "p99_ms": 1, "max_ms": 1}}})",
            "latency.tracking.bins"},
           {R"({"latency": {"tracking": {"count": 2, "p50_ms": 1, "p90_ms": 1, "p99_ms": 1, "max_ms": 1,
               "bins": [[1, 2]]}}})",
            "latency.tracking.bins[0]"},
           {R"({"latency": {"tracking": {"count": 2, "p50_ms": "fast", "p90_ms": 1, "p99_ms": 1, "max_ms": 1,
               "bins": []}}})",
            "latency.tracking.p50_ms"},
       }) {
    try {
      read_replay_latencies(write("bad.json", b.json));
      ADD_FAILURE() << "accepted: " << b.json;
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find("bad.json"), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find(b.names), std::string::npos) << e.what();
    }
  }
  EXPECT_THROW(read_replay_latencies(dir + "/absent.json"), std::runtime_error);
}

}  // namespace
}  // namespace kestrel::tools

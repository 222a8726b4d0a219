// Output contracts: text first line, text/JSON key parity, JSON escaping, SVG.
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
  EXPECT_NE(json.find("\"est_file\": \"dir\\\\with \\\"quotes\\\"\\nand\\ttab\\u0001.txt\""), std::string::npos)
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
  EXPECT_EQ(svg.find("href"), std::string::npos);   // nothing external
  EXPECT_EQ(svg.find("nan"), std::string::npos);
  size_t polylines = 0;
  for (size_t p = svg.find("<polyline"); p != std::string::npos; p = svg.find("<polyline", p + 1)) ++polylines;
  EXPECT_EQ(polylines, 3u);   // GT, estimate, error curve
  EXPECT_THROW(write_svg_plot(dir + "/no/such/plot.svg", gt, r), std::runtime_error);
}

}  // namespace
}  // namespace kestrel::tools

#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include "kestrel/tools/cpu_budget.hpp"
#include "run_command.hpp"

namespace fs = std::filesystem;
using kestrel::tools::callgrind_inclusive;

namespace {

std::string temp_file(const std::string& name, const std::string& text) {
  const fs::path p =
      fs::temp_directory_path() / ("kestrel_profile_" + std::to_string(::getpid()) + "_" + name);
  std::ofstream(p) << text;
  return p.string();
}

}  // namespace

// A hand-written file in callgrind's format: costs on call arcs are
// inclusive; arcs from several callers add up; a function calling itself is
// not counted twice; compressed names "(id) name" / "(id)" resolve.
TEST(CallgrindProfile, SumsInclusiveCostsOverCallArcs) {
  const std::string f = temp_file("a.out",
                                  "# callgrind format\nversion: 1\npositions: line\nevents: Ir\n"
                                  "fl=a.cpp\nfn=main\n1 10\ncfn=(1) ns::stage(int)\ncalls=3 20\n2 300\n"
                                  "cfn=other\ncalls=1 30\n3 7\n"
                                  "fn=helper\n5 1\ncfn=(1)\ncalls=2 20\n6 200\n"
                                  "fn=(1)\n20 100\ncfn=(1)\ncalls=4 20\n21 80\n"
                                  "totals: 1000\n");
  const auto c = callgrind_inclusive(f, {"ns::stage", "other", "missing"});
  EXPECT_EQ(c.at("ns::stage").calls, 5u);
  EXPECT_EQ(c.at("ns::stage").inclusive_ir, 500u);
  EXPECT_EQ(c.at("other").calls, 1u);
  EXPECT_EQ(c.at("other").inclusive_ir, 7u);
  EXPECT_EQ(c.at("missing").calls, 0u);
  fs::remove(f);
}

TEST(CallgrindProfile, PicksTheIrColumnAmongSeveralEvents) {
  const std::string f =
      temp_file("b.out", "# callgrind format\nevents: Dr Ir Dw\nfn=main\ncfn=g\ncalls=2 9\n4 11 222 33\n");
  EXPECT_EQ(callgrind_inclusive(f, {"g"}).at("g").inclusive_ir, 222u);
  fs::remove(f);
}

TEST(CallgrindProfile, RefusesWhatIsNotCallgrindOutputNamingTheFile) {
  const std::string f = temp_file("c.out", "timestamp,x,y\n1,2,3\n");
  try {
    callgrind_inclusive(f, {"x"});
    FAIL() << "accepted a CSV file";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(f + ":1"), std::string::npos) << e.what();
  }
  const std::string g = temp_file("d.out", "# callgrind format\nevents: Dr\n");
  EXPECT_THROW(callgrind_inclusive(g, {"x"}), std::runtime_error);
  EXPECT_THROW(callgrind_inclusive("/nonexistent/callgrind.out", {"x"}), std::runtime_error);
  fs::remove(f);
  fs::remove(g);
}

// valgrind's real output for a program whose call counts are known: what
// `kestrel bench --cpu-budget` relies on (valgrind comes from install-deps).
TEST(CallgrindProfile, ReadsRealCallgrindOutputOfTheProbe) {
  const std::string probe = std::string(KESTREL_BIN_DIR) + "/profile_probe";
  ASSERT_TRUE(fs::exists(probe)) << probe;
  if (kestrel::test::cross_emulated())
    GTEST_SKIP() << "SKIPPED LOUDLY: this build runs under an emulator (" << KESTREL_RUN_PREFIX
                 << "); the host's valgrind cannot run its binaries. The native suites run this test.";
  ASSERT_EQ(std::system("valgrind --version > /dev/null 2>&1"), 0)
      << "valgrind is not installed (tools/install-deps.sh installs it)";
  const fs::path out =
      fs::temp_directory_path() / ("kestrel_probe_" + std::to_string(::getpid()) + ".callgrind");
  const std::string cmd =
      "valgrind --tool=callgrind --compress-strings=no --compress-pos=no --dump-instr=no "
      "--callgrind-out-file=" +
      out.string() + " " + probe + " > /dev/null 2>&1";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  const auto c = callgrind_inclusive(out.string(), {"probe::leaf", "probe::work", "probe::recurse"});
  EXPECT_EQ(c.at("probe::work").calls, 10u);
  EXPECT_EQ(c.at("probe::leaf").calls, 1000u);
  EXPECT_EQ(c.at("probe::recurse").calls, 1u);  // the 5 recursive calls are inside the first
  // leaf: 100 multiply-adds and the loop, a few hundred instructions a call.
  const double per_leaf = double(c.at("probe::leaf").inclusive_ir) / 1000.0;
  EXPECT_GT(per_leaf, 200.0);
  EXPECT_LT(per_leaf, 2000.0);
  EXPECT_GT(c.at("probe::work").inclusive_ir, c.at("probe::leaf").inclusive_ir);
  fs::remove(out);
}

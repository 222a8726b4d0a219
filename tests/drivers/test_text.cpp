// The text layer (drivers/text): line reading, splitting and exact number
// parsing shared by the dataset readers, eval's trajectory files and the
// simulator's tables. Edge cases first: each is a way a real file went wrong.
#include <gtest/gtest.h>

#include <cerrno>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "kestrel/drivers/text.hpp"
#include "test_data.hpp"

namespace kestrel::drivers::text {
namespace {

using V = std::vector<std::string>;

TEST(Text, ReadLinesStripsCrlfAndKeepsEmptyLines) {
  const std::string dir = kestrel::test::temp_dir("text_lines");
  const std::string path = dir + "/t.csv";
  std::ofstream(path, std::ios::binary) << "a,b\r\n\r\nc\n  d \r\nlast";
  std::vector<std::string> lines{"stale"};
  const LinesRead r = read_lines(path, lines);
  ASSERT_TRUE(r);
  EXPECT_TRUE(r.opened);
  EXPECT_EQ(r.error, 0);
  EXPECT_EQ(lines, (V{"a,b", "", "c", "  d ", "last"}));  // a lone '\r' only goes at the end

  std::ofstream(path, std::ios::binary) << "";
  ASSERT_TRUE(read_lines(path, lines));
  EXPECT_TRUE(lines.empty());

  const LinesRead missing = read_lines(dir + "/none.csv", lines);
  EXPECT_FALSE(missing);
  EXPECT_FALSE(missing.opened);
  EXPECT_EQ(missing.error, ENOENT);
}

TEST(Text, ReadFileAndPathHelpers) {
  const std::string dir = kestrel::test::temp_dir("text_file");
  const std::string path = dir + "/bytes.bin";
  const std::string bytes("a\0b\r\nc", 6);
  std::ofstream(path, std::ios::binary) << bytes;
  EXPECT_EQ(read_file(path), bytes) << "every byte, NUL and CR included";
  try {
    read_file(dir + "/none.txt", " (a hint)");
    FAIL() << "a missing file must throw";
  } catch (const std::runtime_error& e) {
    EXPECT_EQ(std::string(e.what()), dir + "/none.txt: cannot open (a hint)");
  }
  EXPECT_EQ(strip_trailing_slashes("a/b//"), "a/b");
  EXPECT_EQ(strip_trailing_slashes("a/b"), "a/b");
  EXPECT_EQ(strip_trailing_slashes("/"), "/");
  EXPECT_EQ(strip_trailing_slashes("///"), "/");
  EXPECT_EQ(fmt6(0.000123456789), "0.000123457");
  EXPECT_EQ(fmt6(2.5), "2.5");
}

TEST(Text, Utf8IsCheckedByteForByte) {
  EXPECT_TRUE(is_utf8(""));
  EXPECT_TRUE(is_utf8("plain ascii\t\n"));
  EXPECT_TRUE(is_utf8(
      "\xc3\xa9 \xe2\x82\xac \xf0\x9f\x9a\x81 \xf4\x8f\xbf\xbf"));  // e-acute, euro, helicopter, U+10FFFF
  EXPECT_FALSE(is_utf8("\xca"));              // a lead byte alone (the fuzz_rig_yaml finding)
  EXPECT_FALSE(is_utf8("\xc3"));              // cut short
  EXPECT_FALSE(is_utf8("\x80"));              // a continuation byte first
  EXPECT_FALSE(is_utf8("\xc0\xaf"));          // overlong '/'
  EXPECT_FALSE(is_utf8("\xe0\x80\xaf"));      // overlong, three bytes
  EXPECT_FALSE(is_utf8("\xed\xa0\x80"));      // a surrogate
  EXPECT_FALSE(is_utf8("\xf4\x90\x80\x80"));  // past U+10FFFF
  EXPECT_FALSE(is_utf8("\xe2\x82"));          // cut short
  EXPECT_FALSE(is_utf8("\xe2\x28\xa1"));      // a bad continuation
}

TEST(Text, TrimAndSplit) {
  EXPECT_EQ(trim(" \t x y \r\n"), "x y");
  EXPECT_EQ(trim(" \t\r\n"), "");
  EXPECT_EQ(split("", ','), (V{""}));
  EXPECT_EQ(split("a, b ,c", ','), (V{"a", "b", "c"}));
  EXPECT_EQ(split("a,,b,", ','), (V{"a", "", "b", ""}));  // empty fields are fields
  EXPECT_EQ(split(" , ", ','), (V{"", ""}));
  EXPECT_EQ(split_ws(""), V{});
  EXPECT_EQ(split_ws("  1.0\t2  3\r"), (V{"1.0", "2", "3"}));
}

TEST(Text, Int64IsExactAndRefusesWhatIsNotOne) {
  int64_t v = 7;
  ASSERT_TRUE(parse_i64("1403715273262142976", v));
  EXPECT_EQ(v, 1403715273262142976);
  ASSERT_TRUE(parse_i64("+12", v));
  EXPECT_EQ(v, 12);
  ASSERT_TRUE(parse_i64("-9223372036854775808", v));
  EXPECT_EQ(v, std::numeric_limits<int64_t>::min());
  ASSERT_TRUE(parse_i64("9223372036854775807", v));
  EXPECT_EQ(v, std::numeric_limits<int64_t>::max());
  ASSERT_TRUE(parse_i64("00000000000000000000042", v));  // 23 digits, most of them zeros
  EXPECT_EQ(v, 42);
  v = 7;
  for (const char* bad : {"", "9223372036854775808", "-9223372036854775809", "12345678901234567890", "1e3",
                          "1.0", "12abc", "0x10", "12 ", "-", "nan"}) {
    EXPECT_FALSE(parse_i64(bad, v)) << bad;
    EXPECT_EQ(v, 7) << bad << ": a refused token leaves the output alone";
  }
}

TEST(Text, DoubleTakesWhatStrtodTakesFiniteOnlyWhatIsInRange) {
  double v = 0;
  ASSERT_TRUE(parse_f64("1e3", v));
  EXPECT_EQ(v, 1000.0);
  ASSERT_TRUE(parse_f64("-0.5", v));
  EXPECT_EQ(v, -0.5);
  ASSERT_TRUE(parse_f64("0.1", v));
  EXPECT_EQ(v, 0.1);  // strtod's correctly rounded value, bit for bit
  ASSERT_TRUE(parse_f64("nan", v));
  EXPECT_TRUE(std::isnan(v));
  ASSERT_TRUE(parse_f64("-inf", v));
  EXPECT_EQ(v, -std::numeric_limits<double>::infinity());
  ASSERT_TRUE(parse_f64("1e999", v));  // overflow saturates; the caller sees a non-finite value
  EXPECT_EQ(v, std::numeric_limits<double>::infinity());
  for (const char* bad : {"", "abc", "1.0x", "1,5", "1e", "--1", "1.0 "})
    EXPECT_FALSE(parse_f64(bad, v)) << bad;

  ASSERT_TRUE(parse_finite_f64("2.5e-3", v));
  EXPECT_EQ(v, 2.5e-3);
  ASSERT_TRUE(parse_finite_f64("+1", v));
  EXPECT_EQ(v, 1.0);
  v = 3;
  for (const char* bad :
       {"nan", "inf", "-Infinity", "1e999", "-1e999", "1e-400", "1e-310", "", "abc", "1.5.2"}) {
    EXPECT_FALSE(parse_finite_f64(bad, v)) << bad;
    EXPECT_EQ(v, 3.0) << bad;
  }
}

TEST(Text, SecondsToNanosecondsIsExact) {
  int64_t t = 0;
  ASSERT_TRUE(parse_seconds_ns("1305031102.175304", t));
  EXPECT_EQ(t, 1305031102175304000);  // a double would be ~100 ns off here
  ASSERT_TRUE(parse_seconds_ns("1403715273.262142976", t));
  EXPECT_EQ(t, 1403715273262142976);
  ASSERT_TRUE(parse_seconds_ns("-0.5", t));  // the sign survives a zero whole part
  EXPECT_EQ(t, -500000000);
  ASSERT_TRUE(parse_seconds_ns("+2", t));
  EXPECT_EQ(t, 2000000000);
  ASSERT_TRUE(parse_seconds_ns("5.", t));
  EXPECT_EQ(t, 5000000000);
  ASSERT_TRUE(parse_seconds_ns(".25", t));
  EXPECT_EQ(t, 250000000);
  ASSERT_TRUE(parse_seconds_ns("-0", t));
  EXPECT_EQ(t, 0);
  ASSERT_TRUE(parse_seconds_ns("0000000000000000000001.5", t));  // leading zeros do not overflow
  EXPECT_EQ(t, 1500000000);
  ASSERT_TRUE(parse_seconds_ns("9223372036.854775807", t));
  EXPECT_EQ(t, std::numeric_limits<int64_t>::max());
  ASSERT_TRUE(parse_seconds_ns("-9223372036.854775807", t));
  EXPECT_EQ(t, -std::numeric_limits<int64_t>::max());
  t = 11;
  for (const char* bad : {"", ".", "-", "+.", "1e3", "nan", "inf", " 1", "1 ", "1.2.3", "1,5", "0x1", "1.5s",
                          "9223372036.854775808", "9300000000", "99999999999999999999"}) {
    EXPECT_FALSE(parse_seconds_ns(bad, t)) << bad;
    EXPECT_EQ(t, 11) << bad;
  }
}

TEST(Text, SecondsBelowANanosecondTruncateRoundOrRefuse) {
  int64_t t = 0;
  const SecondsSyntax truncate{BelowNs::kTruncate, false}, round{BelowNs::kRound, false},
      reject{BelowNs::kReject, false};
  ASSERT_TRUE(parse_seconds_ns("1.0000000019", t, truncate));
  EXPECT_EQ(t, 1000000001);
  ASSERT_TRUE(parse_seconds_ns("1.0000000015", t, round));
  EXPECT_EQ(t, 1000000002);
  ASSERT_TRUE(parse_seconds_ns("1.00000000149999", t, round));  // only the first dropped digit counts
  EXPECT_EQ(t, 1000000001);
  ASSERT_TRUE(parse_seconds_ns("-1.0000000015", t, round));  // half away from zero
  EXPECT_EQ(t, -1000000002);
  ASSERT_TRUE(parse_seconds_ns("0.9999999999", t, round));  // the carry reaches the whole seconds
  EXPECT_EQ(t, 1000000000);
  ASSERT_TRUE(parse_seconds_ns("0.00000000049", t, round));
  EXPECT_EQ(t, 0);
  EXPECT_FALSE(parse_seconds_ns("9223372036.8547758075", t, round));  // the rounding overflows
  ASSERT_TRUE(parse_seconds_ns("9223372036.8547758075", t, truncate));
  EXPECT_EQ(t, std::numeric_limits<int64_t>::max());

  t = 5;
  EXPECT_FALSE(parse_seconds_ns("1.0000000001", t, reject));
  EXPECT_FALSE(parse_seconds_ns("1.00000000000000000001", t, reject));
  EXPECT_EQ(t, 5);
  ASSERT_TRUE(parse_seconds_ns("1.000000001000", t, reject));  // trailing zeros lose nothing
  EXPECT_EQ(t, 1000000001);
}

TEST(Text, SecondsWithAnExponentStayExact) {
  const SecondsSyntax e{BelowNs::kRound, true};
  int64_t t = 0;
  ASSERT_TRUE(parse_seconds_ns("1e3", t, e));
  EXPECT_EQ(t, 1000000000000);
  ASSERT_TRUE(parse_seconds_ns("1.5e9", t, e));
  EXPECT_EQ(t, 1500000000000000000);
  ASSERT_TRUE(parse_seconds_ns("1.305031102175304E9", t, e));  // exact where llround(s * 1e9) is not
  EXPECT_EQ(t, 1305031102175304000);
  ASSERT_TRUE(parse_seconds_ns("-25E-2", t, e));
  EXPECT_EQ(t, -250000000);
  ASSERT_TRUE(parse_seconds_ns("15e-10", t, e));  // 1.5 ns, rounded
  EXPECT_EQ(t, 2);
  ASSERT_TRUE(parse_seconds_ns("1e-12", t, e));
  EXPECT_EQ(t, 0);
  ASSERT_TRUE(parse_seconds_ns("0e999999999", t, e));  // zero whatever the exponent
  EXPECT_EQ(t, 0);
  ASSERT_TRUE(parse_seconds_ns("1e+1", t, e));
  EXPECT_EQ(t, 10000000000);
  for (const char* bad : {"1e", "1e+", "e3", "1e3.5", "1e10", "1e999999999", "1.5e3x"})
    EXPECT_FALSE(parse_seconds_ns(bad, t, e)) << bad;
}

TEST(Text, SecondsFromNanosecondsIsTheInverse) {
  EXPECT_EQ(seconds_from_ns(1305031102175304000), "1305031102.175304000");
  EXPECT_EQ(seconds_from_ns(-500000000), "-0.500000000");
  EXPECT_EQ(seconds_from_ns(0), "0.000000000");
  EXPECT_EQ(seconds_from_ns(std::numeric_limits<int64_t>::min()), "-9223372036.854775808");
  for (int64_t t :
       {int64_t{1}, int64_t{-1}, int64_t{1403715273262142976}, std::numeric_limits<int64_t>::max()}) {
    int64_t back = 0;
    ASSERT_TRUE(parse_seconds_ns(seconds_from_ns(t), back)) << t;
    EXPECT_EQ(back, t);
  }
  double d = 0;
  ASSERT_TRUE(parse_f64(fmt17(0.1 + 0.2), d));
  EXPECT_EQ(d, 0.1 + 0.2);
}

TEST(Text, PathHelpers) {
  const std::string dir = kestrel::test::temp_dir("text_paths");
  std::ofstream(dir + "/f.txt") << "x";
  EXPECT_TRUE(is_file(dir + "/f.txt"));
  EXPECT_FALSE(is_dir(dir + "/f.txt"));
  EXPECT_TRUE(is_dir(dir));
  EXPECT_FALSE(is_file(dir));
  EXPECT_FALSE(is_file(dir + "/none"));
  EXPECT_EQ(file_name("/a/b/c.csv"), "c.csv");
  EXPECT_EQ(file_name("c.csv"), "c.csv");
  EXPECT_EQ(file_name("/a/b/"), "");
}

}  // namespace
}  // namespace kestrel::drivers::text

// The shared text layer (drivers/text) every dataset and trajectory reader
// stands on: any line through split / split_ws / trim and every number and
// seconds parser. Invariants: an accepted seconds token prints back
// (seconds_from_ns) to a token that parses to the same nanoseconds; fields
// never hold the separator; trim is idempotent.
// Seeds: lines of the kinds the readers meet (EuRoC CSV, TUM, ETH3D stamps).
#include "fuzz_target.hpp"
#include "kestrel/drivers/text.hpp"

namespace tx = kestrel::drivers::text;

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string line(reinterpret_cast<const char*>(data), size);
  const std::string t = tx::trim(line);
  if (tx::trim(t) != t) std::abort();
  for (char sep : {',', ' '}) {
    for (const auto& f : tx::split(line, sep))
      if (f.find(sep) != std::string::npos) std::abort();
  }
  for (const auto& f : tx::split_ws(line)) {
    if (f.empty()) std::abort();
    int64_t i = 0;
    double d = 0;
    tx::parse_i64(f, i);
    tx::parse_f64(f, d);
    tx::parse_finite_f64(f, d);
    for (auto below : {tx::BelowNs::kTruncate, tx::BelowNs::kRound, tx::BelowNs::kReject})
      for (bool exponent : {false, true}) {
        int64_t ns = 0;
        if (!tx::parse_seconds_ns(f, ns, {below, exponent})) continue;
        int64_t again = 0;
        if (!tx::parse_seconds_ns(tx::seconds_from_ns(ns), again) || again != ns) std::abort();
      }
  }
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  write_file(dir + "/euroc_imu.csv",
             "1403636579758555392,-0.099134701513277898,0.14730578886832138,"
             "0.02722713633111154,8.1476917083333333,-0.37592158333333331,-2.4026292499999999");
  write_file(dir + "/tum.txt", "1305031102.175304 1.3405 0.6266 1.6575 0.6574 0.6126 -0.2949 -0.3248");
  write_file(dir + "/stamps.txt", "  -12.5e3\t+0.000000001 1e-9 9223372036.854775807  nan inf 0x10 ");
  return 3;
}

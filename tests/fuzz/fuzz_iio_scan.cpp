// Linux IIO buffered capture (drivers/iio iio_scan, iio_device): the
// scan_elements type strings, the sysfs rate list, and the byte stream of scan
// records through RecordFramer and decode_record.
//
// Input: text lines up to the first empty line, then the record bytes. A line
// "rates:TEXT" goes to parse_available_rates, "num:TEXT" to parse_number; any
// other line is one scan element's type, given the next channel kind (accel
// x y z, anglvel x y z, timestamp, then others) and its line number as index.
// Invariants: an accepted type re-formats to a string that parses to the same
// type; a layout keeps every element aligned to its size inside the record;
// the framer never stalls, hands out no more records than the bytes hold, and
// its stamps rise except where it says the clock restarted; raw values stay
// within their type's range.
// Seeds: the layouts the driver tests use, with clean, torn and gapped streams.
#include <cmath>
#include <cstdio>
#include <cstring>
#include <string>
#include <string_view>

#include "fuzz_target.hpp"
#include "kestrel/drivers/iio_device.hpp"
#include "kestrel/drivers/iio_scan.hpp"

namespace iio = kestrel::drivers::iio;

namespace {

void check_type(const iio::ScanType& t) {
  if (t.real_bits < 1 || t.real_bits > t.storage_bits || t.shift + t.real_bits > t.storage_bits) std::abort();
  const uint32_t b = t.bytes();
  if (b == 0 || (b & (b - 1)) != 0) std::abort();
  char s[64];
  if (t.repeat > 1)
    std::snprintf(s, sizeof s, "%s:%c%u/%uX%u>>%u", t.big_endian ? "be" : "le", t.is_signed ? 's' : 'u',
                  t.real_bits, t.storage_bits, t.repeat, t.shift);
  else
    std::snprintf(s, sizeof s, "%s:%c%u/%u>>%u", t.big_endian ? "be" : "le", t.is_signed ? 's' : 'u',
                  t.real_bits, t.storage_bits, t.shift);
  iio::ScanType u;
  if (iio::parse_scan_type(s, u) != nullptr) std::abort();
  if (u.big_endian != t.big_endian || u.is_signed != t.is_signed || u.real_bits != t.real_bits ||
      u.storage_bits != t.storage_bits || u.shift != t.shift || u.repeat != t.repeat)
    std::abort();
}

void check_layout(const iio::ScanLayout& l) {
  size_t largest = 1;
  for (size_t i = 0; i < l.count; ++i) {
    const iio::ScanElement& e = l.el[i];
    const size_t len = e.type.bytes();
    if (e.offset_bytes % len != 0 || e.offset_bytes + len > l.record_bytes) std::abort();
    if (i > 0 && (e.index <= l.el[i - 1].index ||
                  e.offset_bytes < l.el[i - 1].offset_bytes + l.el[i - 1].type.bytes()))
      std::abort();
    largest = std::max(largest, len);
  }
  if (l.count > 0 && l.record_bytes % largest != 0) std::abort();
  if (l.record_bytes > iio::kMaxRecordBytes) std::abort();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view all(reinterpret_cast<const char*>(data), size);
  const size_t blank = all.find("\n\n");
  const std::string_view text = all.substr(0, blank);
  const std::string_view bytes = blank == std::string_view::npos ? std::string_view() : all.substr(blank + 2);

  iio::ScanLayout l;
  int line_no = 0, kind = static_cast<int>(iio::ChannelKind::kAccelX);
  size_t at = 0;
  while (at <= text.size() && !text.empty()) {
    size_t end = text.find('\n', at);
    if (end == std::string_view::npos) end = text.size();
    const std::string_view line = text.substr(at, end - at);
    at = end + 1;
    ++line_no;
    if (line.substr(0, 6) == "rates:") {
      iio::AvailableRates a;
      if (iio::parse_available_rates(line.substr(6), a) == nullptr) {
        const double r = iio::choose_rate(a, 100.0);
        if (!(r > 0) || !std::isfinite(r)) std::abort();
      }
      continue;
    }
    if (line.substr(0, 4) == "num:") {
      double v = 0;
      if (iio::parse_number(line.substr(4), v) && !std::isfinite(v)) std::abort();
      continue;
    }
    iio::ScanElement e;
    if (iio::parse_scan_type(line, e.type) != nullptr) continue;
    check_type(e.type);
    if (l.count >= iio::kMaxScanElements) continue;
    e.index = line_no;
    e.kind = static_cast<iio::ChannelKind>(kind <= static_cast<int>(iio::ChannelKind::kTimestamp) ? kind : 0);
    ++kind;
    e.scale = 0.001;
    l.el[l.count++] = e;
  }
  if (iio::compute_layout(l) != nullptr) return 0;
  check_layout(l);
  if (l.timestamp < 0 || l.record_bytes == 0) return 0;

  iio::RecordFramer f;
  iio::FramerOptions o;
  o.nominal_period_ns = 5'000'000;
  o.max_gap_ns = 1'000'000'000;
  f.configure(&l, o);
  const auto* p = reinterpret_cast<const uint8_t*>(bytes.data());
  size_t pos = 0, piece = 1, handed = 0;
  bool have = false;
  int64_t last = 0;
  iio::DecodedRecord d;
  while (pos < bytes.size()) {
    const size_t n = std::min(piece, bytes.size() - pos);
    const size_t took = f.feed(p + pos, n);
    if (took == 0) std::abort();  // full although drained: the framer stalled
    pos += took;
    iio::RecordFramer::Record r;
    while (f.next(r)) {
      ++handed;
      if (have && r.t_dev_ns <= last && (r.flags & iio::kRecordClockReset) == 0) std::abort();
      have = true;
      last = r.t_dev_ns;
      iio::decode_record(r.bytes, l, d);
      if (d.t_dev_ns != r.t_dev_ns || d.non_finite) std::abort();
      for (size_t i = 0; i < l.count; ++i) {
        const int64_t v = iio::extract_raw(r.bytes, l.el[i]);
        if (v > iio::raw_max(l.el[i].type) || v < iio::raw_min(l.el[i].type)) std::abort();
      }
    }
    piece = piece >= 4096 ? 1 : piece * 3;
  }
  if (handed > bytes.size() / l.record_bytes) std::abort();  // records from nowhere
  return 0;
}

namespace {

void put_le(std::string& out, uint64_t v, size_t n) {
  for (size_t i = 0; i < n; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xFF));
}

}  // namespace

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  // Combined s16 accel + gyro + stamp (24-byte records), 200 Hz.
  std::string combined =
      "le:s16/16>>0\nle:s16/16>>0\nle:s16/16>>0\nle:s16/16>>0\nle:s16/16>>0\nle:s16/16>>0\n"
      "le:s64/64>>0\nrates:25 50 100 200 400\nnum:0.004788403\n\n";
  std::string torn = combined;
  for (int i = 0; i < 40; ++i) {
    std::string r;
    for (int a = 0; a < 6; ++a) put_le(r, static_cast<uint64_t>(static_cast<int16_t>(100 * a - 7 * i)), 2);
    put_le(r, 0, 4);
    put_le(r, 1'000'000'000ull + 5'000'000ull * static_cast<uint64_t>(i), 8);
    combined += r;
    torn += i == 20 ? r.substr(0, 11) : i == 30 ? std::string() : r;  // a torn record, then a gap
  }
  write_file(dir + "/combined.bin", combined);
  write_file(dir + "/torn_and_gap.bin", torn);
  // D4xx HID style: s32 accel x y z + stamp (24 bytes), 100 Hz, big-endian 12-bit variant too.
  std::string hid = "le:s32/32>>0\nle:s32/32>>0\nle:s32/32>>0\nle:s64/64>>0\nrates:[12.5 12.5 800]\n\n";
  std::string be12 = "be:s12/16>>4\nbe:s12/16>>4\nbe:s12/16>>4\nle:s64/64>>0\n\n";
  for (int i = 0; i < 30; ++i) {
    for (int a = 0; a < 3; ++a)
      put_le(hid, static_cast<uint64_t>(static_cast<int32_t>(9800 * (a == 2) - i)), 4);
    put_le(hid, 0, 4);
    put_le(hid, 5'000'000'000ull + 10'000'000ull * static_cast<uint64_t>(i), 8);
    for (int a = 0; a < 3; ++a) {
      const uint16_t v = static_cast<uint16_t>((static_cast<uint16_t>(-3 * i + a) & 0x0FFF) << 4);
      be12.push_back(static_cast<char>(v >> 8));
      be12.push_back(static_cast<char>(v & 0xFF));
    }
    put_le(be12, 0, 2);
    put_le(be12, 7'000'000'000ull + 5'000'000ull * static_cast<uint64_t>(i), 8);
  }
  write_file(dir + "/hid_s32.bin", hid);
  write_file(dir + "/be12.bin", be12);
  return 4;
}

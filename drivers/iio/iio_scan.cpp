#include "kestrel/drivers/iio_scan.hpp"

#include <cmath>
#include <cstring>

namespace kestrel::drivers::iio {
namespace {

// Reads a decimal number of at most 3 digits at s[i]; false when none.
bool read_small(std::string_view s, size_t& i, unsigned& v) {
  size_t digits = 0;
  v = 0;
  while (i < s.size() && s[i] >= '0' && s[i] <= '9') {
    if (++digits > 3) return false;
    v = v * 10 + static_cast<unsigned>(s[i] - '0');
    ++i;
  }
  return digits > 0;
}

bool is_pow2(size_t v) { return v != 0 && (v & (v - 1)) == 0; }
size_t align_up(size_t v, size_t a) { return (v + a - 1) / a * a; }

}  // namespace

const char* parse_scan_type(std::string_view s, ScanType& out) {
  while (!s.empty() && (s.back() == '\n' || s.back() == ' ' || s.back() == '\r' || s.back() == '\t'))
    s.remove_suffix(1);
  if (s.size() < 3 || s[2] != ':') return "expected \"le:\" or \"be:\" first";
  ScanType t;
  if (s.substr(0, 2) == "le") {
    t.big_endian = false;
  } else if (s.substr(0, 2) == "be") {
    t.big_endian = true;
  } else {
    return "endianness must be le or be";
  }
  size_t i = 3;
  if (i >= s.size() || (s[i] != 's' && s[i] != 'u')) return "sign must be s or u";
  t.is_signed = s[i++] == 's';
  unsigned real = 0, storage = 0, repeat = 1, shift = 0;
  if (!read_small(s, i, real)) return "missing real bits";
  if (i >= s.size() || s[i++] != '/') return "expected '/' after the real bits";
  if (!read_small(s, i, storage)) return "missing storage bits";
  if (i < s.size() && s[i] == 'X') {
    ++i;
    if (!read_small(s, i, repeat)) return "missing repeat count after X";
  }
  if (i + 1 >= s.size() || s[i] != '>' || s[i + 1] != '>') return "expected \">>shift\"";
  i += 2;
  if (!read_small(s, i, shift)) return "missing shift";
  if (i != s.size()) return "unexpected characters after the shift";
  if (storage != 8 && storage != 16 && storage != 32 && storage != 64)
    return "storage bits must be 8, 16, 32 or 64";
  if (real < 1 || real > storage) return "real bits must be in 1..storage bits";
  if (shift + real > storage) return "shift + real bits exceed the storage bits";
  if (repeat < 1 || repeat > 16) return "repeat must be in 1..16";
  if (!is_pow2(static_cast<size_t>(storage / 8) * repeat))
    return "storage bytes x repeat is not a power of two (no defined alignment)";
  t.real_bits = static_cast<uint8_t>(real);
  t.storage_bits = static_cast<uint8_t>(storage);
  t.shift = static_cast<uint8_t>(shift);
  t.repeat = static_cast<uint8_t>(repeat);
  out = t;
  return nullptr;
}

ChannelKind channel_kind(std::string_view n) {
  if (n == "in_accel_x") return ChannelKind::kAccelX;
  if (n == "in_accel_y") return ChannelKind::kAccelY;
  if (n == "in_accel_z") return ChannelKind::kAccelZ;
  if (n == "in_anglvel_x") return ChannelKind::kAnglvelX;
  if (n == "in_anglvel_y") return ChannelKind::kAnglvelY;
  if (n == "in_anglvel_z") return ChannelKind::kAnglvelZ;
  if (n == "in_timestamp") return ChannelKind::kTimestamp;
  return ChannelKind::kOther;
}

const char* channel_name(ChannelKind k) {
  switch (k) {
    case ChannelKind::kAccelX:
      return "in_accel_x";
    case ChannelKind::kAccelY:
      return "in_accel_y";
    case ChannelKind::kAccelZ:
      return "in_accel_z";
    case ChannelKind::kAnglvelX:
      return "in_anglvel_x";
    case ChannelKind::kAnglvelY:
      return "in_anglvel_y";
    case ChannelKind::kAnglvelZ:
      return "in_anglvel_z";
    case ChannelKind::kTimestamp:
      return "in_timestamp";
    case ChannelKind::kOther:
      break;
  }
  return "other";
}

const char* compute_layout(ScanLayout& l) {
  if (l.count > kMaxScanElements) return "too many scan elements";
  // Insertion sort by index: a handful of elements.
  for (size_t i = 1; i < l.count; ++i) {
    const ScanElement e = l.el[i];
    size_t j = i;
    while (j > 0 && l.el[j - 1].index > e.index) {
      l.el[j] = l.el[j - 1];
      --j;
    }
    l.el[j] = e;
  }
  l.timestamp = -1;
  l.accel = {-1, -1, -1};
  l.gyro = {-1, -1, -1};
  size_t bytes = 0, largest = 0;
  for (size_t i = 0; i < l.count; ++i) {
    ScanElement& e = l.el[i];
    if (i > 0 && l.el[i - 1].index == e.index) return "two scan elements share one index";
    const size_t len = e.type.bytes();
    if (len == 0 || !is_pow2(len)) return "a scan element has no valid size";
    bytes = align_up(bytes, len);
    e.offset_bytes = static_cast<uint32_t>(bytes);
    bytes += len;
    if (len > largest) largest = len;
    if (bytes > kMaxRecordBytes) return "scan record longer than the parser's maximum";
    int* slot = nullptr;
    switch (e.kind) {
      case ChannelKind::kAccelX:
        slot = &l.accel[0];
        break;
      case ChannelKind::kAccelY:
        slot = &l.accel[1];
        break;
      case ChannelKind::kAccelZ:
        slot = &l.accel[2];
        break;
      case ChannelKind::kAnglvelX:
        slot = &l.gyro[0];
        break;
      case ChannelKind::kAnglvelY:
        slot = &l.gyro[1];
        break;
      case ChannelKind::kAnglvelZ:
        slot = &l.gyro[2];
        break;
      case ChannelKind::kTimestamp:
        slot = &l.timestamp;
        break;
      case ChannelKind::kOther:
        break;
    }
    if (slot == nullptr) continue;
    if (*slot >= 0) return "a channel appears twice in the scan";
    if (e.type.repeat != 1) return "a motion or timestamp channel with a repeat count";
    if (e.kind == ChannelKind::kTimestamp && e.type.storage_bits != 64)
      return "the timestamp is not stored in 64 bits";
    *slot = static_cast<int>(i);
  }
  l.record_bytes = largest == 0 ? 0 : align_up(bytes, largest);
  if (l.record_bytes > kMaxRecordBytes) return "scan record longer than the parser's maximum";
  return nullptr;
}

int64_t extract_raw(const uint8_t* record, const ScanElement& e, unsigned k) {
  const ScanType& t = e.type;
  const unsigned nb = t.storage_bits / 8u;
  const uint8_t* p = record + e.offset_bytes + static_cast<size_t>(k) * nb;
  uint64_t v = 0;
  if (t.big_endian) {
    for (unsigned i = 0; i < nb; ++i) v = (v << 8) | p[i];
  } else {
    for (unsigned i = nb; i-- > 0;) v = (v << 8) | p[i];
  }
  v >>= t.shift;
  if (t.real_bits < 64) {
    const uint64_t mask = (uint64_t{1} << t.real_bits) - 1;
    v &= mask;
    if (t.is_signed && ((v >> (t.real_bits - 1)) & 1u)) v |= ~mask;
  }
  // An unsigned 64-bit value beyond int64 cannot be held: it saturates at
  // raw_max (decode_record flags it), rather than wrap to a negative count.
  if (!t.is_signed && v > static_cast<uint64_t>(INT64_MAX)) return INT64_MAX;
  return static_cast<int64_t>(v);
}

int64_t raw_max(const ScanType& t) {
  if (t.is_signed) return t.real_bits >= 64 ? INT64_MAX : (int64_t{1} << (t.real_bits - 1)) - 1;
  return t.real_bits >= 63 ? INT64_MAX : (int64_t{1} << t.real_bits) - 1;
}

int64_t raw_min(const ScanType& t) {
  if (!t.is_signed) return 0;
  if (t.real_bits >= 64) return INT64_MIN;
  return -(int64_t{1} << (t.real_bits - 1));
}

void decode_record(const uint8_t* record, const ScanLayout& l, DecodedRecord& out) {
  out.non_finite = false;
  out.t_dev_ns = l.timestamp >= 0 ? extract_raw(record, l.el[static_cast<size_t>(l.timestamp)]) : 0;
  auto axes = [&](const std::array<int, 3>& idx, Vec3d& v, bool& sat) {
    sat = false;
    if (idx[0] < 0 || idx[1] < 0 || idx[2] < 0) return;
    for (int i = 0; i < 3; ++i) {
      const ScanElement& e = l.el[static_cast<size_t>(idx[static_cast<size_t>(i)])];
      const int64_t raw = extract_raw(record, e);
      if (raw >= raw_max(e.type) || raw <= raw_min(e.type)) sat = true;
      v[static_cast<size_t>(i)] = (static_cast<double>(raw) + e.offset) * e.scale;
      if (!std::isfinite(v[static_cast<size_t>(i)])) out.non_finite = true;
    }
  };
  axes(l.accel, out.acc_mps2, out.acc_saturated);
  axes(l.gyro, out.gyro_rps, out.gyro_saturated);
}

// ---- RecordFramer ------------------------------------------------------------------

void RecordFramer::configure(const ScanLayout* layout, const FramerOptions& o) {
  l_ = layout;
  o_ = o;
  if (o_.confirm_records < 2) o_.confirm_records = 2;
  if (o_.max_gap_ns <= 0) o_.max_gap_ns = 1'000'000'000;
  reset();
}

void RecordFramer::reset() {
  start_ = end_ = 0;
  synced_ = false;
  have_last_ = false;
  resync_pending_ = false;
  consecutive_ooo_ = 0;
  period_ns_ = o_.nominal_period_ns;
}

void RecordFramer::compact() {
  if (start_ == 0) return;
  if (end_ > start_) std::memmove(buf_.data(), buf_.data() + start_, end_ - start_);
  end_ -= start_;
  start_ = 0;
}

uint8_t* RecordFramer::write_ptr() {
  compact();
  return buf_.data() + end_;
}

size_t RecordFramer::write_space() {
  compact();
  return buf_.size() - end_;
}

void RecordFramer::commit(size_t n) {
  const size_t space = buf_.size() - end_;
  if (n > space) {
    c_.overflow_bytes += n - space;
    n = space;
  }
  end_ += n;
}

size_t RecordFramer::feed(const uint8_t* data, size_t n) {
  const size_t space = write_space();
  const size_t take = n < space ? n : space;
  if (take > 0) std::memcpy(buf_.data() + end_, data, take);
  end_ += take;
  c_.overflow_bytes += n - take;
  return take;
}

int64_t RecordFramer::stamp_at(size_t pos) const {
  return extract_raw(buf_.data() + pos, l_->el[static_cast<size_t>(l_->timestamp)]);
}

bool RecordFramer::window_consistent(size_t pos, int n, bool strict) const {
  const size_t r = l_->record_bytes;
  if (pos + static_cast<size_t>(n) * r > end_) return false;
  // About one period apart (up to a few lost samples); unknown period: the gap limit.
  const int64_t bound = period_ns_ > 0 ? 4 * period_ns_ : o_.max_gap_ns;
  // Off the kernel's framing, sensor bytes read as a stamp can rise slowly
  // and steadily (a ramp in one axis): there the steps must also be near a
  // period. Not at offset 0, where a device that stamps in bursts must pass.
  const int64_t floor = strict && period_ns_ > 0 ? period_ns_ / 4 : 0;
  int64_t prev = stamp_at(pos);
  for (int i = 1; i < n; ++i) {
    const int64_t t = stamp_at(pos + static_cast<size_t>(i) * r);
    // Differences of arbitrary 64-bit values: compare without overflow.
    if (t <= prev) return false;
    const uint64_t d = static_cast<uint64_t>(t) - static_cast<uint64_t>(prev);
    if (d > static_cast<uint64_t>(bound) || d < static_cast<uint64_t>(floor)) return false;
    prev = t;
  }
  return true;
}

bool RecordFramer::follows_last(int64_t t) const {
  if (!have_last_) return true;
  return t > last_t_ &&
         static_cast<uint64_t>(t) - static_cast<uint64_t>(last_t_) <= static_cast<uint64_t>(o_.max_gap_ns);
}

uint32_t RecordFramer::lost_for_gap(int64_t dt) const {
  if (period_ns_ <= 0 || 2 * dt <= 3 * period_ns_) return 0;
  const double n = std::round(static_cast<double>(dt) / static_cast<double>(period_ns_)) - 1.0;
  if (n < 1.0) return 0;
  return n > 4e9 ? 4'000'000'000u : static_cast<uint32_t>(n);
}

void RecordFramer::accept(size_t pos, int64_t t, uint32_t flags, uint32_t lost, Record& out) {
  if (have_last_ && lost == 0 && (flags & kRecordClockReset) == 0 && period_ns_ > 0) {
    // Follow the device's real rate (nominal rates are often rounded), only
    // from steps that look like one period.
    const int64_t dt = t - last_t_;
    if (2 * dt > period_ns_ && 2 * dt < 3 * period_ns_) period_ns_ += (dt - period_ns_) / 16;
  }
  out.bytes = buf_.data() + pos;
  out.t_dev_ns = t;
  out.flags = flags;
  out.lost_before = lost;
  if (lost > 0) {
    ++c_.gaps;
    c_.samples_lost += lost;
  }
  if (flags & kRecordClockReset) ++c_.clock_resets;
  last_t_ = t;
  have_last_ = true;
  start_ = pos + l_->record_bytes;
  ++c_.records;
}

bool RecordFramer::next(Record& out) {
  if (l_ == nullptr || l_->timestamp < 0 || l_->record_bytes == 0) return false;
  const size_t r = l_->record_bytes;
  for (;;) {
    const size_t avail = end_ - start_;
    if (synced_) {
      if (avail < r) return false;
      const int64_t t = stamp_at(start_);
      // Unsigned difference: stamps are arbitrary 64-bit values here.
      const auto du = static_cast<uint64_t>(t) - static_cast<uint64_t>(last_t_);
      const bool forward = t > last_t_;
      if (forward && du <= static_cast<uint64_t>(o_.max_gap_ns)) {
        const int64_t dt = static_cast<int64_t>(du);
        const uint32_t lost = lost_for_gap(dt);
        consecutive_ooo_ = 0;
        accept(start_, t, lost > 0 ? kRecordGapBefore : 0u, lost, out);
        return true;
      }
      const auto back = static_cast<uint64_t>(last_t_) - static_cast<uint64_t>(t);
      if (!forward && back <= static_cast<uint64_t>(o_.max_gap_ns) && consecutive_ooo_ < o_.confirm_records) {
        // A stamp at or behind the previous one: a duplicate or a reordered
        // record. Dropped; a run of them is a clock that restarted (below).
        ++c_.out_of_order;
        ++consecutive_ooo_;
        start_ += r;
        continue;
      }
      synced_ = false;
      consecutive_ooo_ = 0;
    }
    // Alignment search: the first byte offset where confirm_records records
    // in a row have stamps about one period apart.
    const size_t need = static_cast<size_t>(o_.confirm_records) * r + (r - 1);
    if (avail < need) return false;
    // First an alignment that continues from the previous stamp; failing
    // that, any (a clock that restarted, a stall longer than the gap limit).
    size_t off = 0;
    bool found = false;
    for (int pass = 0; pass < 2 && !found; ++pass) {
      for (off = 0; off < r; ++off) {
        if (window_consistent(start_ + off, o_.confirm_records, off != 0) &&
            (pass == 1 || follows_last(stamp_at(start_ + off)))) {
          found = true;
          break;
        }
      }
    }
    if (!found) {
      ++c_.discarded_records;
      c_.bytes_skipped += r;
      start_ += r;
      continue;
    }
    const bool first = !have_last_ && off == 0;
    if (!first) ++c_.resyncs;
    if (off > 0) ++c_.torn_records;
    c_.bytes_skipped += off;
    start_ += off;
    synced_ = true;
    if (period_ns_ <= 0) period_ns_ = stamp_at(start_ + r) - stamp_at(start_);
    const int64_t t = stamp_at(start_);
    uint32_t flags = first ? 0u : static_cast<uint32_t>(kRecordResynced);
    uint32_t lost = 0;
    if (have_last_) {
      if (t > last_t_) {
        const auto du = static_cast<uint64_t>(t) - static_cast<uint64_t>(last_t_);
        lost = lost_for_gap(du > static_cast<uint64_t>(INT64_MAX) ? INT64_MAX : static_cast<int64_t>(du));
        if (lost > 0) flags |= kRecordGapBefore;
      } else {
        flags |= kRecordClockReset;
      }
    }
    accept(start_, t, flags, lost, out);
    return true;
  }
}

}  // namespace kestrel::drivers::iio

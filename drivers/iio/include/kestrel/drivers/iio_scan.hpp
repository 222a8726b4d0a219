// Linux IIO buffered capture: the parser (pure functions over bytes, no I/O).
//
// A buffered IIO device hands out fixed-size scan records through its
// character device. Which channels a record holds, in which order, and how
// each is stored is described in sysfs (scan_elements/in_<chan>_{en,index,type}):
//   type  "le:s16/16>>0"  endianness : sign real-bits / storage-bits [X repeat] >> shift
//   index the element's position: records hold the enabled elements by rising index
// Layout rule (the kernel's iio_compute_scan_bytes): each element starts at a
// multiple of its own size (storage bytes x repeat), the record is padded to a
// multiple of its largest element; so the 64-bit timestamp sits 8-aligned.
// Values are SI after `(raw + offset) * scale` (accel m/s^2, anglvel rad/s,
// timestamp ns on the device's current_timestamp_clock).
//
// RecordFramer turns the byte stream into records. The kernel only returns
// whole records, but a pipe, a driver bug or a short read can tear one; the
// stream has no framing bytes, so the framer keeps alignment with the one
// thing it can check, the timestamps: a record whose stamp does not follow the
// previous one is suspect, and alignment is searched among the record's byte
// offsets for a run of records whose stamps advance by about one sample period.
// Fixed buffer, no allocation.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "kestrel/msgs.hpp"

namespace kestrel::drivers::iio {

struct ScanType {
  bool big_endian = false;
  bool is_signed = true;
  uint8_t real_bits = 0;
  uint8_t storage_bits = 0;
  uint8_t shift = 0;
  uint8_t repeat = 1;
  uint32_t bytes() const { return static_cast<uint32_t>(storage_bits / 8) * repeat; }
};

// Parses a scan_elements in_*_type string (a trailing newline is allowed).
// Returns nullptr, or a static message saying what is wrong.
const char* parse_scan_type(std::string_view text, ScanType& out);

enum class ChannelKind : uint8_t {
  kOther,
  kAccelX,
  kAccelY,
  kAccelZ,
  kAnglvelX,
  kAnglvelY,
  kAnglvelZ,
  kTimestamp,
};
// "in_accel_x" -> kAccelX, "in_anglvel_z" -> kAnglvelZ, "in_timestamp" -> kTimestamp.
ChannelKind channel_kind(std::string_view element_name);
const char* channel_name(ChannelKind k);  // "in_accel_x", ... ("other")

struct ScanElement {
  ChannelKind kind = ChannelKind::kOther;
  int index = 0;  // scan_elements/<name>_index
  ScanType type;
  uint32_t offset_bytes = 0;  // in the record (compute_layout)
  double scale = 1.0;         // SI per count (timestamp: 1)
  double offset = 0.0;        // counts added before scaling
};

constexpr size_t kMaxScanElements = 32;
constexpr size_t kMaxRecordBytes = 512;

struct ScanLayout {
  std::array<ScanElement, kMaxScanElements> el{};
  size_t count = 0;
  size_t record_bytes = 0;
  int timestamp = -1;                    // element of in_timestamp
  std::array<int, 3> accel{-1, -1, -1};  // elements of x, y, z (-1: absent)
  std::array<int, 3> gyro{-1, -1, -1};
  bool has_accel() const { return accel[0] >= 0 && accel[1] >= 0 && accel[2] >= 0; }
  bool has_gyro() const { return gyro[0] >= 0 && gyro[1] >= 0 && gyro[2] >= 0; }
};

// Sorts the enabled elements by index, places them (offsets, record size) and
// finds the accel / anglvel / timestamp elements. Returns nullptr or a static
// message (duplicate index, record too long, timestamp not 64-bit, ...).
const char* compute_layout(ScanLayout& l);

// Element e's k-th value in a record (k < repeat): storage bytes in the
// element's endianness, shifted, masked to real bits, sign-extended.
int64_t extract_raw(const uint8_t* record, const ScanElement& e, unsigned k = 0);
// The largest and smallest raw values the element can hold (saturation).
int64_t raw_max(const ScanType& t);
int64_t raw_min(const ScanType& t);

struct DecodedRecord {
  int64_t t_dev_ns = 0;  // the timestamp element, device clock
  Vec3d acc_mps2{};      // sensor axes; valid when the layout has accel
  Vec3d gyro_rps{};
  bool acc_saturated = false;
  bool gyro_saturated = false;
  bool non_finite = false;  // a value that is not finite after scaling
};
void decode_record(const uint8_t* record, const ScanLayout& l, DecodedRecord& out);

// ---- the byte stream -> records ------------------------------------------------

enum RecordFlag : uint32_t {
  kRecordGapBefore = 1u << 0,   // stamps skipped samples (kernel buffer overflow, a stall)
  kRecordClockReset = 1u << 1,  // the stamps restarted behind the previous record (clock changed)
  kRecordResynced = 1u << 2,    // first record after alignment was searched
};

struct FramerOptions {
  int64_t nominal_period_ns = 0;       // 1 / sampling_frequency (0: unknown)
  int64_t max_gap_ns = 1'000'000'000;  // a longer jump between stamps is confirmed before it is believed
  int confirm_records = 4;             // records whose stamps must agree to (re)gain alignment
};

struct FramerCounters {
  uint64_t records = 0;            // handed out
  uint64_t resyncs = 0;            // alignment searched and found
  uint64_t torn_records = 0;       // found at a non-zero byte offset: bytes went missing before
  uint64_t bytes_skipped = 0;      // skipped to regain alignment
  uint64_t discarded_records = 0;  // a record's worth dropped because no alignment fitted
  uint64_t out_of_order = 0;       // a stamp not after the previous one, dropped
  uint64_t gaps = 0;               // stamp gaps (kRecordGapBefore)
  uint64_t samples_lost = 0;       // estimated from the gaps
  uint64_t clock_resets = 0;       // kRecordClockReset
  uint64_t overflow_bytes = 0;     // offered while the buffer was full
};

class RecordFramer {
 public:
  static constexpr size_t kBufferBytes = 16384;

  struct Record {
    const uint8_t* bytes = nullptr;  // record_bytes long; valid until the buffer is next written
    int64_t t_dev_ns = 0;
    uint32_t flags = 0;        // RecordFlag
    uint32_t lost_before = 0;  // estimated samples missing before this one
  };

  RecordFramer() = default;
  // The layout must stay alive (and unchanged) while the framer is used.
  void configure(const ScanLayout* layout, const FramerOptions& o);
  void reset();  // forget buffered bytes and the previous stamp (reopen)

  // Zero-copy read: fill write_ptr() with up to write_space() bytes, then commit.
  uint8_t* write_ptr();
  size_t write_space();
  void commit(size_t n);
  // Copying variant (tests, fuzz): returns bytes taken.
  size_t feed(const uint8_t* data, size_t n);

  // The next record whose alignment and stamp are believed; false: more bytes needed.
  bool next(Record& out);

  const FramerCounters& counters() const { return c_; }
  size_t buffered() const { return end_ - start_; }
  int64_t period_estimate_ns() const { return period_ns_; }
  bool synced() const { return synced_; }

 private:
  int64_t stamp_at(size_t pos) const;
  bool window_consistent(size_t pos, int n, bool strict) const;
  bool follows_last(int64_t t) const;
  void accept(size_t pos, int64_t t, uint32_t flags, uint32_t lost, Record& out);
  uint32_t lost_for_gap(int64_t dt) const;
  void compact();

  const ScanLayout* l_ = nullptr;
  FramerOptions o_;
  std::array<uint8_t, kBufferBytes> buf_{};
  size_t start_ = 0;
  size_t end_ = 0;
  bool synced_ = false;
  bool have_last_ = false;
  bool resync_pending_ = false;
  int64_t last_t_ = 0;
  int64_t period_ns_ = 0;
  int consecutive_ooo_ = 0;
  FramerCounters c_;
};

}  // namespace kestrel::drivers::iio

#include "kestrel/drivers/iio_imu.hpp"

#include <poll.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstdio>
#include <stdexcept>

namespace kestrel::drivers::iio {

const char* to_string(ImuState s) {
  switch (s) {
    case ImuState::kClosed:
      return "closed";
    case ImuState::kWaiting:
      return "waiting";
    case ImuState::kStreaming:
      return "streaming";
    case ImuState::kStalled:
      return "stalled";
    case ImuState::kDisconnected:
      return "disconnected";
  }
  return "?";
}

void ImuConfig::validate() const {
  bool seen[3] = {false, false, false};
  for (int8_t r : axis_remap) {
    const int a = r < 0 ? -r : r;
    if (a < 1 || a > 3 || seen[a - 1])
      throw std::invalid_argument("axis_remap: must be a signed permutation of x, y, z");
    seen[a - 1] = true;
  }
  if (device.empty() && (accel_device.empty() || gyro_device.empty()))
    throw std::invalid_argument("device: missing (a combined device, or accel_device and gyro_device)");
  if (!device.empty() && (!accel_device.empty() || !gyro_device.empty()))
    throw std::invalid_argument("device: a combined device excludes accel_device and gyro_device");
  if (!device.empty() && device == accel_device) throw std::invalid_argument("device: named twice");
  if (device.empty() && accel_device == gyro_device)
    throw std::invalid_argument("accel_device: the same as gyro_device (use device: for a combined one)");
  static const char* kClocks[] = {
      "realtime", "monotonic", "monotonic_raw", "realtime_coarse", "monotonic_coarse", "boottime", "tai"};
  bool clock_ok = false;
  for (const char* c : kClocks) clock_ok = clock_ok || timestamp_clock == c;
  if (!clock_ok) {
    throw std::invalid_argument(
        "timestamp_clock: expected realtime, monotonic, monotonic_raw, realtime_coarse, "
        "monotonic_coarse, boottime or tai");
  }
  if (sysfs_root.empty()) throw std::invalid_argument("sysfs_root: must not be empty");
  if (dev_root.empty()) throw std::invalid_argument("dev_root: must not be empty");
  if (!(rate_hz >= 0) || !(accel_rate_hz >= 0) || !(gyro_rate_hz >= 0) || rate_hz > 100000 ||
      accel_rate_hz > 100000 || gyro_rate_hz > 100000)
    throw std::invalid_argument("rate_hz: must be in [0, 100000] (0 = the device's)");
  if (buffer_length_samples < 2 || buffer_length_samples > 1'000'000)
    throw std::invalid_argument("buffer_length_samples: must be in 2..1000000");
  if (watermark_samples < 1 || watermark_samples > buffer_length_samples)
    throw std::invalid_argument("watermark_samples: must be in 1..buffer_length_samples");
  if (read_timeout_ms <= 0) throw std::invalid_argument("read_timeout_ms: must be > 0");
  if (stall_timeout_ns <= 0) throw std::invalid_argument("stall_timeout_ms: must be > 0");
  if (max_stamp_gap_ns <= 0) throw std::invalid_argument("max_stamp_gap_ms: must be > 0");
  if (resync_records < 2 || resync_records > 16)
    throw std::invalid_argument("resync_records: must be in 2..16");
}

ImuDriver::ImuDriver(const HostClock& clock, const ImuConfig& cfg)
    : clock_(clock), cfg_(cfg), sync_(cfg.clock) {
  cfg_.validate();
}

ImuDriver::~ImuDriver() { close(); }

bool ImuDriver::is_open() const { return state_ != ImuState::kClosed; }

void ImuDriver::close() {
  for (Stream& s : streams_) s.dev.close();
  state_ = ImuState::kClosed;
}

std::string ImuDriver::open() {
  close();
  DeviceOptions base;
  base.sysfs_root = cfg_.sysfs_root;
  base.dev_root = cfg_.dev_root;
  base.timestamp_clock = cfg_.timestamp_clock;
  base.buffer_length_samples = cfg_.buffer_length_samples;
  base.watermark_samples = cfg_.watermark_samples;
  DeviceOptions opts[2] = {base, base};
  if (cfg_.combined()) {
    n_streams_ = 1;
    opts[0].name = cfg_.device;
    opts[0].want_accel = opts[0].want_gyro = true;
    opts[0].rate_hz = cfg_.rate_hz;
  } else {
    n_streams_ = 2;
    opts[0].name = cfg_.gyro_device;
    opts[0].want_gyro = true;
    opts[0].rate_hz = cfg_.gyro_rate_hz;
    opts[1].name = cfg_.accel_device;
    opts[1].want_accel = true;
    opts[1].rate_hz = cfg_.accel_rate_hz;
  }
  const int64_t now = clock_.now_ns();
  for (int i = 0; i < n_streams_; ++i) {
    Stream& s = streams_[static_cast<size_t>(i)];
    if (std::string e = s.dev.open(opts[i]); !e.empty()) {
      close();
      return e;
    }
    s.accel = opts[i].want_accel;
    s.gyro = opts[i].want_gyro;
    FramerOptions fo;
    fo.nominal_period_ns =
        s.dev.rate_hz() > 0 ? static_cast<int64_t>(std::llround(1e9 / s.dev.rate_hz())) : 0;
    fo.max_gap_ns = cfg_.max_stamp_gap_ns;
    fo.confirm_records = cfg_.resync_records;
    s.framer.configure(&s.dev.layout(), fo);
    s.last_data_ns = now;
    s.stalled = false;
    s.got = false;
  }
  primary_ = 0;
  if (n_streams_ == 2 && streams_[1].dev.rate_hz() > streams_[0].dev.rate_hz()) primary_ = 1;
  const Stream& sec = streams_[static_cast<size_t>(1 - primary_)];
  secondary_period_ns_ = n_streams_ == 2 && sec.dev.rate_hz() > 0
                             ? static_cast<int64_t>(std::llround(1e9 / sec.dev.rate_hz()))
                             : 0;
  if (n_streams_ == 2 && streams_[0].dev.timestamp_clock() != streams_[1].dev.timestamp_clock()) {
    const std::string a = streams_[0].dev.timestamp_clock(), b = streams_[1].dev.timestamp_clock();
    close();
    return cfg_.gyro_device + " stamps on " + a + " but " + cfg_.accel_device + " on " + b +
           ": the merge needs one clock (set timestamp_clock, docs/drivers/iio.md)";
  }
  want_host_stamps_ = cfg_.timestamp_clock == "monotonic" &&
                      streams_[static_cast<size_t>(primary_)].dev.timestamp_clock() == "monotonic";
  host_stamps_ = want_host_stamps_;
  clock_checked_ = false;
  have_lag_ = false;
  sync_ = ClockSync(cfg_.clock);
  pend_head_ = pend_count_ = 0;
  hist_head_ = hist_count_ = 0;
  lost_carry_ = 0;
  state_ = ImuState::kWaiting;
  return "";
}

ImuState ImuDriver::step(ImuSink& sink) {
  if (state_ == ImuState::kClosed || state_ == ImuState::kDisconnected) return state_;
  pollfd pfd[2];
  for (int i = 0; i < n_streams_; ++i) {
    pfd[i].fd = streams_[static_cast<size_t>(i)].dev.fd();
    pfd[i].events = POLLIN;
    pfd[i].revents = 0;
  }
  int r = ::poll(pfd, static_cast<nfds_t>(n_streams_), cfg_.read_timeout_ms);
  if (r < 0) r = 0;  // EINTR: the checks below still run
  const int64_t t_rx = clock_.now_ns();
  for (int i = 0; i < n_streams_; ++i) {
    Stream& s = streams_[static_cast<size_t>(i)];
    s.got = false;
    if (r > 0 && (pfd[i].revents & (POLLIN | POLLERR | POLLNVAL))) read_stream(i, t_rx, sink);
    if (state_ == ImuState::kDisconnected) return state_;
  }
  const Stream& p = streams_[static_cast<size_t>(primary_)];
  if (p.got) observe_clock(p.newest_t_dev, t_rx, sink);
  bool any_stalled = false;
  for (int i = 0; i < n_streams_; ++i) {
    Stream& s = streams_[static_cast<size_t>(i)];
    if (!s.stalled && t_rx - s.last_data_ns > cfg_.stall_timeout_ns) {
      s.stalled = true;
      ++counters_.stalls;
      sink.event(
          t_rx, EventCode::kDriverFault,
          i == primary_
              ? "iio imu: no data within stall_timeout_ms"
              : "iio imu: the slower stream sent nothing within stall_timeout_ms (its last value is held)");
    }
    any_stalled = any_stalled || s.stalled;
  }
  drain(t_rx, sink);
  if (any_stalled) {
    state_ = ImuState::kStalled;
  } else if (have_out_ || p.got) {
    state_ = ImuState::kStreaming;
  }
  return state_;
}

void ImuDriver::read_stream(int i, int64_t t_rx, ImuSink& sink) {
  Stream& s = streams_[static_cast<size_t>(i)];
  // A few buffer loads at most: a backlog larger than that is worked off
  // over the next steps rather than starving the other stream.
  for (int k = 0; k < 4; ++k) {
    const size_t space = s.framer.write_space();
    if (space == 0) break;
    const ssize_t n = ::read(s.dev.fd(), s.framer.write_ptr(), space);
    if (n > 0) {
      s.framer.commit(static_cast<size_t>(n));
      ++counters_.reads;
      counters_.bytes += static_cast<uint64_t>(n);
      if (s.stalled) {
        s.stalled = false;
        sink.event(t_rx, EventCode::kInfo, "iio imu: stream resumed");
      }
      s.last_data_ns = t_rx;
      RecordFramer::Record rec;
      while (s.framer.next(rec)) on_record(i, rec, t_rx, sink);
      if (static_cast<size_t>(n) < space) break;
      continue;
    }
    if (n == 0) break;  // a FIFO with no writer (tests); a device never returns 0
    if (errno == EINTR) continue;
    if (errno == EAGAIN) break;
    ++counters_.read_errors;
    if (errno == ENODEV || errno == ENXIO || errno == EIO) {
      state_ = ImuState::kDisconnected;
      sink.event(t_rx, EventCode::kDriverFault, "iio imu: device gone (read failed)");
    }
    break;
  }
}

void ImuDriver::on_record(int i, const RecordFramer::Record& r, int64_t t_rx, ImuSink& sink) {
  Stream& s = streams_[static_cast<size_t>(i)];
  decode_record(r.bytes, s.dev.layout(), dec_);
  if (dec_.non_finite) {
    ++counters_.non_finite;
    return;
  }
  if (r.flags & kRecordClockReset)
    sink.event(t_rx, EventCode::kClockJump, "iio imu: device stamps restarted");
  if (i != primary_) {
    if (r.flags & kRecordClockReset) hist_count_ = 0;
    SecondaryPoint& h = hist_[hist_head_];
    h.t_dev = r.t_dev_ns;
    h.v = s.accel ? dec_.acc_mps2 : dec_.gyro_rps;
    h.sat = s.accel ? dec_.acc_saturated : dec_.gyro_saturated;
    hist_head_ = (hist_head_ + 1) % kHistoryCap;
    if (hist_count_ < kHistoryCap) ++hist_count_;
    s.got = true;
    s.newest_t_dev = r.t_dev_ns;
    return;
  }
  if (r.flags & kRecordClockReset) {
    // Queued samples carry stamps of the old clock: mapping them with the
    // new one would put them in the wrong place.
    counters_.dropped_on_reset += pend_count_;
    lost_carry_ += static_cast<uint32_t>(pend_count_);
    pend_count_ = 0;
    hist_count_ = 0;
  }
  if (pend_count_ == kPendingCap) {
    ++counters_.pending_overflows;
    Pending& old = pending_[pend_head_];
    if (fill_secondary(old, true) > 0) emit(old, sink);
    pend_head_ = (pend_head_ + 1) % kPendingCap;
    --pend_count_;
  }
  Pending& p = pending_[(pend_head_ + pend_count_) % kPendingCap];
  p.t_dev = r.t_dev_ns;
  p.t_rx = t_rx;
  p.acc = dec_.acc_mps2;
  p.gyro = dec_.gyro_rps;
  p.acc_sat = s.accel && dec_.acc_saturated;
  p.gyro_sat = s.gyro && dec_.gyro_saturated;
  p.complete = n_streams_ == 1;
  p.lost = r.lost_before;
  ++pend_count_;
  s.got = true;
  s.newest_t_dev = r.t_dev_ns;
}

void ImuDriver::observe_clock(int64_t t_dev, int64_t t_rx, ImuSink& sink) {
  const int64_t lag = t_rx - t_dev;
  if (!clock_checked_) {
    clock_checked_ = true;
    // Monotonic stamps were asked for and the file says so, but HID sensors
    // with their own timestamp usage ignore it: believe the first read.
    if (want_host_stamps_ && (lag < -1'000'000 || lag > 1'000'000'000)) {
      host_stamps_ = false;
      ++counters_.not_host_clock;
      sink.event(
          t_rx, EventCode::kDriverFault,
          "iio imu: stamps are not on CLOCK_MONOTONIC although the device says so; mapped by clock sync");
    }
  }
  if (!have_lag_ || lag < min_lag_ns_) min_lag_ns_ = lag;
  if (!have_lag_ || lag > max_lag_ns_) max_lag_ns_ = lag;
  have_lag_ = true;
  const bool ok =
      host_stamps_ ? sync_.add(t_dev, t_dev + cfg_.clock.latency_floor_ns) : sync_.add(t_dev, t_rx);
  if (!ok) {
    ++counters_.clock_jumps;
    sink.event(t_rx, EventCode::kClockJump, "iio imu: device clock jumped; clock sync restarted");
  }
}

int ImuDriver::fill_secondary(Pending& p, bool force) {
  if (hist_count_ == 0) return force ? -1 : 0;
  const auto at = [&](size_t k) -> const SecondaryPoint& {  // k = 0 oldest
    return hist_[(hist_head_ + kHistoryCap - hist_count_ + k) % kHistoryCap];
  };
  const SecondaryPoint& oldest = at(0);
  const SecondaryPoint& newest = at(hist_count_ - 1);
  const Stream& sec = streams_[static_cast<size_t>(1 - primary_)];
  Vec3d& dst = sec.accel ? p.acc : p.gyro;
  bool& sat = sec.accel ? p.acc_sat : p.gyro_sat;
  if (p.t_dev < oldest.t_dev) return -1;  // nothing before it (the slower stream started later)
  if (p.t_dev >= newest.t_dev) {
    if (p.t_dev > newest.t_dev) {
      if (!force) return 0;  // wait for the next slower-stream sample
      ++counters_.secondary_held;
    }
    dst = newest.v;
    sat = newest.sat;
    return 1;
  }
  size_t k = hist_count_ - 1;
  while (k > 0 && at(k - 1).t_dev > p.t_dev) --k;
  const SecondaryPoint& s0 = at(k - 1);
  const SecondaryPoint& s1 = at(k);
  const double w = static_cast<double>(p.t_dev - s0.t_dev) / static_cast<double>(s1.t_dev - s0.t_dev);
  for (size_t a = 0; a < 3; ++a) dst[a] = s0.v[a] + w * (s1.v[a] - s0.v[a]);
  sat = s0.sat || s1.sat;
  if (secondary_period_ns_ > 0 && s1.t_dev - s0.t_dev > 3 * secondary_period_ns_)
    ++counters_.secondary_gap_interpolations;
  return 1;
}

void ImuDriver::drain(int64_t t_rx, ImuSink& sink) {
  const bool sec_stalled = n_streams_ == 2 && streams_[static_cast<size_t>(1 - primary_)].stalled;
  while (pend_count_ > 0) {
    Pending& p = pending_[pend_head_];
    if (!p.complete) {
      const bool force = sec_stalled || t_rx - p.t_rx > cfg_.stall_timeout_ns;
      const int r = fill_secondary(p, force);
      if (r == 0) break;
      if (r < 0) {
        ++counters_.secondary_missing;
        if (have_out_) lost_carry_ += 1 + p.lost;
        pend_head_ = (pend_head_ + 1) % kPendingCap;
        --pend_count_;
        continue;
      }
    }
    emit(p, sink);
    pend_head_ = (pend_head_ + 1) % kPendingCap;
    --pend_count_;
  }
}

void ImuDriver::emit(const Pending& p, ImuSink& sink) {
  ImuSample s;
  s.t_ns = sync_.valid() ? sync_.to_host_ns(p.t_dev) : p.t_rx;
  if (have_out_ && s.t_ns <= last_out_t_ns_) {
    ++counters_.time_clamped;
    s.t_ns = last_out_t_ns_ + 1;
  }
  s.t_recv_ns = p.t_rx;
  const uint32_t lost = p.lost + lost_carry_;
  lost_carry_ = 0;
  if (have_out_) {
    seq_ += 1 + lost;
    if (lost > 0) s.flags |= kImuGapBefore;
  }
  s.seq = seq_;
  if (p.acc_sat) {
    s.flags |= kImuAccSaturated;
    ++counters_.acc_saturated;
  }
  if (p.gyro_sat) {
    s.flags |= kImuGyroSaturated;
    ++counters_.gyro_saturated;
  }
  for (size_t i = 0; i < 3; ++i) {
    // A signed axis number (-3..3), not a character.
    const int r = cfg_.axis_remap[i];  // NOLINT(bugprone-signed-char-misuse)
    const size_t a = static_cast<size_t>((r < 0 ? -r : r) - 1);
    const double sign = r < 0 ? -1.0 : 1.0;
    s.gyro_rps[i] = sign * p.gyro[a];
    s.acc_mps2[i] = sign * p.acc[a];
  }
  have_out_ = true;
  last_out_t_ns_ = s.t_ns;
  if (sink.push(s)) {
    ++counters_.samples;
  } else {
    ++counters_.sink_drops;
  }
}

FramerCounters ImuDriver::framer_totals() const {
  FramerCounters t;
  for (int i = 0; i < n_streams_; ++i) {
    const FramerCounters& c = framer_counters(i);
    t.records += c.records;
    t.resyncs += c.resyncs;
    t.torn_records += c.torn_records;
    t.bytes_skipped += c.bytes_skipped;
    t.discarded_records += c.discarded_records;
    t.out_of_order += c.out_of_order;
    t.gaps += c.gaps;
    t.samples_lost += c.samples_lost;
    t.clock_resets += c.clock_resets;
    t.overflow_bytes += c.overflow_bytes;
  }
  return t;
}

std::string ImuDriver::description() const {
  std::string s;
  for (int i = 0; i < n_streams_; ++i) {
    if (i > 0) s += " + ";
    s += device(i).describe();
  }
  if (n_streams_ == 2) s += "; output at " + device(primary_).name() + "'s stamps";
  s += host_stamps_ ? "; stamps used as host time" : "; stamps mapped by clock sync";
  return s;
}

std::string ImuDriver::report() const {
  const ImuCounters& c = counters_;
  const FramerCounters f = framer_totals();
  char b[768];
  std::snprintf(
      b, sizeof b,
      "iio imu: state %s, %llu samples, %llu stalls, %llu gaps (%llu samples lost), %llu torn records, "
      "%llu out-of-order, %llu discarded, %llu clock resets, %llu slower-stream holds, %llu saturated, "
      "%llu sink drops, %s, read lag %.3f..%.3f ms, clock skew %.1f ppm",
      to_string(state_), (unsigned long long)c.samples, (unsigned long long)c.stalls,
      (unsigned long long)f.gaps, (unsigned long long)f.samples_lost, (unsigned long long)f.torn_records,
      (unsigned long long)f.out_of_order, (unsigned long long)f.discarded_records,
      (unsigned long long)f.clock_resets, (unsigned long long)c.secondary_held,
      (unsigned long long)c.acc_saturated + (unsigned long long)c.gyro_saturated,
      (unsigned long long)c.sink_drops, host_stamps_ ? "host-clock stamps" : "device-clock stamps",
      min_lag_ns_ * 1e-6, max_lag_ns_ * 1e-6, sync_.skew() * 1e6);
  return b;
}

}  // namespace kestrel::drivers::iio

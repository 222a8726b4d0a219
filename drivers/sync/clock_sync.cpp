#include "kestrel/drivers/clock_sync.hpp"

#include <cmath>
#include <cstdlib>

#include "kestrel/rt/clock.hpp"

namespace kestrel::drivers {
namespace {

int64_t floor_div(int64_t a, int64_t b) {
  int64_t q = a / b;
  if ((a % b != 0) && ((a < 0) != (b < 0))) --q;
  return q;
}

}  // namespace

int64_t MonotonicHostClock::now_ns() const { return rt::now_ns(); }

void ClockSync::reset() {
  first_ = 0;
  count_ = 0;
  open_ = false;
  n_points_total_ = 0;
  skew_ = opt_.prior_skew;
  mean_excess_ns_ = 0.0;
}

bool ClockSync::add(int64_t device_ns, int64_t host_ns) {
  host_ns -= opt_.latency_floor_ns;
  bool ok = true;
  if (valid()) {
    // A device clock that runs backwards (bridge reboot, counter reset) or a
    // point far below the envelope (the device clock leapt ahead) invalidates
    // the whole window: start again rather than bend the line.
    const bool backwards = device_ns < last_d_;
    const bool below = host_ns - to_host_ns(device_ns) < -opt_.jump_threshold_ns;
    if (backwards || below) {
      ++jumps_;
      reset();
      ok = false;
    }
  }
  last_d_ = device_ns;
  ++n_points_total_;
  const int64_t bucket = floor_div(device_ns, opt_.bucket_ns > 0 ? opt_.bucket_ns : 1);
  if (!open_) {
    open_ = true;
    cur_ = Point{device_ns, host_ns};
    cur_bucket_ = bucket;
    refit();
    return ok;
  }
  if (bucket == cur_bucket_) {
    // Within one bucket the skew is negligible (100 ppm * 100 ms = 10 us is
    // below what the lowest-latency choice needs), so compare plain offsets.
    if (host_ns - device_ns < cur_.h - cur_.d) {
      cur_ = Point{device_ns, host_ns};
      refit();
    }
    return ok;
  }
  close_bucket();
  cur_ = Point{device_ns, host_ns};
  cur_bucket_ = bucket;
  refit();
  return ok;
}

void ClockSync::close_bucket() {
  const int cap =
      opt_.max_buckets < 2 ? 2 : (opt_.max_buckets > kMaxBuckets ? kMaxBuckets : opt_.max_buckets);
  if (count_ >= cap) {
    first_ = (first_ + 1) % kMaxBuckets;
    --count_;
  }
  pts_[static_cast<size_t>((first_ + count_) % kMaxBuckets)] = cur_;
  ++count_;
}

void ClockSync::refit() {
  int n = 0;
  for (int i = 0; i < count_; ++i) scratch_[static_cast<size_t>(n++)] = at(i);
  if (open_) scratch_[static_cast<size_t>(n++)] = cur_;
  if (n == 0) return;
  const Point p0 = scratch_[0];
  auto x = [&](int i) { return static_cast<double>(scratch_[static_cast<size_t>(i)].d - p0.d); };
  auto y = [&](int i) { return static_cast<double>(scratch_[static_cast<size_t>(i)].h - p0.h); };

  // Fixed-slope fit: the line with the prior slope lowered onto the lowest point.
  auto fit_with_slope = [&](double skew) {
    int best = 0;
    double best_v = 0;
    for (int i = 0; i < n; ++i) {
      const double v = y(i) - x(i) * (1.0 + skew);
      if (i == 0 || v < best_v) {
        best_v = v;
        best = i;
      }
    }
    skew_ = skew;
    base_d_ = scratch_[static_cast<size_t>(best)].d;
    base_h_origin_ = scratch_[static_cast<size_t>(best)].h;
  };

  if (n < opt_.min_buckets_for_skew || n < 2) {
    fit_with_slope(opt_.prior_skew);
  } else {
    // Lower convex hull, monotone chain over points sorted by device time.
    int m = 0;
    for (int i = 0; i < n; ++i) {
      while (m >= 2) {
        const int a = hull_[static_cast<size_t>(m - 2)];
        const int b = hull_[static_cast<size_t>(m - 1)];
        const double cross = (x(b) - x(a)) * (y(i) - y(a)) - (y(b) - y(a)) * (x(i) - x(a));
        if (cross <= 0) {
          --m;  // b is not below the chord a-i: drop it
        } else {
          break;
        }
      }
      hull_[static_cast<size_t>(m++)] = i;
    }
    double mean_x = 0;
    for (int i = 0; i < n; ++i) mean_x += x(i);
    mean_x /= n;
    int e = 0;
    while (e + 2 < m && x(hull_[static_cast<size_t>(e + 1)]) < mean_x) ++e;
    const int a = hull_[static_cast<size_t>(e)];
    const int b = hull_[static_cast<size_t>(e + 1 < m ? e + 1 : e)];
    if (a == b || x(b) == x(a)) {
      fit_with_slope(skew_);
    } else {
      // slope - 1 computed from differences to keep the precision of ppm.
      const double dx = x(b) - x(a);
      const double skew = ((y(b) - y(a)) - dx) / dx;
      if (std::abs(skew) > opt_.max_abs_skew) {
        ++skew_faults_;
        fit_with_slope(opt_.prior_skew);
      } else {
        skew_ = skew;
        base_d_ = scratch_[static_cast<size_t>(a)].d;
        base_h_origin_ = scratch_[static_cast<size_t>(a)].h;
      }
    }
  }
  double excess = 0;
  for (int i = 0; i < n; ++i) {
    const Point& p = scratch_[static_cast<size_t>(i)];
    excess += static_cast<double>(p.h - to_host_ns(p.d));
  }
  mean_excess_ns_ = excess / n;
}

int64_t ClockSync::to_host_ns(int64_t device_ns) const {
  const int64_t dd = device_ns - base_d_;
  return base_h_origin_ + dd + static_cast<int64_t>(std::llround(static_cast<double>(dd) * skew_));
}

// ---- StrobeMatcher ------------------------------------------------------------

void StrobeMatcher::add_strobe(const StrobeStamp& s) {
  if (size_ == kHistory) {
    const int oldest = (head_ - size_ + kHistory) % kHistory;
    if (!used_[static_cast<size_t>(oldest)]) ++unused_;
    --size_;
  }
  hist_[static_cast<size_t>(head_)] = s;
  used_[static_cast<size_t>(head_)] = false;
  head_ = (head_ + 1) % kHistory;
  ++size_;
}

StrobeMatch StrobeMatcher::match(int64_t t_camera_ns) {
  StrobeMatch out;
  const int64_t pred = t_camera_ns - static_cast<int64_t>(offset_ns_);
  int best = -1;
  int64_t best_err = 0;
  for (int k = 0; k < size_; ++k) {
    const int i = (head_ - 1 - k + kHistory) % kHistory;
    if (used_[static_cast<size_t>(i)]) continue;
    const int64_t err = std::llabs(hist_[static_cast<size_t>(i)].t_host_ns - pred);
    if (err <= opt_.tolerance_ns && (best < 0 || err < best_err)) {
      best = i;
      best_err = err;
    }
  }
  if (best < 0) {
    ++unmatched_;
    out.t_exposure_start_ns = pred;
    return out;
  }
  const StrobeStamp& s = hist_[static_cast<size_t>(best)];
  used_[static_cast<size_t>(best)] = true;
  out.matched = true;
  out.strobe_seq = s.seq;
  out.t_exposure_start_ns = s.t_host_ns;
  out.residual_ns = t_camera_ns - s.t_host_ns;
  const double r = static_cast<double>(out.residual_ns);
  if (!have_offset_) {
    offset_ns_ = r;
    have_offset_ = true;
  } else {
    offset_ns_ += opt_.offset_gain * (r - offset_ns_);
  }
  sum_sq_dev_ += (r - offset_ns_) * (r - offset_ns_);
  ++matched_;
  return out;
}

double StrobeMatcher::residual_rms_ns() const {
  return matched_ > 0 ? std::sqrt(sum_sq_dev_ / static_cast<double>(matched_)) : 0.0;
}

}  // namespace kestrel::drivers

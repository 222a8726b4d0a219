#include "kestrel/drivers/iio_device.hpp"

#include <dirent.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>

namespace kestrel::drivers::iio {
namespace {

bool exists(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0;
}

std::string trim(std::string s) {
  while (!s.empty() &&
         (s.back() == '\n' || s.back() == ' ' || s.back() == '\r' || s.back() == '\t' || s.back() == '\0'))
    s.pop_back();
  size_t i = 0;
  while (i < s.size() && (s[i] == ' ' || s[i] == '\t')) ++i;
  return s.substr(i);
}

std::string fmt_num(double v) {
  char b[32];
  std::snprintf(b, sizeof b, "%.6g", v);
  return b;
}

constexpr double kG = 9.80665;

}  // namespace

bool read_attr(const std::string& path, std::string& out) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return false;
  char buf[4096];
  std::string s;
  for (;;) {
    const ssize_t n = ::read(fd, buf, sizeof buf);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) {
      ::close(fd);
      return false;
    }
    if (n == 0) break;
    s.append(buf, static_cast<size_t>(n));
    if (s.size() > 65536) break;  // no attribute is this long
  }
  ::close(fd);
  out = trim(std::move(s));
  return true;
}

std::string write_attr(const std::string& path, const std::string& value) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_TRUNC | O_CLOEXEC);
  if (fd < 0) return path + ": cannot open for writing: " + std::strerror(errno);
  ssize_t n;
  do {
    n = ::write(fd, value.data(), value.size());
  } while (n < 0 && errno == EINTR);
  const int err = errno;
  ::close(fd);
  if (n < 0) return path + ": cannot write \"" + value + "\": " + std::strerror(err);
  if (static_cast<size_t>(n) != value.size()) return path + ": short write of \"" + value + "\"";
  return "";
}

bool parse_number(std::string_view text, double& out) {
  std::string s(text);
  s = trim(s);
  if (s.empty() || s.size() > 64) return false;
  // strtod also takes "nan", "inf" and hex: sysfs numbers are plain decimals.
  for (char c : s)
    if (!((c >= '0' && c <= '9') || c == '.' || c == '-' || c == '+' || c == 'e' || c == 'E')) return false;
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(s.c_str(), &end);
  if (end != s.c_str() + s.size() || errno == ERANGE || !std::isfinite(v)) return false;
  out = v;
  return true;
}

const char* parse_available_rates(std::string_view text, AvailableRates& out) {
  AvailableRates a;
  std::string s = trim(std::string(text));
  if (s.empty()) return "empty list";
  const bool range = s.front() == '[';
  if (range) {
    if (s.back() != ']') return "a range must end with ']'";
    s = s.substr(1, s.size() - 2);
  }
  std::vector<double> v;
  size_t i = 0;
  while (i < s.size()) {
    while (i < s.size() && (s[i] == ' ' || s[i] == '\t' || s[i] == '\n')) ++i;
    if (i >= s.size()) break;
    size_t j = i;
    while (j < s.size() && s[j] != ' ' && s[j] != '\t' && s[j] != '\n') ++j;
    double x = 0;
    if (!parse_number(std::string_view(s).substr(i, j - i), x)) return "not a number";
    if (!(x > 0) && !(range && x == 0 && v.size() == 1)) return "frequencies must be > 0";
    if (v.size() >= 256) return "too many frequencies";
    v.push_back(x);
    i = j;
  }
  if (v.empty()) return "empty list";
  if (range) {
    if (v.size() != 3) return "a range is [min step max]";
    if (v[2] < v[0]) return "range max below min";
    a.is_range = true;
    a.min_hz = v[0];
    a.step_hz = v[1];
    a.max_hz = v[2];
  } else {
    std::sort(v.begin(), v.end());
    a.list_hz = std::move(v);
  }
  out = std::move(a);
  return nullptr;
}

double choose_rate(const AvailableRates& a, double requested_hz) {
  if (!(requested_hz > 0)) return 0;
  if (a.is_range) {
    double r = std::min(std::max(requested_hz, a.min_hz), a.max_hz);
    if (a.step_hz > 0) {
      r = a.min_hz + std::ceil((r - a.min_hz) / a.step_hz - 1e-9) * a.step_hz;
      if (r > a.max_hz) r = a.max_hz;
    }
    return r;
  }
  if (a.list_hz.empty()) return requested_hz;
  for (double f : a.list_hz)
    if (f >= requested_hz * (1 - 1e-9)) return f;
  return a.list_hz.back();
}

std::vector<DeviceEntry> list_devices(const std::string& root, std::string* error) {
  std::vector<DeviceEntry> out;
  DIR* d = ::opendir(root.c_str());
  if (d == nullptr) {
    if (error) *error = root + ": cannot list IIO devices: " + std::strerror(errno);
    return out;
  }
  while (dirent* e = ::readdir(d)) {
    const std::string n = e->d_name;
    if (n.rfind("iio:device", 0) != 0 || n.size() == 10 || n.size() > 16) continue;
    bool digits = true;
    for (size_t i = 10; i < n.size(); ++i) digits = digits && n[i] >= '0' && n[i] <= '9';
    if (!digits) continue;
    DeviceEntry de;
    de.number = std::atoi(n.c_str() + 10);
    de.dir = root + "/" + n;
    if (!read_attr(de.dir + "/name", de.name)) de.name.clear();
    de.has_accel = exists(de.dir + "/scan_elements/in_accel_x_en");
    de.has_gyro = exists(de.dir + "/scan_elements/in_anglvel_x_en");
    de.has_timestamp = exists(de.dir + "/scan_elements/in_timestamp_en");
    de.has_buffer = exists(de.dir + "/buffer/enable");
    out.push_back(std::move(de));
  }
  ::closedir(d);
  std::sort(out.begin(), out.end(),
            [](const DeviceEntry& a, const DeviceEntry& b) { return a.number < b.number; });
  return out;
}

// ---- Device -----------------------------------------------------------------------

Device::~Device() { close(); }

void Device::close() {
  if (fd_ >= 0) {
    ::close(fd_);
    fd_ = -1;
    (void)write_attr(dir_ + "/buffer/enable", "0");
  }
}

std::string Device::read_scale(const std::string& type, const char* axis, double& scale,
                               double& offset) const {
  const std::string per_axis = dir_ + "/in_" + type + "_" + axis + "_scale";
  const std::string shared = dir_ + "/in_" + type + "_scale";
  std::string text, path = per_axis;
  if (!read_attr(per_axis, text)) {
    path = shared;
    if (!read_attr(shared, text)) {
      return shared + ": missing (and no in_" + type + "_" + axis + "_scale): cannot convert counts to " +
             (type == "accel" ? "m/s^2" : "rad/s");
    }
  }
  if (!parse_number(text, scale) || !(scale > 0)) {
    return path + ": \"" + text + "\" is not a positive number (the scale in " +
           (type == "accel" ? "m/s^2" : "rad/s") + " per count)";
  }
  offset = 0;
  const std::string off_axis = dir_ + "/in_" + type + "_" + axis + "_offset";
  const std::string off_shared = dir_ + "/in_" + type + "_offset";
  std::string off_path = off_axis;
  if (!read_attr(off_axis, text)) {
    off_path = off_shared;
    if (!read_attr(off_shared, text)) return "";
  }
  if (!parse_number(text, offset))
    return off_path + ": \"" + text + "\" is not a number (an offset in counts)";
  return "";
}

std::string Device::configure_rate(const DeviceOptions& o) {
  std::vector<std::string> attrs;
  if (o.want_gyro && exists(dir_ + "/in_anglvel_sampling_frequency"))
    attrs.push_back("in_anglvel_sampling_frequency");
  if (o.want_accel && exists(dir_ + "/in_accel_sampling_frequency"))
    attrs.push_back("in_accel_sampling_frequency");
  if (attrs.empty() && exists(dir_ + "/sampling_frequency")) attrs.push_back("sampling_frequency");
  rate_hz_ = 0;
  if (attrs.empty()) {
    notes_.push_back(dir_ + ": no sampling_frequency attribute: the rate is learnt from the stamps");
    return "";
  }
  for (size_t k = 0; k < attrs.size(); ++k) {
    const std::string path = dir_ + "/" + attrs[k];
    double target = o.rate_hz;
    std::string avail_path = path + "_available";
    std::string text;
    if (!read_attr(avail_path, text)) {
      avail_path = dir_ + "/sampling_frequency_available";
      if (!read_attr(avail_path, text)) avail_path.clear();
    }
    if (!avail_path.empty()) {
      AvailableRates a;
      if (const char* err = parse_available_rates(text, a)) return avail_path + ": \"" + text + "\": " + err;
      target = choose_rate(a, o.rate_hz);
    }
    if (o.rate_hz > 0) {
      std::string e = write_attr(path, fmt_num(target));
      if (!e.empty()) return e;
    }
    double rb = 0;
    if (!read_attr(path, text) || !parse_number(text, rb) || !(rb > 0))
      return path + ": \"" + text + "\" is not a positive frequency in Hz";
    if (o.rate_hz > 0 && std::abs(rb - target) > 0.01 * target)
      notes_.push_back(path + ": asked " + fmt_num(target) + " Hz, reads " + fmt_num(rb) + " Hz");
    if (k == 0) rate_hz_ = rb;
  }
  return "";
}

std::string Device::open(const DeviceOptions& o) {
  close();
  notes_.clear();
  layout_ = ScanLayout{};
  rate_hz_ = 0;
  std::string err;
  const std::vector<DeviceEntry> devs = list_devices(o.sysfs_root, &err);
  if (!err.empty()) return err;
  const DeviceEntry* found = nullptr;
  std::string names;
  for (const DeviceEntry& d : devs) {
    names += (names.empty() ? "" : ", ") + d.name + " (iio:device" + std::to_string(d.number) + ")";
    if (found == nullptr && d.name == o.name) found = &d;
  }
  if (found == nullptr) {
    return o.sysfs_root + ": no IIO device named \"" + o.name +
           "\" (found: " + (names.empty() ? "none" : names) + ")";
  }
  dir_ = found->dir;
  name_ = found->name;
  const std::string se = dir_ + "/scan_elements/";
  if (!found->has_buffer) return dir_ + "/buffer/enable: missing: the device has no buffered capture";
  // Scan elements and the clock can only change while the buffer is off.
  if (std::string e = write_attr(dir_ + "/buffer/enable", "0"); !e.empty()) return e;

  const std::string clk = dir_ + "/current_timestamp_clock";
  clock_file_ = exists(clk);
  if (clock_file_) {
    if (std::string e = write_attr(clk, o.timestamp_clock); !e.empty()) {
      return e +
             " (the kernel takes realtime, monotonic, monotonic_raw, realtime_coarse, monotonic_coarse, "
             "boottime, tai)";
    }
    if (!read_attr(clk, clock_)) return clk + ": cannot read back";
    if (clock_ != o.timestamp_clock)
      return clk + ": reads \"" + clock_ + "\" after writing \"" + o.timestamp_clock + "\"";
  } else {
    clock_ = "realtime";
    notes_.push_back(clk +
                     ": missing (a kernel before 4.10): stamps are on CLOCK_REALTIME; clock sync maps them");
  }
  if (std::string e = configure_rate(o); !e.empty()) return e;

  DIR* d = ::opendir(se.c_str());
  if (d == nullptr) return se + ": cannot list scan elements: " + std::strerror(errno);
  std::vector<std::string> elements;
  while (dirent* e = ::readdir(d)) {
    const std::string n = e->d_name;
    if (n.size() > 3 && n.compare(n.size() - 3, 3, "_en") == 0) elements.push_back(n.substr(0, n.size() - 3));
  }
  ::closedir(d);
  std::sort(elements.begin(), elements.end());
  for (const std::string& n : elements) {
    const ChannelKind kind = channel_kind(n);
    const bool accel =
        kind == ChannelKind::kAccelX || kind == ChannelKind::kAccelY || kind == ChannelKind::kAccelZ;
    const bool gyro =
        kind == ChannelKind::kAnglvelX || kind == ChannelKind::kAnglvelY || kind == ChannelKind::kAnglvelZ;
    const bool want = (accel && o.want_accel) || (gyro && o.want_gyro) || kind == ChannelKind::kTimestamp;
    const std::string en = se + n + "_en";
    if (std::string e = write_attr(en, want ? "1" : "0"); !e.empty()) return e;
    std::string v;
    if (!read_attr(en, v)) return en + ": cannot read back";
    if (v != "0" && v != "1") return en + ": \"" + v + "\" is not 0 or 1";
    if (v != (want ? "1" : "0")) {
      if (want) return en + ": reads 0 after writing 1 (the device refused the channel)";
      notes_.push_back(en + ": stays enabled (read and skipped)");
    }
    if (v != "1") continue;
    if (layout_.count >= kMaxScanElements)
      return se + ": more than " + std::to_string(kMaxScanElements) + " enabled elements";
    ScanElement el;
    el.kind = kind;
    const std::string idx_path = se + n + "_index", type_path = se + n + "_type";
    double idx = 0;
    if (!read_attr(idx_path, v) || !parse_number(v, idx) || idx < 0 || idx > 1e6 || idx != std::floor(idx))
      return idx_path + ": \"" + v + "\" is not a scan index";
    el.index = static_cast<int>(idx);
    if (!read_attr(type_path, v)) return type_path + ": missing";
    if (const char* msg = parse_scan_type(v, el.type)) return type_path + ": \"" + v + "\": " + msg;
    layout_.el[layout_.count++] = el;
  }
  if (const char* msg = compute_layout(layout_)) return se + ": " + msg;
  if (o.want_accel && !layout_.has_accel())
    return se + "in_accel_{x,y,z}_en: missing: \"" + name_ + "\" has no accelerometer channels in its scan";
  if (o.want_gyro && !layout_.has_gyro())
    return se + "in_anglvel_{x,y,z}_en: missing: \"" + name_ + "\" has no gyroscope channels in its scan";
  if (layout_.timestamp < 0)
    return se + "in_timestamp_en: missing: the driver needs the device's timestamp channel";

  static const char* kAxes[3] = {"x", "y", "z"};
  for (int part = 0; part < 2; ++part) {
    const std::array<int, 3>& idx = part == 0 ? layout_.accel : layout_.gyro;
    if (idx[0] < 0) continue;
    const std::string type = part == 0 ? "accel" : "anglvel";
    for (int a = 0; a < 3; ++a) {
      ScanElement& el = layout_.el[static_cast<size_t>(idx[static_cast<size_t>(a)])];
      if (std::string e = read_scale(type, kAxes[a], el.scale, el.offset); !e.empty()) return e;
      // A scale in the wrong unit (g or mg instead of m/s^2, degrees instead
      // of radians) still parses: its full range gives it away.
      const double range = el.scale * std::max(std::abs(static_cast<double>(raw_max(el.type)) + el.offset),
                                               std::abs(static_cast<double>(raw_min(el.type)) + el.offset));
      const std::string file = dir_ + "/in_" + type + "_scale";
      const bool narrow = el.type.real_bits <= 16;
      if (part == 0 && range < 2 * kG) {
        return file + ": " + fmt_num(el.scale) + " gives a full range of only +-" + fmt_num(range) +
               " m/s^2 (< 2 g): is the scale in g rather than m/s^2?";
      }
      if (part == 0 && narrow && range > 500 * kG) {
        return file + ": " + fmt_num(el.scale) + " gives a full range of +-" + fmt_num(range) +
               " m/s^2 (> 500 g): is the scale in mg or cm/s^2 rather than m/s^2?";
      }
      if (part == 1 && range < 1.0) {
        return file + ": " + fmt_num(el.scale) + " gives a full range of only +-" + fmt_num(range) +
               " rad/s (< 1 rad/s): a wrong scale";
      }
      if (part == 1 && narrow && range > 200.0) {
        return file + ": " + fmt_num(el.scale) + " gives a full range of +-" + fmt_num(range) +
               " rad/s (> 200 rad/s): is the scale in degrees rather than radians?";
      }
    }
  }

  // A triggered buffer needs a trigger; drivers with their own (HID sensors)
  // set it themselves. Left empty, take the device's own "<name>-devN".
  const std::string trig = dir_ + "/trigger/current_trigger";
  std::string cur;
  if (read_attr(trig, cur) && cur.empty()) {
    const std::string want = name_ + "-dev" + std::to_string(found->number);
    bool set = false;
    if (DIR* td = ::opendir(o.sysfs_root.c_str())) {
      while (dirent* e = ::readdir(td)) {
        std::string tn;
        if (std::string(e->d_name).rfind("trigger", 0) == 0 &&
            read_attr(o.sysfs_root + "/" + e->d_name + "/name", tn) && tn == want)
          set = write_attr(trig, want).empty();
      }
      ::closedir(td);
    }
    if (!set) notes_.push_back(trig + ": empty and no trigger \"" + want + "\" found");
  }

  if (std::string e = write_attr(dir_ + "/buffer/length", std::to_string(o.buffer_length_samples));
      !e.empty())
    return e;
  if (exists(dir_ + "/buffer/watermark")) {
    if (std::string e = write_attr(dir_ + "/buffer/watermark", std::to_string(o.watermark_samples));
        !e.empty())
      return e;
  }
  if (std::string e = write_attr(dir_ + "/buffer/enable", "1"); !e.empty())
    return e + " (a device that needs a trigger: set " + trig + ", docs/drivers/iio.md)";

  node_ = o.dev_root + "/iio:device" + std::to_string(found->number);
  fd_ = ::open(node_.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC);
  if (fd_ < 0) {
    const int e = errno;
    (void)write_attr(dir_ + "/buffer/enable", "0");
    return node_ + ": cannot open: " + std::strerror(e) +
           (e == EACCES  ? " (a udev rule or the iio group: docs/drivers/iio.md)"
            : e == EBUSY ? " (another process reads this device)"
                         : "");
  }
  return "";
}

std::string Device::describe() const {
  std::string s = name_ + " (" + node_ + ") ";
  s += rate_hz_ > 0 ? fmt_num(rate_hz_) + " Hz" : "rate unknown";
  s += ", " + std::to_string(layout_.record_bytes) + " B/record, stamps on " + clock_;
  return s;
}

}  // namespace kestrel::drivers::iio

#include "kestrel/drivers/iio_fake.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>

namespace kestrel::drivers::iio {
namespace fs = std::filesystem;

namespace {

void put(const fs::path& p, const std::string& v) {
  fs::create_directories(p.parent_path());
  std::ofstream f(p, std::ios::binary | std::ios::trunc);
  f << v << "\n";
  if (!f) throw std::runtime_error("fake iio: cannot write " + p.string());
}

std::string get(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  if (!f) return "";
  std::stringstream s;
  s << f.rdbuf();
  std::string v = s.str();
  while (!v.empty() && (v.back() == '\n' || v.back() == ' ')) v.pop_back();
  return v;
}

}  // namespace

FakeIioTree::FakeIioTree(const std::string& dir, std::vector<FakeDeviceSpec> specs)
    : dir_(dir),
      sysfs_root_(dir + "/sys/bus/iio/devices"),
      dev_root_(dir + "/dev"),
      specs_(std::move(specs)) {
  fs::create_directories(sysfs_root_);
  fs::create_directories(dev_root_);
  for (size_t i = 0; i < specs_.size(); ++i) {
    const FakeDeviceSpec& s = specs_[i];
    const fs::path d = device_dir(static_cast<int>(i));
    put(d / "name", s.name);
    if (s.has_buffer) {
      put(d / "buffer/enable", "0");
      put(d / "buffer/length", "2");
      put(d / "buffer/watermark", "1");
    }
    if (s.timestamp_clock_file) put(d / "current_timestamp_clock", s.timestamp_clock);
    if (!s.rate_attr.empty()) {
      put(d / s.rate_attr, s.rate_hz);
      if (!s.available_hz.empty()) put(d / (s.rate_attr + "_available"), s.available_hz);
    }
    int index = 0;
    auto element = [&](const std::string& n, const std::string& type, bool enabled) {
      put(d / "scan_elements" / (n + "_en"), enabled ? "1" : "0");
      put(d / "scan_elements" / (n + "_index"), std::to_string(index++));
      put(d / "scan_elements" / (n + "_type"), type);
    };
    auto part = [&](const char* type, const std::string& scan_type, const std::string& scale,
                    const std::string& offset) {
      for (const char* a : {"x", "y", "z"}) {
        element(std::string("in_") + type + "_" + a, scan_type, false);
        if (s.per_axis_scale && !scale.empty())
          put(d / (std::string("in_") + type + "_" + a + "_scale"), scale);
      }
      if (!s.per_axis_scale && !scale.empty()) put(d / (std::string("in_") + type + "_scale"), scale);
      if (!offset.empty()) put(d / (std::string("in_") + type + "_offset"), offset);
    };
    if (s.gyro_first && s.gyro) part("anglvel", s.gyro_type, s.gyro_scale, s.gyro_offset);
    if (s.accel) part("accel", s.accel_type, s.accel_scale, s.accel_offset);
    if (!s.gyro_first && s.gyro) part("anglvel", s.gyro_type, s.gyro_scale, s.gyro_offset);
    for (const std::string& e : s.extra_elements) element(e, "le:s16/16>>0", true);
    element("in_timestamp", s.timestamp_type, false);
    const std::string node = dev_root_ + "/iio:device" + std::to_string(i);
    if (::mkfifo(node.c_str(), 0600) != 0 && errno != EEXIST)
      throw std::runtime_error("fake iio: mkfifo " + node + ": " + std::strerror(errno));
  }
}

FakeIioTree::~FakeIioTree() { close_writers(); }

std::string FakeIioTree::device_dir(int i) const { return sysfs_root_ + "/iio:device" + std::to_string(i); }

std::string FakeIioTree::read(int i, const std::string& rel) const {
  return get(fs::path(device_dir(i)) / rel);
}

void FakeIioTree::write(int i, const std::string& rel, const std::string& value) const {
  put(fs::path(device_dir(i)) / rel, value);
}

void FakeIioTree::remove(int i, const std::string& rel) const {
  std::error_code ec;
  fs::remove(fs::path(device_dir(i)) / rel, ec);
}

FakeIioTree::Layout FakeIioTree::freeze(int i) const {
  // Straight from the kernel's rule, written out separately from the parser:
  // enabled elements by index, each at a multiple of its storage bytes, the
  // record a multiple of the largest.
  struct El {
    int index;
    Field f;
  };
  std::vector<El> els;
  const fs::path se = fs::path(device_dir(i)) / "scan_elements";
  for (const auto& e : fs::directory_iterator(se)) {
    const std::string n = e.path().filename().string();
    if (n.size() < 4 || n.substr(n.size() - 3) != "_en") continue;
    const std::string base = n.substr(0, n.size() - 3);
    if (get(se / n) != "1") continue;
    El el{};
    el.index = std::atoi(get(se / (base + "_index")).c_str());
    char endian[3] = {};
    char sign = 0;
    const std::string type = get(se / (base + "_type"));
    if (std::sscanf(type.c_str(), "%2[a-z]:%c%u/%u>>%u", endian, &sign, &el.f.real, &el.f.storage,
                    &el.f.shift) != 5)
      throw std::runtime_error("fake iio: cannot read " + type);
    el.f.be = std::string(endian) == "be";
    el.f.is_signed = sign == 's';
    static const char* kNames[7] = {"in_accel_x",   "in_accel_y",   "in_accel_z",  "in_anglvel_x",
                                    "in_anglvel_y", "in_anglvel_z", "in_timestamp"};
    for (int k = 0; k < 7; ++k)
      if (base == kNames[k]) el.f.kind = k;
    els.push_back(el);
  }
  std::sort(els.begin(), els.end(), [](const El& a, const El& b) { return a.index < b.index; });
  Layout l;
  size_t at = 0, largest = 1;
  for (El& e : els) {
    const size_t b = e.f.storage / 8;
    if (at % b) at += b - at % b;
    e.f.offset = at;
    at += b;
    largest = std::max(largest, b);
    l.fields.push_back(e.f);
  }
  if (at % largest) at += largest - at % largest;
  l.record_bytes = at;
  l.acc_scale = accel_scale(i);
  l.gyro_scale = gyro_scale(i);
  l.acc_offset = std::atof(read(i, "in_accel_offset").c_str());
  l.gyro_offset = std::atof(read(i, "in_anglvel_offset").c_str());
  return l;
}

void FakeIioTree::open_writers() {
  close_writers();
  for (size_t i = 0; i < specs_.size(); ++i) {
    const std::string node = dev_root_ + "/iio:device" + std::to_string(i);
    const int fd = ::open(node.c_str(), O_WRONLY | O_NONBLOCK | O_CLOEXEC);
    // ENXIO: no reader, the driver did not open this device (a test with fewer devices in use).
    fds_.push_back(fd);
    if (fd >= 0) (void)::fcntl(fd, F_SETPIPE_SZ, 1 << 20);
    layouts_.push_back(freeze(static_cast<int>(i)));
  }
}

void FakeIioTree::close_writers() {
  for (int fd : fds_)
    if (fd >= 0) ::close(fd);
  fds_.clear();
  layouts_.clear();
}

double FakeIioTree::accel_scale(int i) const {
  const FakeDeviceSpec& s = specs_.at(static_cast<size_t>(i));
  return std::atof((s.per_axis_scale ? read(i, "in_accel_x_scale") : read(i, "in_accel_scale")).c_str());
}

double FakeIioTree::gyro_scale(int i) const {
  const FakeDeviceSpec& s = specs_.at(static_cast<size_t>(i));
  return std::atof((s.per_axis_scale ? read(i, "in_anglvel_x_scale") : read(i, "in_anglvel_scale")).c_str());
}

size_t FakeIioTree::encode(int i, int64_t t_ns, const Vec3d& acc, const Vec3d& gyro, uint8_t* out,
                           size_t cap) const {
  const Layout& l = layouts_.at(static_cast<size_t>(i));
  if (cap < l.record_bytes) return 0;
  std::memset(out, 0, l.record_bytes);
  const double sa = l.acc_scale, sg = l.gyro_scale, oa = l.acc_offset, og = l.gyro_offset;
  for (const Field& f : l.fields) {
    uint64_t u = 0;
    if (f.kind == 6) {
      u = static_cast<uint64_t>(t_ns);
    } else {
      long double raw = 0;
      if (f.kind >= 0 && f.kind < 3) raw = std::llround(acc[static_cast<size_t>(f.kind)] / sa - oa);
      if (f.kind >= 3 && f.kind < 6) raw = std::llround(gyro[static_cast<size_t>(f.kind - 3)] / sg - og);
      const long double hi = f.is_signed ? std::ldexp(1.0L, static_cast<int>(f.real) - 1) - 1
                                         : std::ldexp(1.0L, static_cast<int>(f.real)) - 1;
      const long double lo = f.is_signed ? -std::ldexp(1.0L, static_cast<int>(f.real) - 1) : 0;
      raw = std::min(std::max(raw, lo), hi);
      const auto r = static_cast<int64_t>(raw);
      const uint64_t mask = f.real >= 64 ? ~uint64_t{0} : (uint64_t{1} << f.real) - 1;
      u = (static_cast<uint64_t>(r) & mask) << f.shift;
    }
    const size_t nb = f.storage / 8;
    for (size_t b = 0; b < nb; ++b) {
      const auto byte = static_cast<uint8_t>(u >> (8 * b));
      out[f.offset + (f.be ? nb - 1 - b : b)] = byte;
    }
  }
  return l.record_bytes;
}

size_t FakeIioTree::write_bytes(int i, const uint8_t* p, size_t n) {
  const int fd = fds_.at(static_cast<size_t>(i));
  if (fd < 0) return 0;
  size_t done = 0;
  while (done < n) {
    const ssize_t w = ::write(fd, p + done, n - done);
    if (w > 0) {
      done += static_cast<size_t>(w);
      continue;
    }
    if (w < 0 && errno == EINTR) continue;
    break;
  }
  return done;
}

}  // namespace kestrel::drivers::iio

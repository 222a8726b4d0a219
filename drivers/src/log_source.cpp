// open_log(): one entry point for every recorded format.
#include <cstring>
#include <fstream>
#include <stdexcept>

#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "text_log.hpp"

namespace kestrel::drivers {
namespace {

bool has_klog_magic(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  char m[4] = {};
  return f.read(m, 4) && std::memcmp(m, "KLOG", 4) == 0;
}

}  // namespace

LogFormat parse_log_format(const std::string& name) {
  if (name == "auto") return LogFormat::kAuto;
  if (name == "klog") return LogFormat::kKlog;
  if (name == "euroc") return LogFormat::kEuroc;
  if (name == "tum") return LogFormat::kTum;
  throw std::runtime_error("unknown log format \"" + name + "\" (expected auto, klog, euroc or tum)");
}

std::unique_ptr<LogSource> open_log(const std::string& path, LogFormat format) {
  switch (format) {
    case LogFormat::kKlog: return std::make_unique<KlogReader>(path);
    case LogFormat::kEuroc: return std::make_unique<EurocReader>(path);
    case LogFormat::kTum: return std::make_unique<TumReader>(path);
    case LogFormat::kAuto: break;
  }
  if (text::is_file(path)) {
    const bool ext = path.size() >= 5 && path.compare(path.size() - 5, 5, ".klog") == 0;
    if (ext || has_klog_magic(path)) return std::make_unique<KlogReader>(path);
    throw std::runtime_error(path + ": not a .klog file (no KLOG magic) and not a folder");
  }
  if (text::is_dir(path)) {
    if (is_euroc_folder(path)) return std::make_unique<EurocReader>(path);
    if (is_tum_folder(path)) return std::make_unique<TumReader>(path);
    throw std::runtime_error(path + ": unknown log folder (no mav0/, imu0/, imu0.csv or rgb.txt)");
  }
  throw std::runtime_error(path + ": no such file or folder");
}

}  // namespace kestrel::drivers

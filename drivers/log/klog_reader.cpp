// KlogReader: streaming, damage-tolerant reading of .klog files.
//
// Only the file header is trusted to fail loudly; after it every byte may be
// damaged, so each record is checked (sync, length cap, length vs file size,
// CRC) before anything is allocated or decoded from it.
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <stdexcept>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/klog_format.hpp"
#include "kestrel/drivers/rig_yaml.hpp"

namespace kestrel::drivers {
namespace {

constexpr size_t kWindowBytes = 64 * 1024;
constexpr uint8_t kSyncBytes[4] = {
    kestrel::drivers::klog::kSyncMarker & 0xffu, (kestrel::drivers::klog::kSyncMarker >> 8) & 0xffu,
    (kestrel::drivers::klog::kSyncMarker >> 16) & 0xffu, (kestrel::drivers::klog::kSyncMarker >> 24) & 0xffu};

bool pread_all(int fd, uint8_t* dst, size_t n, uint64_t offset) {
  while (n > 0) {
    const ssize_t got = ::pread(fd, dst, n, static_cast<off_t>(offset));
    if (got < 0 && errno == EINTR) continue;
    if (got <= 0) return false;
    dst += got;
    n -= static_cast<size_t>(got);
    offset += static_cast<uint64_t>(got);
  }
  return true;
}

}  // namespace

KlogReader::KlogReader(const std::string& path) : KlogReader(path, Options{}) {}

KlogReader::KlogReader(const std::string& path, const Options& options) : name_(path) {
  fd_ = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd_ < 0) throw std::runtime_error(path + ": cannot open klog: " + std::strerror(errno));
  struct stat st {};
  if (::fstat(fd_, &st) != 0 || !S_ISREG(st.st_mode)) {
    ::close(fd_);
    fd_ = -1;
    throw std::runtime_error(path + ": not a regular file");
  }
  size_ = static_cast<uint64_t>(st.st_size);
  try {
    open_header(options);
  } catch (...) {
    ::close(fd_);
    fd_ = -1;
    throw;
  }
}

KlogReader::KlogReader(std::string name, std::vector<uint8_t> memory, const Options& options)
    : name_(std::move(name)), memory_(std::move(memory)) {
  size_ = memory_.size();
  open_header(options);
}

std::unique_ptr<KlogReader> KlogReader::from_memory(const uint8_t* data, size_t size, const std::string& name,
                                                    const Options& options) {
  std::vector<uint8_t> copy(data, data + size);
  return std::unique_ptr<KlogReader>(new KlogReader(name, std::move(copy), options));
}

KlogReader::~KlogReader() {
  if (fd_ >= 0) ::close(fd_);
}

void KlogReader::open_header(const Options& options) {
  std::string why;
  uint32_t header_len = 0;
  uint32_t yaml_len = 0;
  std::vector<uint8_t> header;
  const size_t min_header = klog::kFileHeaderFixedBytes + klog::kFileHeaderCrcBytes;
  if (size_ < min_header) {
    why = "file is " + std::to_string(size_) + " bytes, shorter than a klog header";
  } else {
    uint8_t fixed[klog::kFileHeaderFixedBytes];
    if (!read_at(0, fixed, sizeof fixed)) throw std::runtime_error(name_ + ": cannot read the klog header");
    klog::ByteReader r(fixed, sizeof fixed);
    const uint8_t* magic = r.skip(4);
    version_ = r.u32();
    header_len = r.u32();
    yaml_len = r.u32();
    if (std::memcmp(magic, klog::kMagic, 4) != 0) {
      why = "not a klog file (the first 4 bytes are not \"KLOG\")";
    } else if (yaml_len > klog::kMaxRigYamlBytes || header_len < min_header + uint64_t{yaml_len} ||
               header_len > size_) {
      why = "header length " + std::to_string(header_len) + " / rig length " + std::to_string(yaml_len) +
            " inconsistent with a " + std::to_string(size_) + "-byte file";
    } else {
      header.resize(header_len);
      if (!read_at(0, header.data(), header_len))
        throw std::runtime_error(name_ + ": cannot read the klog header");
      klog::ByteReader c(header.data() + header_len - 4, 4);
      const uint32_t stored = c.u32();
      const auto actual = static_cast<uint32_t>(crc32(
          crc32(0L, Z_NULL, 0), header.data(), static_cast<uInt>(header_len - klog::kFileHeaderCrcBytes)));
      if (stored != actual) why = "file header CRC mismatch";
    }
  }
  if (why.empty() && (version_ == 0 || version_ > kKlogVersion)) {
    throw std::runtime_error(name_ + ": klog version " + std::to_string(version_) +
                             ", this build reads versions 1.." + std::to_string(kKlogVersion));
  }
  if (why.empty()) {
    const std::string yaml(reinterpret_cast<const char*>(header.data()) + klog::kFileHeaderFixedBytes,
                           yaml_len);
    try {
      rig_ = rig_from_yaml(yaml, name_ + " (rig in the klog header)");
    } catch (const std::exception& e) {
      why = std::string("rig in the header does not parse: ") + e.what();
    }
  }
  if (why.empty()) {
    data_start_ = header_len;
    pos_ = data_start_;
    shift_ = CameraTimeShift(rig_.time_offset_cam_imu_ns);
    return;
  }
  if (!options.salvage_bad_header) {
    throw std::runtime_error(name_ + ": damaged klog file header: " + why +
                             ". The rig is lost; the records can be recovered with salvage_bad_header.");
  }
  rig_ = Rig{};
  rig_.name = "unknown (damaged klog header)";
  version_ = kKlogVersion;
  RecordHeader h;
  data_start_ = resync(0, h);
  pos_ = data_start_;
  problem(0, "bad-header",
          why + "; using a default rig, records start at offset " + std::to_string(data_start_));
}

bool KlogReader::read_at(uint64_t offset, void* dst, size_t n) {
  if (offset > size_ || n > size_ - offset) return false;
  if (n == 0) return true;
  if (fd_ < 0) {
    std::memcpy(dst, memory_.data() + offset, n);
    return true;
  }
  if (n >= kWindowBytes / 2) return pread_all(fd_, static_cast<uint8_t*>(dst), n, offset);
  if (offset < window_offset_ || offset + n > window_offset_ + window_size_) {
    if (window_.size() < kWindowBytes) window_.resize(kWindowBytes);
    const size_t want = static_cast<size_t>(std::min<uint64_t>(kWindowBytes, size_ - offset));
    window_size_ = 0;
    if (!pread_all(fd_, window_.data(), want, offset)) return false;
    window_offset_ = offset;
    window_size_ = want;
  }
  std::memcpy(dst, window_.data() + (offset - window_offset_), n);
  return true;
}

bool KlogReader::read_header_at(uint64_t offset, RecordHeader& h) {
  uint8_t b[klog::kRecordHeaderBytes];
  if (!read_at(offset, b, sizeof b)) return false;
  klog::ByteReader r(b, sizeof b);
  h.sync = r.u32();
  h.type = r.u16();
  h.flags = r.u16();
  h.length = r.u32();
  h.crc = r.u32();
  return true;
}

bool KlogReader::load_payload(uint64_t offset, const RecordHeader& h) {
  // Never shrink: the buffer settles at the largest record and stays there.
  if (payload_.size() < h.length) payload_.resize(h.length);
  if (!read_at(offset + klog::kRecordHeaderBytes, payload_.data(), h.length)) return false;
  return klog::record_crc(h.type, h.flags, h.length, payload_.data()) == h.crc;
}

uint64_t KlogReader::resync(uint64_t from, RecordHeader& h) {
  std::vector<uint8_t> chunk(kWindowBytes);
  uint64_t at = from;
  while (at + klog::kRecordHeaderBytes <= size_) {
    const size_t n = static_cast<size_t>(std::min<uint64_t>(chunk.size(), size_ - at));
    if (!read_at(at, chunk.data(), n)) return size_;
    // Candidates whose header would run past the chunk are retried in the next one.
    const size_t last = n >= 4 ? n - 4 : 0;
    size_t i = 0;
    for (; i <= last && n >= 4; ++i) {
      const uint8_t* p =
          static_cast<const uint8_t*>(std::memchr(chunk.data() + i, kSyncBytes[0], last + 1 - i));
      if (!p) {
        i = last + 1;
        break;
      }
      i = static_cast<size_t>(p - chunk.data());
      if (std::memcmp(p, kSyncBytes, 4) != 0) continue;
      const uint64_t q = at + i;
      if (!read_header_at(q, h)) return size_;
      if (h.length <= klog::kMaxPayloadBytes && h.length <= size_ - q - klog::kRecordHeaderBytes &&
          load_payload(q, h))
        return q;
    }
    if (at + n >= size_) break;
    at += std::max<size_t>(i, 1);
  }
  return size_;
}

void KlogReader::problem(uint64_t offset, const char* kind, std::string detail) {
  // After rewind the same damage is met again; it is reported once.
  if (!problems_.empty() && offset < reported_until_) return;
  problems_.push_back(LogProblem{name_ + "@" + std::to_string(offset), kind, std::move(detail)});
  reported_until_ = offset + 1;
}

bool KlogReader::decode(uint64_t offset, const RecordHeader& h, LogRecord& out, std::string& why) {
  out.type = static_cast<RecordType>(h.type);
  out.offset = offset;
  const uint8_t* p = payload_.data();
  switch (out.type) {
    case RecordType::kImu:
      return klog::decode_imu(p, h.length, out.imu, why);
    case RecordType::kRgb:
    case RecordType::kDepth:
    case RecordType::kRight:
      return klog::decode_image(p, h.length, out.image, why, decoder_, version_);
    case RecordType::kGroundTruth:
      return klog::decode_ground_truth(p, h.length, out.gt, why);
    case RecordType::kEvent:
      return klog::decode_event(p, h.length, out.event, why);
  }
  why = "unknown record type";
  return false;
}

bool KlogReader::next(LogRecord& out) {
  if (shift_.offset_ns() == 0) return next_as_stored(out);
  for (;;) {
    if (shift_.pop(out, stored_done_)) return true;
    if (stored_done_) return false;
    if (next_as_stored(scratch_)) {
      shift_.push(std::move(scratch_));
    } else {
      stored_done_ = true;
    }
  }
}

bool KlogReader::next_as_stored(LogRecord& out) {
  for (;;) {
    const uint64_t at = pos_;
    RecordHeader h;
    if (pending_) {
      h = pending_header_;  // resync already checked it and left the payload in payload_
      pending_ = false;
    } else {
      if (at >= size_) return false;
      const char* kind = nullptr;
      std::string detail;
      bool past_end = false;
      const uint64_t left = size_ - at;
      if (left < klog::kRecordHeaderBytes) {
        kind = "truncated";
        detail = "file ends " + std::to_string(left) + " bytes into a record header";
      } else if (!read_header_at(at, h)) {
        problem(at, "io-error", std::strerror(errno));
        pos_ = size_;
        return false;
      } else if (h.sync != klog::kSyncMarker) {
        kind = "bad-sync";
        detail = "no record sync marker";
      } else if (h.length > klog::kMaxPayloadBytes) {
        kind = "bad-length";
        detail = "payload length " + std::to_string(h.length) + " exceeds the 64 MiB limit";
      } else if (h.length > left - klog::kRecordHeaderBytes) {
        past_end = true;
        detail = "payload length " + std::to_string(h.length) + " runs " +
                 std::to_string(h.length - (left - klog::kRecordHeaderBytes)) +
                 " bytes past the end of the file";
      } else if (!load_payload(at, h)) {
        kind = "bad-crc";
        detail = "record CRC mismatch (type " + std::to_string(h.type) + ", length " +
                 std::to_string(h.length) + ")";
      }
      if (kind || past_end) {
        RecordHeader nh;
        const uint64_t next_at = resync(at + 1, nh);
        // A length running past the end is a cut file unless intact records follow.
        if (past_end) kind = next_at >= size_ ? "truncated" : "bad-length";
        if (next_at >= size_) {
          detail += "; no intact record after it (" + std::to_string(size_ - at) + " bytes dropped)";
        } else {
          detail += "; skipped " + std::to_string(next_at - at) +
                    " bytes to the next intact record at offset " + std::to_string(next_at);
        }
        problem(at, kind, std::move(detail));
        pos_ = next_at;
        if (next_at < size_) {
          pending_ = true;
          pending_header_ = nh;
        }
        continue;
      }
    }
    pos_ = at + klog::kRecordHeaderBytes + h.length;
    if (!klog::is_known_record_type(h.type)) {
      problem(at, "bad-type",
              "record type " + std::to_string(h.type) + " unknown to this reader (klog version " +
                  std::to_string(kKlogVersion) + "); skipped");
      continue;
    }
    std::string why;
    if (!decode(at, h, out, why)) {
      problem(at, "bad-payload", why + "; skipped");
      continue;
    }
    return true;
  }
}

void KlogReader::rewind() {
  pos_ = data_start_;
  shift_.clear();
  stored_done_ = false;
  pending_ = false;
}

}  // namespace kestrel::drivers

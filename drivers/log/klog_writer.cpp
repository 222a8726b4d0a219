// KlogWriter: the append-only .klog file (layout in docs/log-format.md).
#include <unistd.h>
#include <zlib.h>

#include <cerrno>
#include <cstring>
#include <stdexcept>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/klog_format.hpp"
#include "kestrel/drivers/rig_yaml.hpp"

namespace kestrel::drivers {

KlogWriter::~KlogWriter() { close(); }

void KlogWriter::open(const std::string& path, const Rig& rig) { open(path, rig, Options{}); }

void KlogWriter::open(const std::string& path, const Rig& rig, const Options& options) {
  close();
  if (options.version < 1 || options.version > kKlogVersion)
    throw std::invalid_argument(path + ": cannot write klog version " + std::to_string(options.version));
  if (options.version < 2 && options.compression.codec != klog::ImageCodec::kRaw)
    throw std::invalid_argument(path + ": klog version 1 has no compressed images");
  const std::string yaml = rig_to_yaml(rig);
  if (yaml.size() > klog::kMaxRigYamlBytes)
    throw std::runtime_error(path + ": rig YAML too large for a klog header");
  std::FILE* f = std::fopen(path.c_str(), "wb");
  if (!f) throw std::runtime_error(path + ": cannot create klog: " + std::strerror(errno));

  std::string header;
  klog::ByteWriter w(header);
  w.bytes(klog::kMagic, 4);
  w.u32(options.version);
  w.u32(static_cast<uint32_t>(klog::kFileHeaderFixedBytes + yaml.size() + klog::kFileHeaderCrcBytes));
  w.u32(static_cast<uint32_t>(yaml.size()));
  w.bytes(yaml.data(), yaml.size());
  w.u32(static_cast<uint32_t>(crc32(crc32(0L, Z_NULL, 0), reinterpret_cast<const Bytef*>(header.data()),
                                    static_cast<uInt>(header.size()))));
  if (std::fwrite(header.data(), 1, header.size(), f) != header.size() || std::fflush(f) != 0) {
    const int err = errno;
    std::fclose(f);
    throw std::runtime_error(path + ": cannot write klog header: " + std::strerror(err));
  }
  file_ = f;
  path_ = path;
  records_ = 0;
  bytes_ = header.size();
  image_raw_ = 0;
  image_stored_ = 0;
  options_ = options;
  encoder_.set_compression(options.compression);
}

void KlogWriter::set_compression(const klog::ImageCompression& c) {
  if (options_.version < 2 && c.codec != klog::ImageCodec::kRaw)
    throw std::invalid_argument(path_ + ": klog version 1 has no compressed images");
  options_.compression = c;
  encoder_.set_compression(c);
}

void KlogWriter::close() {
  if (!file_) return;
  std::fflush(file_);
  if (fsync_every_ > 0) ::fsync(fileno(file_));
  std::fclose(file_);
  file_ = nullptr;
}

void KlogWriter::begin_record() {
  if (!file_) throw std::logic_error("KlogWriter: write on a closed writer");
  scratch_.clear();
  scratch_.resize(klog::kRecordHeaderBytes);
}

void KlogWriter::finish_record(RecordType type) {
  const size_t payload_size = scratch_.size() - klog::kRecordHeaderBytes;
  if (payload_size > klog::kMaxPayloadBytes) {
    throw std::invalid_argument(path_ + ": record of " + std::to_string(payload_size) +
                                " bytes exceeds the klog payload limit");
  }
  const auto* payload = reinterpret_cast<const uint8_t*>(scratch_.data()) + klog::kRecordHeaderBytes;
  const auto t = static_cast<uint16_t>(type);
  const auto len = static_cast<uint32_t>(payload_size);
  std::string h;
  h.reserve(klog::kRecordHeaderBytes);
  klog::ByteWriter w(h);
  w.u32(klog::kSyncMarker);
  w.u16(t);
  w.u16(0);
  w.u32(len);
  w.u32(klog::record_crc(t, 0, len, payload));
  std::memcpy(scratch_.data(), h.data(), klog::kRecordHeaderBytes);

  if (std::fwrite(scratch_.data(), 1, scratch_.size(), file_) != scratch_.size() || std::fflush(file_) != 0) {
    throw std::runtime_error(path_ + ": klog write failed after " + std::to_string(records_) +
                             " records: " + std::strerror(errno));
  }
  ++records_;
  bytes_ += scratch_.size();
  if (fsync_every_ > 0 && records_ % fsync_every_ == 0) ::fsync(fileno(file_));
}

void KlogWriter::write_record(RecordType type, const uint8_t* payload, uint32_t size) {
  begin_record();
  scratch_.append(reinterpret_cast<const char*>(payload), size);
  finish_record(type);
}

void KlogWriter::write_imu(const ImuSample& s) {
  begin_record();
  klog::encode_imu(s, scratch_);
  finish_record(RecordType::kImu);
}

void KlogWriter::write_image(RecordType type, const LogImage& img) {
  write_image(type, img.t_ns, img.t_recv_ns, img.seq, img.exposure_us, img.view());
}

void KlogWriter::write_image(RecordType type, int64_t t_ns, int64_t t_recv_ns, uint32_t seq,
                             int32_t exposure_us, const ImageView& view) {
  if (type != RecordType::kRgb && type != RecordType::kDepth && type != RecordType::kRight)
    throw std::invalid_argument("KlogWriter::write_image: type must be kRgb, kDepth or kRight");
  const int bpp = bytes_per_pixel(view.format);
  if (bpp == 0 || view.width < 0 || view.height < 0 ||
      static_cast<uint32_t>(view.width) > klog::kMaxImageSide ||
      static_cast<uint32_t>(view.height) > klog::kMaxImageSide) {
    throw std::invalid_argument(path_ + ": bad image " + std::to_string(view.width) + "x" +
                                std::to_string(view.height));
  }
  const size_t row = static_cast<size_t>(view.width) * static_cast<size_t>(bpp);
  if (view.height > 0 && (!view.data || static_cast<size_t>(view.stride_bytes) < row))
    throw std::invalid_argument(path_ + ": image view without data or with stride < width * bpp");
  begin_record();
  klog::encode_image_header(t_ns, t_recv_ns, seq, exposure_us, view.width, view.height, view.format,
                            scratch_);
  const size_t pixels_at = scratch_.size();
  klog::ImageCodec codec = klog::ImageCodec::kRaw;
  klog::ImageFilter filter = klog::ImageFilter::kNone;
  // Packed rows (or their compressed form): the stride is a property of the
  // producer's buffer, not of the image.
  encoder_.encode(view, scratch_, codec, filter);
  const size_t image_at = klog::kRecordHeaderBytes;
  scratch_[image_at + klog::kImageCodecByte] = static_cast<char>(codec);
  scratch_[image_at + klog::kImageFilterByte] = static_cast<char>(filter);
  image_raw_ += row * static_cast<size_t>(view.height);
  image_stored_ += scratch_.size() - pixels_at;
  finish_record(type);
}

void KlogWriter::write_ground_truth(const GroundTruthPose& gt) {
  begin_record();
  klog::encode_ground_truth(gt, scratch_);
  finish_record(RecordType::kGroundTruth);
}

void KlogWriter::write_event(const Event& e) {
  begin_record();
  klog::encode_event(e, scratch_);
  finish_record(RecordType::kEvent);
}

}  // namespace kestrel::drivers

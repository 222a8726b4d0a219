#include "kestrel/recording.hpp"

#include <cstdio>

#include "kestrel/commands.hpp"

namespace kestrel::cli {

std::unique_ptr<drivers::KlogLogger> make_recording_logger(const drivers::LiveConfig& cfg,
                                                           const std::string& path, double buffer_s,
                                                           uint32_t fsync_every) {
  drivers::KlogLogger::Options lo;
  const size_t pixels = static_cast<size_t>(cfg.drivers.camera.width_px) * cfg.drivers.camera.height_px;
  lo.max_image_bytes = pixels * 3;
  // Colour up to 3 bytes a pixel, depth 2.
  lo.buffer_bytes =
      drivers::KlogLogger::staging_bytes_for(buffer_s, cfg.drivers.camera.rate_hz, pixels * 3, pixels * 2);
  lo.fsync_every = fsync_every;
  lo.thread = cfg.threads[drivers::PipelineThread::kLog];
  lo.compression = cfg.record.compression;
  return std::make_unique<drivers::KlogLogger>(path, cfg.rig, lo);
}

void add_image_compression_options(CLI::App* app, ImageCompressionArgs& a) {
  app->add_option("--image-codec", a.codec,
                  "image compression in the .klog: zstd, lz4 or none (docs/log-format.md)")
      ->capture_default_str();
  app->add_option("--zstd-level", a.zstd_level, "zstd level (negative = faster, larger)")
      ->capture_default_str();
}

drivers::klog::ImageCompression image_compression_from(const ImageCompressionArgs& a) {
  drivers::klog::ImageCompression c;
  if (!drivers::klog::parse_codec(a.codec, c.codec))
    throw UsageError("--image-codec: expected zstd, lz4 or none, got '" + a.codec + "'");
  if (a.zstd_level < drivers::klog::zstd_min_level() || a.zstd_level > drivers::klog::zstd_max_level()) {
    throw UsageError("--zstd-level: expected " + std::to_string(drivers::klog::zstd_min_level()) + ".." +
                     std::to_string(drivers::klog::zstd_max_level()));
  }
  c.zstd_level = a.zstd_level;
  return c;
}

std::string recording_summary(const drivers::KlogLogger& logger) {
  const auto st = logger.stats();
  char buf[768];
  std::snprintf(
      buf, sizeof buf,
      "log: %llu records, %.1f MB, drops: imu %llu, images %llu, events %llu; image staging peak %.1f of "
      "%.1f MB; images %.1f MB -> %.1f MB (%s), logger CPU %.1f s\n",
      (unsigned long long)st.records_written, st.bytes_written / 1e6, (unsigned long long)st.imu_drops,
      (unsigned long long)st.image_drops, (unsigned long long)st.event_drops, st.staging_peak_bytes / 1e6,
      st.staging_bytes / 1e6, st.image_bytes_raw / 1e6, st.image_bytes_stored / 1e6,
      drivers::klog::describe(logger.compression()).c_str(), st.thread_cpu_ns * 1e-9);
  return buf;
}

}  // namespace kestrel::cli

#include "kestrel/recording.hpp"

#include <cstdio>

namespace kestrel::cli {

std::unique_ptr<drivers::KlogLogger> make_recording_logger(const drivers::LiveConfig& cfg, const std::string& path,
                                                           double buffer_s, uint32_t fsync_every) {
  drivers::KlogLogger::Options lo;
  const size_t pixels = static_cast<size_t>(cfg.drivers.camera.width_px) * cfg.drivers.camera.height_px;
  lo.max_image_bytes = pixels * 3;
  // Colour up to 3 bytes a pixel, depth 2.
  lo.buffer_bytes = drivers::KlogLogger::staging_bytes_for(buffer_s, cfg.drivers.camera.rate_hz, pixels * 3, pixels * 2);
  lo.fsync_every = fsync_every;
  lo.thread = cfg.threads[drivers::PipelineThread::kLog];
  return std::make_unique<drivers::KlogLogger>(path, cfg.rig, lo);
}

std::string recording_summary(const drivers::KlogLogger& logger) {
  const auto st = logger.stats();
  char buf[512];
  std::snprintf(buf, sizeof buf,
                "log: %llu records, %.1f MB, drops: imu %llu, images %llu, events %llu; image staging peak %.1f of "
                "%.1f MB\n",
                (unsigned long long)st.records_written, st.bytes_written / 1e6, (unsigned long long)st.imu_drops,
                (unsigned long long)st.image_drops, (unsigned long long)st.event_drops, st.staging_peak_bytes / 1e6,
                st.staging_bytes / 1e6);
  return buf;
}

}  // namespace kestrel::cli

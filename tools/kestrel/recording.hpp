// Recording live sensors into a .klog: the sinks the drivers push into and
// the logger behind them, shared by `kestrel record` and `kestrel run
// --record`. The drivers' threads only copy into the logger's preallocated
// rings (no allocation, no blocking); its own thread writes the file. Frames
// are recorded with the stamps the driver gave them, beside the rig that says
// the camera-IMU offset (readers apply it, docs/frames.md).
#pragma once

#include <CLI/CLI.hpp>
#include <memory>
#include <string>

#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/klog_logger.hpp"

namespace kestrel::cli {

class LoggerImuSink final : public drivers::ImuSink {
 public:
  explicit LoggerImuSink(drivers::KlogLogger& l) : log_(l) {}
  bool push(const ImuSample& s) noexcept override { return log_.log_imu(s); }
  void event(int64_t t, EventCode c, const char* text) noexcept override { (void)log_.log_event(t, c, text); }

 private:
  drivers::KlogLogger& log_;
};

class LoggerFrameSink final : public drivers::FrameSink {
 public:
  explicit LoggerFrameSink(drivers::KlogLogger& l) : log_(l) {}
  bool push_frame(const drivers::CameraFrame& f) noexcept override {
    bool ok =
        log_.log_image(drivers::RecordType::kRgb, f.t_ns, f.t_recv_ns, f.seq, f.exposure_us, f.rgb->view());
    if (f.depth != nullptr) {
      ok = log_.log_image(drivers::RecordType::kDepth, f.t_ns, f.t_recv_ns, f.seq, f.exposure_us,
                          f.depth->view()) &&
           ok;
    }
    if (f.right != nullptr) {
      ok = log_.log_image(drivers::RecordType::kRight, f.t_ns, f.t_recv_ns, f.seq, f.exposure_us,
                          f.right->view()) &&
           ok;
    }
    return ok;
  }

 private:
  drivers::KlogLogger& log_;
};

// Every sample to two sinks (the estimator's rings and the recorder): the
// first one's verdict is the driver's, the recorder counts its own drops.
class TeeImuSink final : public drivers::ImuSink {
 public:
  TeeImuSink(drivers::ImuSink& a, drivers::ImuSink& b) : a_(a), b_(b) {}
  bool push(const ImuSample& s) noexcept override {
    (void)b_.push(s);
    return a_.push(s);
  }
  void event(int64_t t, EventCode c, const char* text) noexcept override {
    a_.event(t, c, text);
    b_.event(t, c, text);
  }

 private:
  drivers::ImuSink& a_;
  drivers::ImuSink& b_;
};

class TeeFrameSink final : public drivers::FrameSink {
 public:
  TeeFrameSink(drivers::FrameSink& a, drivers::FrameSink& b) : a_(a), b_(b) {}
  bool push_frame(const drivers::CameraFrame& f) noexcept override {
    (void)b_.push_frame(f);
    return a_.push_frame(f);
  }

 private:
  drivers::FrameSink& a_;
  drivers::FrameSink& b_;
};

// The logger for a live config: image sizes from its camera, a staging buffer
// holding buffer_s seconds of frames, its thread from the config's table.
std::unique_ptr<drivers::KlogLogger> make_recording_logger(const drivers::LiveConfig& cfg,
                                                           const std::string& path, double buffer_s,
                                                           uint32_t fsync_every);

// `--image-codec` and `--zstd-level` for the offline .klog writers (`kestrel
// sim`, `kestrel convert`); their defaults are the config's `record:` ones.
struct ImageCompressionArgs {
  std::string codec = drivers::klog::codec_name(drivers::default_image_compression().codec);
  int zstd_level = drivers::default_image_compression().zstd_level;
};
void add_image_compression_options(CLI::App* app, ImageCompressionArgs& a);
// Throws UsageError naming the option when a value is out of range.
drivers::klog::ImageCompression image_compression_from(const ImageCompressionArgs& a);

// "log: N records, X MB, drops: ...": the logger's end-of-run line.
std::string recording_summary(const drivers::KlogLogger& logger);

}  // namespace kestrel::cli

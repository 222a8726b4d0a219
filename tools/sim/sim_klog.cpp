// The .klog sink: run_simulation straight into a KlogWriter.
#include <filesystem>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/tools/simulator.hpp"

namespace kestrel::tools {
namespace {

class KlogSink final : public SimSink {
 public:
  KlogSink(std::string path, const drivers::klog::ImageCompression& c) : path_(std::move(path)) {
    options_.compression = c;
  }
  void begin(const Rig& rig) override { writer_.open(path_, rig, options_); }
  void imu(const ImuSample& s) override { writer_.write_imu(s); }
  void image(drivers::RecordType type, int64_t t_ns, uint32_t seq, const ImageView& view) override {
    writer_.write_image(type, t_ns, t_ns, seq, 0, view);
  }
  void ground_truth(const GroundTruthPose& gt) override { writer_.write_ground_truth(gt); }
  void event(const Event& e) override { writer_.write_event(e); }
  void end() override {
    bytes_ = writer_.bytes_written();
    writer_.close();
    std::error_code ec;
    const auto size = std::filesystem::file_size(path_, ec);
    if (!ec) bytes_ = size;
  }
  uint64_t bytes() const override { return bytes_; }

 private:
  std::string path_;
  drivers::KlogWriter::Options options_;
  drivers::KlogWriter writer_;
  uint64_t bytes_ = 0;
};

}  // namespace

SimSummary run_simulation(const SimOptions& options) {
  if (options.out_path.empty()) throw SimOptionError("--out is required");
  KlogSink sink(options.out_path, options.image_compression);
  return run_simulation(options, sink);
}

}  // namespace kestrel::tools

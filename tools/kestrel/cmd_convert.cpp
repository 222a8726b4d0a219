// `kestrel convert IN --out OUT`: any log Kestrel reads, written as a .klog
// (default) or exported to a dataset layout (--to eth3d|openloris|euroc|rosbag).
#include <cstdio>
#include <fstream>
#include <iostream>
#include <memory>
#include <string>

#include "kestrel/commands.hpp"
#include "kestrel/drivers/camera_time_shift.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_export.hpp"
#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/drivers/rosbag2.hpp"
#include "kestrel/recording.hpp"

namespace kestrel::cli {
namespace {

struct ConvertArgs {
  std::string in;
  std::string out;
  std::string format = "auto";
  std::string to;
  std::string rig_path;
  std::string rig_out;
  drivers::LogOpenOptions open;
  bool quiet = false;
  ImageCompressionArgs compression;
  std::string mcap_compression = "zstd";
  size_t mcap_chunk_bytes = 4u << 20;
};

bool ends_with(const std::string& s, const std::string& e) {
  return s.size() >= e.size() && s.compare(s.size() - e.size(), e.size(), e) == 0;
}

drivers::ExportStats write_klog(drivers::LogSource& src, const std::string& path,
                                const drivers::klog::ImageCompression& compression) {
  drivers::KlogWriter w;
  drivers::KlogWriter::Options wo;
  wo.compression = compression;
  // The reader put the camera stamps on the IMU's clock: the copy has no offset left.
  w.open(path, drivers::rig_for_shifted_records(src.rig()), wo);
  drivers::ExportStats st;
  drivers::LogRecord r;
  src.rewind();
  while (src.next(r)) {
    switch (r.type) {
      case drivers::RecordType::kImu:
        w.write_imu(r.imu), ++st.imu;
        break;
      case drivers::RecordType::kRgb:
        w.write_image(r.type, r.image), ++st.rgb;
        break;
      case drivers::RecordType::kDepth:
        w.write_image(r.type, r.image), ++st.depth;
        break;
      case drivers::RecordType::kRight:
        w.write_image(r.type, r.image);
        break;
      case drivers::RecordType::kGroundTruth:
        w.write_ground_truth(r.gt), ++st.ground_truth;
        break;
      case drivers::RecordType::kEvent:
        w.write_event(r.event), ++st.events;
        break;
    }
  }
  w.close();
  return st;
}

int run_convert(const ConvertArgs& a) {
  drivers::LogOpenOptions o = a.open;
  try {
    o.format = drivers::parse_log_format(a.format);
  } catch (const std::exception& e) {
    throw UsageError(e.what());
  }
  o.rig_path = a.rig_path;
  std::string to = a.to;
  if (to.empty()) {
    if (ends_with(a.out, ".klog")) {
      to = "klog";
    } else if (ends_with(a.out, ".bag")) {
      to = "rosbag";
    } else {
      throw UsageError("--out " + a.out +
                       ": say the output format with --to (klog, eth3d, openloris, euroc, rosbag)");
    }
  }
  if (to != "klog" && to != "eth3d" && to != "openloris" && to != "euroc" && to != "rosbag" &&
      to != "rosbag2")
    throw UsageError("unknown --to '" + to + "' (expected klog, eth3d, openloris, euroc, rosbag or rosbag2)");
  if (to == "rosbag2" && a.mcap_compression != "zstd" && a.mcap_compression != "lz4" &&
      a.mcap_compression != "none")
    throw UsageError("--mcap-compression " + a.mcap_compression + " (expected zstd, lz4 or none)");
  if (to == "rosbag" && !drivers::rosbag_built()) {
    throw std::runtime_error(
        "ROS bag support not built (tools/install-deps.sh installs librosbag-dev; reconfigure)");
  }

  std::unique_ptr<drivers::LogSource> src = drivers::open_log(a.in, o);
  const bool rig_used = o.format == drivers::LogFormat::kEth3d ||
                        o.format == drivers::LogFormat::kOpenLoris ||
                        o.format == drivers::LogFormat::kRosbag || o.format == drivers::LogFormat::kRosbag2 ||
                        o.format == drivers::LogFormat::kSevenScenes ||
                        (o.format == drivers::LogFormat::kAuto &&
                         (src->format_name() == "eth3d" || src->format_name() == "openloris" ||
                          src->format_name() == "rosbag" || src->format_name() == "rosbag2" ||
                          src->format_name() == "7scenes"));
  if (!a.rig_path.empty() && !rig_used) {
    std::fprintf(stderr, "kestrel convert: warning: --rig is ignored for %s input (it carries its own rig)\n",
                 src->format_name().c_str());
  }

  drivers::ExportStats st;
  if (to == "klog") {
    st = write_klog(*src, a.out, image_compression_from(a.compression));
  } else if (to == "eth3d") {
    st = drivers::export_eth3d(*src, a.out);
  } else if (to == "openloris") {
    st = drivers::export_openloris(*src, a.out);
  } else if (to == "euroc") {
    st = drivers::export_euroc(*src, a.out);
  } else if (to == "rosbag2") {
    drivers::Rosbag2WriteOptions w;
    if (!o.rgb_topic.empty()) w.topics.rgb = o.rgb_topic;
    if (!o.depth_topic.empty()) w.topics.depth = o.depth_topic;
    if (!o.imu_topic.empty()) w.topics.imu = o.imu_topic;
    if (!o.camera_info_topic.empty()) w.topics.camera_info = o.camera_info_topic;
    if (!o.ground_truth_topic.empty()) w.topics.ground_truth = o.ground_truth_topic;
    w.mcap.compression = a.mcap_compression == "none" ? "" : a.mcap_compression;
    w.mcap.chunk_size_bytes = a.mcap_chunk_bytes;
    const drivers::Rosbag2Stats r = drivers::export_rosbag2(*src, a.out, w);
    st.imu = r.imu, st.rgb = r.rgb, st.depth = r.depth, st.ground_truth = r.ground_truth;
  } else {
    drivers::RosbagTopics t;
    if (!o.rgb_topic.empty()) t.rgb = o.rgb_topic;
    if (!o.depth_topic.empty()) t.depth = o.depth_topic;
    if (!o.imu_topic.empty()) t.imu = o.imu_topic;
    if (!o.camera_info_topic.empty()) t.camera_info = o.camera_info_topic;
    if (!o.ground_truth_topic.empty()) t.ground_truth = o.ground_truth_topic;
    st = drivers::export_rosbag(*src, a.out, t);
  }
  if (!a.rig_out.empty()) {
    std::ofstream f(a.rig_out);
    if (!(f << drivers::rig_to_yaml(drivers::rig_for_shifted_records(src->rig()))))
      throw std::runtime_error(a.rig_out + ": cannot write the rig");
  }
  size_t skipped = 0;
  for (const auto& p : src->problems()) {
    if (!a.quiet) std::cerr << "problem: " << p.where << ": " << p.kind << ": " << p.detail << "\n";
    ++skipped;
  }
  if (!a.quiet) {
    std::printf(
        "kestrel convert: %s (%s) -> %s (%s): %zu IMU, %zu RGB, %zu depth, %zu ground truth, %zu events; "
        "%zu problems\n",
        a.in.c_str(), src->format_name().c_str(), a.out.c_str(), to.c_str(), st.imu, st.rgb, st.depth,
        st.ground_truth, st.events, skipped);
  }
  return 0;
}

}  // namespace

Subcommand add_convert_command(CLI::App& parent) {
  auto a = std::make_shared<ConvertArgs>();
  CLI::App* app =
      parent.add_subcommand("convert", "convert a recording to .klog (or export a log to a dataset layout)");
  app->footer(
      "Examples:\n"
      "  kestrel convert ~/eth3d/sofa_1 --out sofa_1.klog\n"
      "  kestrel convert d435i.bag --out d435i.klog --rig configs/my_d435i.yaml\n"
      "  kestrel convert sim.klog --to eth3d --out sim_eth3d/ --rig-out sim_rig.yaml\n"
      "  kestrel convert sim.klog --to rosbag2 --out sim_ros2/   (ros2 bag play sim_ros2)\n"
      "Formats, columns, units and frames: docs/datasets.md");
  app->add_option("input", a->in, "a .klog, ROS bag, or EuRoC / TUM / ETH3D / OpenLORIS / 7-Scenes folder")
      ->required();
  app->add_option("--out", a->out, "output: OUT.klog (default), OUT.bag, or a folder with --to")->required();
  app->add_option("--format", a->format, std::string("input format: ") + drivers::log_format_names())
      ->capture_default_str();
  app->add_option("--to", a->to,
                  "output format: klog, eth3d, openloris, euroc, rosbag, rosbag2 (default: from --out)");
  app->add_option("--mcap-compression", a->mcap_compression,
                  "rosbag2: MCAP chunk compression (zstd, lz4, none)")
      ->capture_default_str();
  app->add_option("--mcap-chunk-bytes", a->mcap_chunk_bytes,
                  "rosbag2: uncompressed bytes per MCAP chunk (0 = unchunked)")
      ->capture_default_str();
  app->add_option("--rig", a->rig_path,
                  "rig YAML for calibration the dataset lacks (ETH3D, OpenLORIS, 7-Scenes, rosbag)");
  app->add_option("--rig-out", a->rig_out, "also write the resulting rig as YAML here");
  app->add_option("--fps", a->open.fps,
                  "7-Scenes: the frame rate its time stamps are made from (frame i at i / fps)")
      ->capture_default_str();
  app->add_option("--rgb-topic", a->open.rgb_topic,
                  "rosbag / rosbag2 colour topic (default /camera/color/image_raw)");
  app->add_option("--depth-topic", a->open.depth_topic,
                  "rosbag depth topic (default /camera/aligned_depth_to_color/image_raw)");
  app->add_option("--imu-topic", a->open.imu_topic, "rosbag IMU topic (default /camera/imu)");
  app->add_option("--camera-info-topic", a->open.camera_info_topic,
                  "rosbag CameraInfo topic (default: beside the colour topic)");
  app->add_option(
         "--topics", a->open.topics,
         "rosbag2: read only these topics (comma-separated), detected by type among them (docs/ros2.md)")
      ->delimiter(',');
  app->add_option("--gt-topic", a->open.ground_truth_topic,
                  "rosbag ground truth, geometry_msgs/PoseStamped (default /kestrel/ground_truth)");
  add_image_compression_options(app, a->compression);
  app->add_flag("-q,--quiet", a->quiet, "print nothing but errors");
  Subcommand cmd;
  cmd.app = app;
  cmd.run = [a]() { return run_convert(*a); };
  return cmd;
}

}  // namespace kestrel::cli

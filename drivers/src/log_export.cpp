#include "kestrel/drivers/log_export.hpp"

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>

#include "kestrel/drivers/rig_yaml.hpp"
#include "text_log.hpp"

namespace kestrel::drivers {
namespace {

class OutFile {
 public:
  explicit OutFile(std::string path) : path_(std::move(path)), f_(std::fopen(path_.c_str(), "w")) {
    if (!f_) throw std::runtime_error(path_ + ": cannot create: " + std::strerror(errno));
  }
  ~OutFile() {
    if (f_) std::fclose(f_);
  }
  OutFile(const OutFile&) = delete;
  OutFile& operator=(const OutFile&) = delete;
  void put(const std::string& s) {
    if (std::fwrite(s.data(), 1, s.size(), f_) != s.size())
      throw std::runtime_error(path_ + ": write failed: " + std::strerror(errno));
  }
  void close() {
    std::FILE* f = f_;
    f_ = nullptr;
    if (std::fclose(f) != 0) throw std::runtime_error(path_ + ": write failed: " + std::strerror(errno));
  }

 private:
  std::string path_;
  std::FILE* f_;
};

void mkdirs(const std::string& dir) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) throw std::runtime_error(dir + ": cannot create folder: " + ec.message());
}

std::string matrix_yaml(const Mat4d& m) {
  std::string s = "T_BS:\n  cols: 4\n  rows: 4\n  data: [";
  for (int i = 0; i < 16; ++i) s += (i == 0 ? "" : (i % 4 == 0 ? ",\n         " : ", ")) + text::fmt17(m[i]);
  return s + "]\n";
}

std::string camera_sensor_yaml(const Rig& r, const char* comment) {
  const auto& c = r.rgb;
  std::string s = "%YAML:1.0\nsensor_type: camera\ncomment: " + std::string(comment) + "\n\n" + matrix_yaml(r.T_BC);
  s += "\nrate_hz: " + text::fmt17(r.camera_rate_hz) + "\n";
  s += "resolution: [" + std::to_string(c.width) + ", " + std::to_string(c.height) + "]\n";
  s += "camera_model: pinhole\n";
  s += "intrinsics: [" + text::fmt17(c.fx) + ", " + text::fmt17(c.fy) + ", " + text::fmt17(c.cx) + ", " +
       text::fmt17(c.cy) + "] #fu, fv, cu, cv\n";
  const char* model = c.distortion == DistortionModel::kRadTan        ? "radial-tangential"
                      : c.distortion == DistortionModel::kEquidistant ? "equidistant"
                                                                      : "none";
  // ASL files list 4 radtan coefficients; k3 is written only when it is used.
  const size_t n = c.distortion == DistortionModel::kRadTan && c.dist[4] != 0 ? 5 : 4;
  s += "distortion_model: " + std::string(model) + "\ndistortion_coefficients: [";
  for (size_t i = 0; i < n; ++i) s += (i ? ", " : "") + text::fmt17(c.dist[i]);
  return s + "]\n";
}

std::string imu_sensor_yaml(const Rig& r) {
  std::string s = "%YAML:1.0\nsensor_type: imu\ncomment: exported by Kestrel\n\n" + matrix_yaml(r.T_BI);
  s += "rate_hz: " + text::fmt17(r.imu_rate_hz) + "\n\n";
  s += "gyroscope_noise_density: " + text::fmt17(r.imu.gyro_noise_density_rad_s_sqrthz) + "     # [ rad / s / sqrt(Hz) ]\n";
  s += "gyroscope_random_walk: " + text::fmt17(r.imu.gyro_random_walk_rad_s2_sqrthz) + "       # [ rad / s^2 / sqrt(Hz) ]\n";
  s += "accelerometer_noise_density: " + text::fmt17(r.imu.acc_noise_density_mps2_sqrthz) + "  # [ m / s^2 / sqrt(Hz) ]\n";
  s += "accelerometer_random_walk: " + text::fmt17(r.imu.acc_random_walk_mps3_sqrthz) + "    # [ m / s^3 / sqrt(Hz) ]\n";
  return s;
}

cv::Mat to_writable(const LogImage& img) {
  // LogImage pixels are packed, so a Mat header over them needs no copy.
  auto* data = const_cast<uint8_t*>(img.pixels.data());
  switch (img.format) {
    case PixelFormat::kGray8: return cv::Mat(img.height, img.width, CV_8UC1, data);
    case PixelFormat::kBgr8: return cv::Mat(img.height, img.width, CV_8UC3, data);
    case PixelFormat::kDepthU16: return cv::Mat(img.height, img.width, CV_16UC1, data);
    case PixelFormat::kRgb8: {
      cv::Mat bgr;
      cv::cvtColor(cv::Mat(img.height, img.width, CV_8UC3, data), bgr, cv::COLOR_RGB2BGR);
      return bgr;
    }
    case PixelFormat::kYuyv: {
      cv::Mat bgr;
      cv::cvtColor(cv::Mat(img.height, img.width, CV_8UC2, data), bgr, cv::COLOR_YUV2BGR_YUYV);
      return bgr;
    }
  }
  return {};
}

}  // namespace

ExportStats export_euroc(LogSource& src, const std::string& out_dir) {
  const std::string mav = out_dir + "/mav0";
  mkdirs(mav + "/imu0");
  mkdirs(mav + "/cam0/data");
  const Rig& rig = src.rig();
  {
    OutFile f(mav + "/kestrel_rig.yaml");
    f.put(rig_to_yaml(rig));
    f.close();
  }
  {
    OutFile f(mav + "/cam0/sensor.yaml");
    f.put(camera_sensor_yaml(rig, "colour camera, exported by Kestrel"));
    f.close();
  }
  {
    OutFile f(mav + "/imu0/sensor.yaml");
    f.put(imu_sensor_yaml(rig));
    f.close();
  }
  OutFile imu(mav + "/imu0/data.csv");
  imu.put("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],"
          "a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n");
  OutFile cam(mav + "/cam0/data.csv");
  cam.put("#timestamp [ns],filename\n");
  std::unique_ptr<OutFile> depth, gt, events;
  ExportStats st;
  int64_t last_rgb_t = 0, last_depth_t = 0;
  int dup = 0;

  src.rewind();
  LogRecord r;
  while (src.next(r)) {
    switch (r.type) {
      case RecordType::kImu: {
        const auto& m = r.imu;
        std::string row = std::to_string(m.t_ns);
        for (double v : m.gyro_rps) row += "," + text::fmt17(v);
        for (double v : m.acc_mps2) row += "," + text::fmt17(v);
        imu.put(row + "\n");
        ++st.imu;
        break;
      }
      case RecordType::kRgb:
      case RecordType::kDepth: {
        const bool is_rgb = r.type == RecordType::kRgb;
        if (!is_rgb && !depth) {
          mkdirs(mav + "/depth0/data");
          OutFile y(mav + "/depth0/sensor.yaml");
          y.put(camera_sensor_yaml(rig, "depth registered to the colour camera (cam0), 16-bit PNG; metres = value * "
                                        "scale_m_per_unit in kestrel_rig.yaml") +
                "scale_m_per_unit: " + text::fmt17(rig.depth.scale_m_per_unit) + "\n");
          y.close();
          depth = std::make_unique<OutFile>(mav + "/depth0/data.csv");
          depth->put("#timestamp [ns],filename\n");
        }
        int64_t& last = is_rgb ? last_rgb_t : last_depth_t;
        // Two frames with one stamp would overwrite each other's file.
        std::string name = std::to_string(r.image.t_ns);
        if ((is_rgb ? st.rgb : st.depth) > 0 && r.image.t_ns == last) name += "_" + std::to_string(++dup);
        name += ".png";
        last = r.image.t_ns;
        const std::string file = mav + (is_rgb ? "/cam0/data/" : "/depth0/data/") + name;
        const cv::Mat m = to_writable(r.image);
        if (m.empty() || !cv::imwrite(file, m)) throw std::runtime_error(file + ": cannot write PNG");
        (is_rgb ? cam : *depth).put(std::to_string(r.image.t_ns) + "," + name + "\n");
        ++(is_rgb ? st.rgb : st.depth);
        break;
      }
      case RecordType::kGroundTruth: {
        if (!gt) {
          mkdirs(mav + "/state_groundtruth_estimate0");
          gt = std::make_unique<OutFile>(mav + "/state_groundtruth_estimate0/data.csv");
          gt->put("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z [],"
                  "v_RS_R_x [m s^-1],v_RS_R_y [m s^-1],v_RS_R_z [m s^-1]\n");
        }
        const auto& g = r.gt;
        std::string row = std::to_string(g.t_ns);
        for (double v : g.p_WB) row += "," + text::fmt17(v);
        for (double v : g.q_WB) row += "," + text::fmt17(v);
        // Rows without velocity stop after the quaternion; the reader takes 8 or 11 columns.
        if (g.has_velocity)
          for (double v : g.v_WB) row += "," + text::fmt17(v);
        gt->put(row + "\n");
        ++st.ground_truth;
        break;
      }
      case RecordType::kEvent: {
        if (!events) {
          events = std::make_unique<OutFile>(mav + "/kestrel_events.csv");
          events->put("#timestamp [ns],code,text\n");
        }
        std::string t = r.event.text;
        for (char& c : t)
          if (c == '\n' || c == '\r') c = ' ';
        events->put(std::to_string(r.event.t_ns) + "," + std::to_string(static_cast<uint32_t>(r.event.code)) + "," +
                    t + "\n");
        ++st.events;
        break;
      }
    }
  }
  imu.close();
  cam.close();
  if (depth) depth->close();
  if (gt) gt->close();
  if (events) events->close();
  return st;
}

size_t export_tum_groundtruth(LogSource& src, const std::string& path) {
  OutFile f(path);
  f.put("# ground truth trajectory, exported by Kestrel\n# timestamp tx ty tz qx qy qz qw\n");
  size_t n = 0;
  src.rewind();
  LogRecord r;
  while (src.next(r)) {
    if (r.type != RecordType::kGroundTruth) continue;
    const auto& g = r.gt;
    f.put(text::seconds_from_ns(g.t_ns) + " " + text::fmt17(g.p_WB[0]) + " " + text::fmt17(g.p_WB[1]) + " " +
          text::fmt17(g.p_WB[2]) + " " + text::fmt17(g.q_WB[1]) + " " + text::fmt17(g.q_WB[2]) + " " +
          text::fmt17(g.q_WB[3]) + " " + text::fmt17(g.q_WB[0]) + "\n");
    ++n;
  }
  f.close();
  return n;
}

}  // namespace kestrel::drivers

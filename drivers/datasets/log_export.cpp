#include "kestrel/drivers/log_export.hpp"

#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>

#include "dataset_common.hpp"
#include "kestrel/drivers/camera_time_shift.hpp"
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
  std::string s =
      "%YAML:1.0\nsensor_type: camera\ncomment: " + std::string(comment) + "\n\n" + matrix_yaml(r.T_BC);
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
  s += "gyroscope_noise_density: " + text::fmt17(r.imu.gyro_noise_density_rad_s_sqrthz) +
       "     # [ rad / s / sqrt(Hz) ]\n";
  s += "gyroscope_random_walk: " + text::fmt17(r.imu.gyro_random_walk_rad_s2_sqrthz) +
       "       # [ rad / s^2 / sqrt(Hz) ]\n";
  s += "accelerometer_noise_density: " + text::fmt17(r.imu.acc_noise_density_mps2_sqrthz) +
       "  # [ m / s^2 / sqrt(Hz) ]\n";
  s += "accelerometer_random_walk: " + text::fmt17(r.imu.acc_random_walk_mps3_sqrthz) +
       "    # [ m / s^3 / sqrt(Hz) ]\n";
  return s;
}

cv::Mat to_writable(const LogImage& img) {
  // LogImage pixels are packed, so a Mat header over them needs no copy.
  auto* data = const_cast<uint8_t*>(img.pixels.data());
  switch (img.format) {
    case PixelFormat::kGray8:
      return cv::Mat(img.height, img.width, CV_8UC1, data);
    case PixelFormat::kBgr8:
      return cv::Mat(img.height, img.width, CV_8UC3, data);
    case PixelFormat::kDepthU16:
      return cv::Mat(img.height, img.width, CV_16UC1, data);
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
    f.put(rig_to_yaml(rig_for_shifted_records(rig)));  // the stamps carry the offset
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
  imu.put(
      "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],"
      "a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n");
  OutFile cam(mav + "/cam0/data.csv");
  cam.put("#timestamp [ns],filename\n");
  std::unique_ptr<OutFile> depth, gt, events, right;
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
          y.put(
              camera_sensor_yaml(rig,
                                 "depth registered to the colour camera (cam0), 16-bit PNG; metres = value * "
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
          gt->put(
              "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z "
              "[],"
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
        events->put(std::to_string(r.event.t_ns) + "," + std::to_string(static_cast<uint32_t>(r.event.code)) +
                    "," + t + "\n");
        ++st.events;
        break;
      }
      case RecordType::kRight: {
        // A stereo log's right camera goes where EuRoC keeps it, cam1.
        if (!right) {
          mkdirs(mav + "/cam1/data");
          right = std::make_unique<OutFile>(mav + "/cam1/data.csv");
          right->put("#timestamp [ns],filename\n");
        }
        const std::string name = std::to_string(r.image.t_ns) + ".png";
        const std::string file = mav + "/cam1/data/" + name;
        const cv::Mat m = to_writable(r.image);
        if (m.empty() || !cv::imwrite(file, m)) throw std::runtime_error(file + ": cannot write PNG");
        right->put(std::to_string(r.image.t_ns) + "," + name + "\n");
        break;
      }
    }
  }
  imu.close();
  if (right) right->close();
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

namespace {

// Depth units converted between scales; 0 stays invalid, out-of-range becomes invalid.
cv::Mat rescale_depth(const LogImage& img, double from_m_per_unit, double to_m_per_unit) {
  cv::Mat in(img.height, img.width, CV_16UC1, const_cast<uint8_t*>(img.pixels.data()));
  if (from_m_per_unit == to_m_per_unit) return in;
  cv::Mat out(img.height, img.width, CV_16UC1);
  const double k = from_m_per_unit / to_m_per_unit;
  for (int y = 0; y < img.height; ++y) {
    for (int x = 0; x < img.width; ++x) {
      const double v = std::round(in.at<uint16_t>(y, x) * k);
      out.at<uint16_t>(y, x) = v > 0 && v <= 65535 ? static_cast<uint16_t>(v) : 0;
    }
  }
  return out;
}

// ETH3D images are undistorted pinhole with the same K: for each output pixel, where the
// distorted source image saw that ray. Colour is interpolated, depth taken from the nearest pixel
// (blending depths across an edge would invent surfaces).
struct Undistorter {
  cv::Mat map_x, map_y;
  bool active = false;

  explicit Undistorter(const CameraIntrinsics& c) {
    if (c.distortion == DistortionModel::kNone || c.width <= 0 || c.height <= 0) return;
    bool any = false;
    for (double d : c.dist) any = any || d != 0;
    if (!any) return;
    active = true;
    map_x.create(c.height, c.width, CV_32FC1);
    map_y.create(c.height, c.width, CV_32FC1);
    const auto& k = c.dist;
    for (int v = 0; v < c.height; ++v) {
      for (int u = 0; u < c.width; ++u) {
        const double x = (u - c.cx) / c.fx, y = (v - c.cy) / c.fy;
        double xd, yd;
        if (c.distortion == DistortionModel::kRadTan) {
          const double r2 = x * x + y * y;
          const double radial = 1 + k[0] * r2 + k[1] * r2 * r2 + k[4] * r2 * r2 * r2;
          xd = x * radial + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x);
          yd = y * radial + k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y;
        } else {
          const double r = std::sqrt(x * x + y * y);
          const double th = std::atan(r), t2 = th * th;
          const double thd =
              th * (1 + k[0] * t2 + k[1] * t2 * t2 + k[2] * t2 * t2 * t2 + k[3] * t2 * t2 * t2 * t2);
          const double s = r > 1e-12 ? thd / r : 1.0;
          xd = x * s, yd = y * s;
        }
        map_x.at<float>(v, u) = static_cast<float>(c.fx * xd + c.cx);
        map_y.at<float>(v, u) = static_cast<float>(c.fy * yd + c.cy);
      }
    }
  }
  cv::Mat apply(const cv::Mat& in, bool depth) const {
    if (!active || in.cols != map_x.cols || in.rows != map_x.rows) return in;
    cv::Mat out;
    cv::remap(in, out, map_x, map_y, depth ? cv::INTER_NEAREST : cv::INTER_LINEAR, cv::BORDER_CONSTANT,
              cv::Scalar());
    return out;
  }
};

void write_png(const std::string& file, const cv::Mat& m) {
  if (m.empty() || !cv::imwrite(file, m)) throw std::runtime_error(file + ": cannot write PNG");
}

std::string tum_pose(int64_t t_ns, const Vec3d& p, const Quatd& q) {
  return text::seconds_from_ns(t_ns) + " " + text::fmt17(p[0]) + " " + text::fmt17(p[1]) + " " +
         text::fmt17(p[2]) + " " + text::fmt17(q[1]) + " " + text::fmt17(q[2]) + " " + text::fmt17(q[3]) +
         " " + text::fmt17(q[0]) + "\n";
}

// One image name per stamp; a repeated stamp gets a suffix so files never collide.
class ImageNamer {
 public:
  std::string operator()(int64_t t_ns) {
    std::string n = text::seconds_from_ns(t_ns);
    if (have_ && t_ns == last_) n += "_" + std::to_string(++dup_);
    have_ = true;
    last_ = t_ns;
    return n + ".png";
  }

 private:
  bool have_ = false;
  int64_t last_ = 0;
  int dup_ = 0;
};

std::string cv_matrix(int rows, int cols, const double* v) {
  std::string s = "!!opencv-matrix\n      rows: " + std::to_string(rows) +
                  "\n      cols: " + std::to_string(cols) + "\n      dt: d\n      data: [ ";
  for (int i = 0; i < rows * cols; ++i) s += (i ? ", " : "") + text::fmt17(v[i]);
  return s + " ]\n";
}

}  // namespace

ExportStats export_eth3d(LogSource& src, const std::string& out_dir) {
  mkdirs(out_dir + "/rgb");
  mkdirs(out_dir + "/depth");
  const Rig& rig = src.rig();
  {
    // What ETH3D has no place for (T_BC, IMU noise, ...): Eth3dReader takes it when no --rig is given.
    OutFile f(out_dir + "/kestrel_rig.yaml");
    f.put(rig_to_yaml(rig_for_shifted_records(rig)));  // the stamps carry the offset
    f.close();
  }
  {
    OutFile f(out_dir + "/calibration.txt");
    f.put(text::fmt17(rig.rgb.fx) + " " + text::fmt17(rig.rgb.fy) + " " + text::fmt17(rig.rgb.cx) + " " +
          text::fmt17(rig.rgb.cy) + "\n");
    f.close();
  }
  OutFile rgb(out_dir + "/rgb.txt"), depth(out_dir + "/depth.txt"), assoc(out_dir + "/associated.txt");
  rgb.put("# colour images, exported by Kestrel\n# timestamp filename\n");
  depth.put("# depth images (16-bit PNG, 5000 units per metre), exported by Kestrel\n# timestamp filename\n");
  std::unique_ptr<OutFile> gt, imu;
  ExportStats st;
  ImageNamer rgb_name, depth_name;
  const Undistorter undistort(rig.rgb);
  bool have_rgb = false;
  int64_t last_rgb_t = 0;
  std::string last_rgb_file;
  const bool body_is_camera = ds::is_identity(rig.T_BC);
  src.rewind();
  LogRecord r;
  while (src.next(r)) {
    switch (r.type) {
      case RecordType::kImu: {
        if (!imu) {
          imu = std::make_unique<OutFile>(out_dir + "/imu.txt");
          imu->put("# timestamp gx gy gz ax ay az (rad/s, m/s^2), exported by Kestrel\n");
        }
        const auto& m = r.imu;
        std::string row = text::seconds_from_ns(m.t_ns);
        for (double v : m.gyro_rps) row += " " + text::fmt17(v);
        for (double v : m.acc_mps2) row += " " + text::fmt17(v);
        imu->put(row + "\n");
        ++st.imu;
        break;
      }
      case RecordType::kRgb: {
        const std::string name = "rgb/" + rgb_name(r.image.t_ns);
        write_png(out_dir + "/" + name, undistort.apply(to_writable(r.image), false));
        rgb.put(text::seconds_from_ns(r.image.t_ns) + " " + name + "\n");
        have_rgb = true;
        last_rgb_t = r.image.t_ns;
        last_rgb_file = name;
        ++st.rgb;
        break;
      }
      case RecordType::kDepth: {
        const std::string name = "depth/" + depth_name(r.image.t_ns);
        write_png(out_dir + "/" + name,
                  undistort.apply(rescale_depth(r.image, rig.depth.scale_m_per_unit, 1.0 / 5000.0), true));
        const std::string t = text::seconds_from_ns(r.image.t_ns);
        depth.put(t + " " + name + "\n");
        if (have_rgb && last_rgb_t == r.image.t_ns)
          assoc.put(t + " " + last_rgb_file + " " + t + " " + name + "\n");
        ++st.depth;
        break;
      }
      case RecordType::kGroundTruth: {
        if (!gt) {
          gt = std::make_unique<OutFile>(out_dir + "/groundtruth.txt");
          gt->put("# colour camera pose T_WC, exported by Kestrel\n# timestamp tx ty tz qx qy qz qw\n");
        }
        const GroundTruthPose c = body_is_camera ? r.gt : ds::compose(r.gt, rig.T_BC);
        gt->put(tum_pose(c.t_ns, c.p_WB, c.q_WB));
        ++st.ground_truth;
        break;
      }
      case RecordType::kEvent:  // ETH3D has no place for events
      case RecordType::kRight:  // nor for a second camera
        break;
    }
  }
  rgb.close();
  depth.close();
  assoc.close();
  if (gt) gt->close();
  if (imu) imu->close();
  return st;
}

ExportStats export_openloris(LogSource& src, const std::string& out_dir) {
  mkdirs(out_dir + "/color");
  mkdirs(out_dir + "/aligned_depth");
  const Rig& rig = src.rig();
  {
    OutFile f(out_dir + "/sensors.yaml");
    const double k[4] = {rig.rgb.fx, rig.rgb.cx, rig.rgb.fy, rig.rgb.cy};
    const char* model = rig.rgb.distortion == DistortionModel::kRadTan        ? "radial-tangential"
                        : rig.rgb.distortion == DistortionModel::kEquidistant ? "equidistant"
                                                                              : "none";
    std::string y = "%YAML:1.0\n# exported by Kestrel\nd400_color_optical_frame:\n   sensor_type: camera\n";
    y += "   fps: " + text::fmt17(rig.camera_rate_hz) + "\n   width: " + std::to_string(rig.rgb.width) +
         "\n   height: " + std::to_string(rig.rgb.height) + "\n   model: pinhole\n";
    y += "   intrinsics: " + cv_matrix(1, 4, k);
    y += "   distortion_model: " + std::string(model) + "\n";
    y += "   distortion_coefficients: " + cv_matrix(1, 5, rig.rgb.dist.data());
    y += "d400_depth_optical_frame:\n   sensor_type: camera\n   depth_scale: " +
         text::fmt17(rig.depth.scale_m_per_unit) + "\n";
    y += "d400_accelerometer:\n   sensor_type: imu\n   fps: " + text::fmt17(rig.imu_rate_hz) + "\n";
    y += "d400_gyroscope:\n   sensor_type: imu\n   fps: " + text::fmt17(rig.imu_rate_hz) + "\n";
    f.put(y);
    f.close();
  }
  {
    OutFile f(out_dir + "/trans_matrix.yaml");
    std::string y =
        "%YAML:1.0\n# T_parent_child: child coordinates into the parent frame; exported by "
        "Kestrel\ntrans_matrix:\n";
    auto entry = [&](const char* parent, const char* child, const Mat4d& m) {
      y += "   - parent_frame: " + std::string(parent) + "\n     child_frame: " + child +
           "\n     matrix: " + cv_matrix(4, 4, m.data());
    };
    entry("base_link", "d400_gyroscope", kIdentity4);
    entry("d400_gyroscope", "d400_accelerometer", kIdentity4);
    entry("d400_gyroscope", "d400_color_optical_frame", rig.T_BC);
    f.put(y);
    f.close();
  }
  OutFile color(out_dir + "/color.txt"), depth(out_dir + "/aligned_depth.txt");
  color.put("# colour images, exported by Kestrel\n# timestamp filename\n");
  depth.put("# depth registered to colour, exported by Kestrel\n# timestamp filename\n");
  OutFile acc(out_dir + "/d400_accelerometer.txt"), gyr(out_dir + "/d400_gyroscope.txt");
  acc.put("# timestamp ax ay az (m/s^2)\n");
  gyr.put("# timestamp gx gy gz (rad/s)\n");
  std::unique_ptr<OutFile> gt;
  ExportStats st;
  ImageNamer rgb_name, depth_name;
  src.rewind();
  LogRecord r;
  while (src.next(r)) {
    switch (r.type) {
      case RecordType::kImu: {
        const std::string t = text::seconds_from_ns(r.imu.t_ns);
        const auto& g = r.imu.gyro_rps;
        const auto& a = r.imu.acc_mps2;
        gyr.put(t + " " + text::fmt17(g[0]) + " " + text::fmt17(g[1]) + " " + text::fmt17(g[2]) + "\n");
        acc.put(t + " " + text::fmt17(a[0]) + " " + text::fmt17(a[1]) + " " + text::fmt17(a[2]) + "\n");
        ++st.imu;
        break;
      }
      case RecordType::kRgb:
      case RecordType::kDepth: {
        const bool is_rgb = r.type == RecordType::kRgb;
        const std::string name =
            (is_rgb ? "color/" : "aligned_depth/") + (is_rgb ? rgb_name : depth_name)(r.image.t_ns);
        write_png(out_dir + "/" + name, to_writable(r.image));
        (is_rgb ? color : depth).put(text::seconds_from_ns(r.image.t_ns) + " " + name + "\n");
        ++(is_rgb ? st.rgb : st.depth);
        break;
      }
      case RecordType::kGroundTruth:
        if (!gt) {
          gt = std::make_unique<OutFile>(out_dir + "/groundtruth.txt");
          gt->put(
              "# base_link (= IMU body) pose in the world, exported by Kestrel\n# timestamp tx ty tz qx qy "
              "qz qw\n");
        }
        gt->put(tum_pose(r.gt.t_ns, r.gt.p_WB, r.gt.q_WB));
        ++st.ground_truth;
        break;
      case RecordType::kEvent:  // nor has OpenLORIS
      case RecordType::kRight:
        break;
    }
  }
  color.close();
  depth.close();
  acc.close();
  gyr.close();
  if (gt) gt->close();
  return st;
}

}  // namespace kestrel::drivers

// `import kestrel`: the log readers, the embedded estimator, the replay harness
// and the trajectory metrics with numpy arrays (docs/python.md).
//
// Everything here is a thin conversion layer: numpy in, the C++ types the
// command line uses, numpy out. The GIL is released around every call that
// does real work (a log record, a frame, a whole replay), so other Python
// threads run meanwhile; a Python state callback takes it back while it runs.
#include <pybind11/functional.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <set>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/core/kestrel.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/tools/config_file.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"
#include "kestrel/tools/trajectory_eval.hpp"

namespace py = pybind11;

namespace kestrel::python {
namespace {

using Clock = std::chrono::steady_clock;

const char* format_name(PixelFormat f) {
  switch (f) {
    case PixelFormat::kGray8:
      return "mono8";
    case PixelFormat::kRgb8:
      return "rgb8";
    case PixelFormat::kBgr8:
      return "bgr8";
    case PixelFormat::kYuyv:
      return "yuyv";
    case PixelFormat::kDepthU16:
      return "depth16";
  }
  return "unknown";
}

const char* record_type_name(drivers::RecordType t) {
  switch (t) {
    case drivers::RecordType::kImu:
      return "imu";
    case drivers::RecordType::kRgb:
      return "rgb";
    case drivers::RecordType::kDepth:
      return "depth";
    case drivers::RecordType::kRight:
      return "right";
    case drivers::RecordType::kGroundTruth:
      return "ground_truth";
    case drivers::RecordType::kEvent:
      return "event";
  }
  return "unknown";
}

py::array_t<double> vec3(const Vec3d& v) {
  py::array_t<double> a(3);
  std::memcpy(a.mutable_data(), v.data(), sizeof(double) * 3);
  return a;
}

py::array_t<double> vec(const Eigen::Vector3d& v) {
  py::array_t<double> a(3);
  for (int i = 0; i < 3; ++i) a.mutable_at(i) = v[i];
  return a;
}

py::array_t<double> mat4(const Mat4d& m) {
  py::array_t<double> a({4, 4});
  std::memcpy(a.mutable_data(), m.data(), sizeof(double) * 16);
  return a;
}

// A copy of the log's pixels (the reader reuses its buffer for the next record).
py::array image_array(const drivers::LogImage& im) {
  const auto h = static_cast<py::ssize_t>(im.height), w = static_cast<py::ssize_t>(im.width);
  py::array out;
  switch (im.format) {
    case PixelFormat::kGray8:
      out = py::array_t<uint8_t>({h, w});
      break;
    case PixelFormat::kRgb8:
    case PixelFormat::kBgr8:
      out = py::array_t<uint8_t>({h, w, py::ssize_t{3}});
      break;
    case PixelFormat::kYuyv:
      out = py::array_t<uint8_t>({h, w, py::ssize_t{2}});
      break;
    case PixelFormat::kDepthU16:
      out = py::array_t<uint16_t>({h, w});
      break;
  }
  const size_t bytes = static_cast<size_t>(out.nbytes());
  if (im.pixels.size() < bytes) {
    throw std::runtime_error("image record at t_ns " + std::to_string(im.t_ns) + " holds " +
                             std::to_string(im.pixels.size()) + " bytes, its header says " +
                             std::to_string(bytes));
  }
  std::memcpy(out.mutable_data(), im.pixels.data(), bytes);
  return out;
}

// ---- log records ------------------------------------------------------------

// One record as Python sees it: only the members of its type are set, the
// others are None (as LogRecord, where only the member named by type counts).
struct Record {
  std::string type;
  int64_t t_ns = 0;
  uint64_t offset = 0;
  uint32_t seq = 0;
  uint32_t flags = 0;
  py::object gyro_rps = py::none(), acc_mps2 = py::none();
  py::object image = py::none(), format = py::none();
  py::object p_WB = py::none(), q_WB_wxyz = py::none(), v_WB = py::none();
  py::object code = py::none(), text = py::none();
};

Record to_python(const drivers::LogRecord& r) {
  Record o;
  o.type = record_type_name(r.type);
  o.offset = r.offset;
  switch (r.type) {
    case drivers::RecordType::kImu:
      o.t_ns = r.imu.t_ns;
      o.seq = r.imu.seq;
      o.flags = r.imu.flags;
      o.gyro_rps = vec3(r.imu.gyro_rps);
      o.acc_mps2 = vec3(r.imu.acc_mps2);
      break;
    case drivers::RecordType::kRgb:
    case drivers::RecordType::kDepth:
    case drivers::RecordType::kRight:  // a stereo rig's right image (docs/stereo.md)
      o.t_ns = r.image.t_ns;
      o.seq = r.image.seq;
      o.image = image_array(r.image);
      o.format = py::str(format_name(r.image.format));
      break;
    case drivers::RecordType::kGroundTruth: {
      o.t_ns = r.gt.t_ns;
      o.p_WB = vec3(r.gt.p_WB);
      py::array_t<double> q(4);
      std::memcpy(q.mutable_data(), r.gt.q_WB.data(), sizeof(double) * 4);
      o.q_WB_wxyz = q;
      if (r.gt.has_velocity) o.v_WB = vec3(r.gt.v_WB);
      break;
    }
    case drivers::RecordType::kEvent:
      o.t_ns = r.event.t_ns;
      o.code = py::int_(static_cast<uint32_t>(r.event.code));
      o.text = py::str(r.event.text);
      break;
  }
  return o;
}

// Keyword options shared by open_log and replay, checked by name so a typo is
// an error naming it rather than an option silently ignored.
drivers::LogOpenOptions open_options(py::dict& kw, drivers::LogFormat& format) {
  drivers::LogOpenOptions o;
  auto take_str = [&kw](const char* key, std::string& out) {
    if (!kw.contains(key)) return;
    py::object v = kw[key];
    if (!v.is_none()) out = py::str(v);
    PyDict_DelItemString(kw.ptr(), key);
  };
  std::string fmt = "auto";
  take_str("format", fmt);
  try {
    format = drivers::parse_log_format(fmt);
  } catch (const std::exception& e) {
    throw py::value_error(std::string("format: ") + e.what());
  }
  take_str("rig", o.rig_path);
  take_str("rgb_topic", o.rgb_topic);
  take_str("depth_topic", o.depth_topic);
  take_str("imu_topic", o.imu_topic);
  take_str("camera_info_topic", o.camera_info_topic);
  take_str("gt_topic", o.ground_truth_topic);
  take_str("right_topic", o.right_topic);
  if (kw.contains("topics")) {
    py::object v = kw["topics"];
    if (py::isinstance<py::str>(v)) {
      std::string all = v.cast<std::string>();
      for (size_t a = 0; a <= all.size();) {
        const size_t b = std::min(all.find(',', a), all.size());
        if (b > a) o.topics.push_back(all.substr(a, b - a));
        a = b + 1;
      }
    } else if (!v.is_none()) {
      o.topics = v.cast<std::vector<std::string>>();
    }
    PyDict_DelItemString(kw.ptr(), "topics");
  }
  if (kw.contains("fps")) {
    o.fps = py::cast<double>(kw["fps"]);
    PyDict_DelItemString(kw.ptr(), "fps");
  }
  o.format = format;
  return o;
}

void refuse_unknown(const py::dict& kw, const char* function, const char* known) {
  if (kw.empty()) return;
  std::string names;
  for (auto item : kw) names += (names.empty() ? "" : ", ") + py::str(item.first).cast<std::string>();
  throw py::type_error(std::string(function) + "(): unknown option(s) " + names + " (known: " + known + ")");
}

class Log {
 public:
  Log(const std::string& path, py::kwargs kw) {
    py::dict d(std::move(kw));
    drivers::LogFormat format = drivers::LogFormat::kAuto;
    const drivers::LogOpenOptions o = open_options(d, format);
    refuse_unknown(d, "open_log",
                   "format, rig, fps, rgb_topic, depth_topic, imu_topic, camera_info_topic, gt_topic, "
                   "right_topic, topics");
    path_ = path;
    src_ = drivers::open_log(path, o);
  }
  Record next() {
    bool more;
    {
      py::gil_scoped_release unlocked;
      more = src_->next(rec_);
    }
    if (!more) throw py::stop_iteration();
    return to_python(rec_);
  }
  void rewind() { src_->rewind(); }
  const Rig& rig() const { return src_->rig(); }
  std::string format() const { return src_->format_name(); }
  const std::string& path() const { return path_; }
  std::vector<py::tuple> problems() const {
    std::vector<py::tuple> out;
    for (const auto& p : src_->problems()) out.push_back(py::make_tuple(p.where, p.kind, p.detail));
    return out;
  }

 private:
  std::string path_;
  std::unique_ptr<drivers::LogSource> src_;
  drivers::LogRecord rec_;
};

// ---- trajectories as (N, 8) TUM rows ----------------------------------------

constexpr double kNsPerS = 1e9;

py::array_t<double> tum_array(const tools::Trajectory& t) {
  py::array_t<double> a({static_cast<py::ssize_t>(t.size()), py::ssize_t{8}});
  auto m = a.mutable_unchecked<2>();
  for (size_t i = 0; i < t.size(); ++i) {
    const auto& p = t[i];
    const auto r = static_cast<py::ssize_t>(i);
    m(r, 0) = static_cast<double>(p.t_ns) / kNsPerS;
    m(r, 1) = p.p.x();
    m(r, 2) = p.p.y();
    m(r, 3) = p.p.z();
    m(r, 4) = p.q.x();
    m(r, 5) = p.q.y();
    m(r, 6) = p.q.z();
    m(r, 7) = p.q.w();
  }
  return a;
}

// TUM rows back to a trajectory; the rows must be in time order with finite
// values and a non-zero quaternion (the error names the argument and row).
tools::Trajectory trajectory_of(const py::array_t<double, py::array::c_style | py::array::forcecast>& a,
                                const char* name) {
  if (a.ndim() != 2 || a.shape(1) != 8) {
    throw py::value_error(
        std::string(name) + ": expected an (N, 8) array of TUM rows t[s] x y z qx qy qz qw, got " +
        std::to_string(a.ndim()) + " dimension(s)" +
        (a.ndim() == 2 ? " with " + std::to_string(a.shape(1)) + " columns" : std::string()));
  }
  auto m = a.unchecked<2>();
  tools::Trajectory t;
  t.reserve(static_cast<size_t>(a.shape(0)));
  for (py::ssize_t i = 0; i < a.shape(0); ++i) {
    for (py::ssize_t j = 0; j < 8; ++j) {
      if (!std::isfinite(m(i, j))) {
        throw py::value_error(std::string(name) + ": row " + std::to_string(i) + " column " +
                              std::to_string(j) + " is not finite");
      }
    }
    tools::TimedPose p;
    p.t_ns = static_cast<int64_t>(std::llround(m(i, 0) * kNsPerS));
    if (!t.empty() && p.t_ns <= t.back().t_ns) {
      throw py::value_error(std::string(name) + ": row " + std::to_string(i) +
                            " (t = " + std::to_string(m(i, 0)) + " s) is not after the row before it");
    }
    p.p = Eigen::Vector3d(m(i, 1), m(i, 2), m(i, 3));
    Eigen::Quaterniond q(m(i, 7), m(i, 4), m(i, 5), m(i, 6));
    if (q.norm() < 1e-9)
      throw py::value_error(std::string(name) + ": row " + std::to_string(i) + " has a zero quaternion");
    p.q = q.normalized();
    t.push_back(p);
  }
  return t;
}

py::dict stats_dict(const tools::Stats& s) {
  py::dict d;
  d["rmse"] = s.rmse;
  d["mean"] = s.mean;
  d["median"] = s.median;
  d["std"] = s.std;
  d["min"] = s.min;
  d["max"] = s.max;
  d["count"] = s.count;
  return d;
}

tools::EvalOptions eval_options(const std::string& align, double max_gap_ms, double rpe_delta_s) {
  tools::EvalOptions o;
  const auto a = tools::parse_alignment(align);
  if (!a) throw py::value_error("align: '" + align + "' is not one of none, se3, sim3, posyaw");
  o.align = *a;
  o.max_gap_ms = max_gap_ms;
  o.rpe_delta_s = rpe_delta_s;
  return o;
}

py::dict evaluate(const py::array_t<double, py::array::c_style | py::array::forcecast>& gt,
                  const py::array_t<double, py::array::c_style | py::array::forcecast>& est,
                  const std::string& align, double max_gap_ms, double rpe_delta_s) {
  const tools::Trajectory g = trajectory_of(gt, "gt"), e = trajectory_of(est, "est");
  tools::EvalResult r;
  {
    py::gil_scoped_release unlocked;
    r = tools::evaluate(g, e, eval_options(align, max_gap_ms, rpe_delta_s));
  }
  py::dict d;
  d["align"] = tools::alignment_name(r.align);
  d["matched"] = r.matched;
  d["interpolated"] = r.interpolated;
  d["unmatched"] = r.unmatched;
  d["coverage"] = r.coverage;
  d["gt_length_m"] = r.gt_length_m;
  d["ate_m"] = stats_dict(r.ate_m);
  d["ate_rot_deg"] = stats_dict(r.ate_rot_deg);
  py::dict rpe;
  rpe["delta_s"] = r.rpe_delta_s;
  rpe["pairs"] = r.rpe_pairs;
  rpe["trans_rmse_m"] = r.rpe_trans_rmse_m;
  rpe["trans_mean_m"] = r.rpe_trans_mean_m;
  rpe["trans_m_per_s"] = r.rpe_trans_m_per_s;
  rpe["rot_rmse_deg"] = r.rpe_rot_rmse_deg;
  rpe["rot_mean_deg"] = r.rpe_rot_mean_deg;
  d["rpe"] = rpe;
  py::array_t<double> R({3, 3});
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) R.mutable_at(i, j) = r.T_align.R(i, j);
  py::dict align_d;
  align_d["scale"] = r.T_align.scale;
  align_d["R"] = R;
  align_d["t"] = vec(r.T_align.t);
  d["T_align"] = align_d;
  d["est_aligned"] = tum_array(r.est_aligned);
  d["gt_matched"] = tum_array(r.gt_matched);
  d["pos_err_m"] = py::array_t<double>(static_cast<py::ssize_t>(r.pos_err_m.size()), r.pos_err_m.data());
  d["warnings"] = r.warnings;
  return d;
}

// ---- the embedded estimator -------------------------------------------------

struct PyState {
  int64_t t_ns = 0;
  py::array_t<double> p_WB, q_WB_wxyz, v_WB, gyro_bias_rps, acc_bias_mps2;
  std::string quality;
  uint32_t reset_counter = 0;
  bool from_frame = false;
};

PyState to_python(const State& s) {
  PyState o;
  o.t_ns = s.t_ns;
  o.p_WB = vec(s.p_WB);
  o.q_WB_wxyz = py::array_t<double>(4);
  o.q_WB_wxyz.mutable_at(0) = s.q_WB.w();
  o.q_WB_wxyz.mutable_at(1) = s.q_WB.x();
  o.q_WB_wxyz.mutable_at(2) = s.q_WB.y();
  o.q_WB_wxyz.mutable_at(3) = s.q_WB.z();
  o.v_WB = vec(s.v_WB);
  o.gyro_bias_rps = vec(s.gyro_bias_rps);
  o.acc_bias_mps2 = vec(s.acc_bias_mps2);
  o.quality = core::tracking_quality_name(s.quality);
  o.reset_counter = s.reset_counter;
  o.from_frame = s.from_frame;
  return o;
}

// A numpy image as the ImageView the estimator reads, checked against the
// rig: rows may be padded (a slice), pixels may not.
ImageView view_of(const py::array& a, const char* name, int width, int height, PixelFormat format) {
  const int bpp = bytes_per_pixel(format);
  const int channels = format == PixelFormat::kRgb8 || format == PixelFormat::kBgr8 ? 3 : 1;
  const bool depth = format == PixelFormat::kDepthU16;
  const py::ssize_t want_ndim = channels == 3 ? 3 : 2;
  std::string expect = std::string(name) + ": expected a (" + std::to_string(height) + ", " +
                       std::to_string(width) + (channels == 3 ? ", 3" : "") + ") " +
                       (depth ? "uint16" : "uint8") + " array";
  if (a.ndim() != want_ndim || a.shape(0) != height || a.shape(1) != width ||
      (channels == 3 && a.shape(2) != 3)) {
    throw py::value_error(
        expect + ", got shape " +
        py::str(py::tuple(py::cast(std::vector<py::ssize_t>(a.shape(), a.shape() + a.ndim()))))
            .cast<std::string>());
  }
  if (depth ? !py::isinstance<py::array_t<uint16_t>>(a) : !py::isinstance<py::array_t<uint8_t>>(a))
    throw py::value_error(expect + ", got dtype " + py::str(a.dtype()).cast<std::string>());
  const bool packed = a.strides(1) == bpp && (channels == 1 || a.strides(2) == 1);
  if (!packed || a.strides(0) < static_cast<py::ssize_t>(width) * bpp)
    throw py::value_error(std::string(name) + ": pixels must be packed within a row (np.ascontiguousarray)");
  ImageView v;
  v.width = width;
  v.height = height;
  v.stride_bytes = static_cast<int>(a.strides(0));
  v.format = format;
  v.data = static_cast<const uint8_t*>(a.data());
  return v;
}

class PyEstimator {
 public:
  PyEstimator(const Rig& rig, const std::string& backend) : rig_(rig) {
    if (!core::estimator_known(backend)) {
      throw py::value_error("backend: unknown '" + backend +
                            "' (expected one of: " + core::estimator_names() + ")");
    }
    est_ = std::make_unique<Estimator>(rig, backend);
    // The trajectory is one pose per camera frame the backend has a pose for,
    // as `kestrel replay --traj-out` writes it; reserved for an hour at the
    // rig's rate so a flight does not reallocate while it is fed.
    const double rate = rig.camera_rate_hz > 0 ? rig.camera_rate_hz : 30.0;
    poses_.reserve(static_cast<size_t>(rate * 3600));
    est_->on_state(
        [this](const State& s) {
          if (s.from_frame && s.quality != core::TrackingQuality::kUninitialized &&
              s.quality != core::TrackingQuality::kLost)
            poses_.push_back({s.t_ns, s.p_WB, s.q_WB});
          if (py_cb_) {
            py::gil_scoped_acquire locked;
            if (s.from_frame || py_cb_imu_rate_) py_cb_(to_python(s));
          }
        },
        /*imu_rate=*/true);
  }

  void on_state(const py::object& cb, bool imu_rate) {
    py_cb_ = cb.is_none() ? py::function() : py::function(cb);
    py_cb_imu_rate_ = imu_rate;
  }

  bool add_imu(int64_t t_ns, const std::array<double, 3>& gyro_rps, const std::array<double, 3>& acc_mps2) {
    ImuSample s;
    s.t_ns = t_ns;
    s.t_recv_ns = t_ns;
    s.seq = imu_seq_++;
    s.gyro_rps = gyro_rps;
    s.acc_mps2 = acc_mps2;
    return feed_imu(s);
  }

  // Many samples in one call: (N,) int64 ns, (N, 3) rad/s, (N, 3) m/s^2.
  int add_imu_batch(const py::array_t<int64_t, py::array::c_style | py::array::forcecast>& t_ns,
                    const py::array_t<double, py::array::c_style | py::array::forcecast>& gyro_rps,
                    const py::array_t<double, py::array::c_style | py::array::forcecast>& acc_mps2) {
    const py::ssize_t n = t_ns.ndim() == 1 ? t_ns.shape(0) : -1;
    if (n < 0) throw py::value_error("t_ns: expected a 1-D array of int64 nanoseconds");
    for (const auto* a : {&gyro_rps, &acc_mps2}) {
      if (a->ndim() != 2 || a->shape(0) != n || a->shape(1) != 3) {
        throw py::value_error(std::string(a == &gyro_rps ? "gyro_rps" : "acc_mps2") + ": expected shape (" +
                              std::to_string(n) + ", 3)");
      }
    }
    auto t = t_ns.unchecked<1>();
    auto g = gyro_rps.unchecked<2>();
    auto f = acc_mps2.unchecked<2>();
    int changed = 0;
    for (py::ssize_t i = 0; i < n; ++i) {
      ImuSample s;
      s.t_ns = t(i);
      s.t_recv_ns = t(i);
      s.seq = imu_seq_++;
      s.gyro_rps = {g(i, 0), g(i, 1), g(i, 2)};
      s.acc_mps2 = {f(i, 0), f(i, 1), f(i, 2)};
      changed += feed_imu(s) ? 1 : 0;
    }
    return changed;
  }

  // rgb: (H, W, 3) uint8 in `rgb_format` order, or (H, W) uint8 grey;
  // depth: (H, W) uint16 in the rig's depth units, or float metres (0 or
  // NaN = no depth), converted here.
  bool add_frame(int64_t t_ns, const py::array& rgb, const py::object& depth, const std::string& rgb_format) {
    const int w = rig_.rgb.width, h = rig_.rgb.height;
    PixelFormat fmt;
    if (rgb_format == "rgb8") {
      fmt = PixelFormat::kRgb8;
    } else if (rgb_format == "bgr8") {
      fmt = PixelFormat::kBgr8;
    } else if (rgb_format == "mono8") {
      fmt = PixelFormat::kGray8;
    } else {
      throw py::value_error("rgb_format: '" + rgb_format + "' is not one of rgb8, bgr8, mono8");
    }
    if (fmt != PixelFormat::kGray8 && rgb.ndim() == 2) fmt = PixelFormat::kGray8;
    const ImageView rgb_view = view_of(rgb, "rgb", w, h, fmt);
    ImageView depth_view;
    if (!depth.is_none()) {
      py::array d = py::array::ensure(depth);
      if (!d) throw py::value_error("depth: expected a numpy array or None");
      if (d.dtype().kind() == 'f') {
        depth_view = metres_to_units(d, w, h);
      } else {
        depth_view = view_of(d, "depth", w, h, PixelFormat::kDepthU16);
      }
    }
    const auto t0 = Clock::now();
    bool changed;
    {
      py::gil_scoped_release unlocked;
      changed = est_->feed_rgbd(t_ns, rgb_view, depth_view);
    }
    native_ns_ += (Clock::now() - t0).count();
    ++frames_;
    return changed;
  }

  py::array_t<double> trajectory() const { return tum_array(poses_); }
  PyState state() const { return to_python(est_->state()); }
  std::string backend() const { return est_->backend_name(); }

  py::dict counters() const {
    const EmbeddedCounters& c = est_->counters();
    py::dict d;
    d["imu_in"] = c.estimator.imu_in;
    d["imu_used"] = c.estimator.imu_used;
    d["frames_in"] = c.estimator.frames_in;
    d["frames_used"] = c.estimator.frames_used;
    d["resets"] = c.estimator.resets;
    d["imu_non_finite"] = c.estimator.imu_rejects.non_finite;
    d["imu_saturated"] = c.estimator.imu_rejects.saturated;
    d["imu_out_of_order"] = c.estimator.imu_rejects.out_of_order;
    d["imu_gaps"] = c.estimator.imu_rejects.gaps;
    d["frames_rejected"] = c.frames_rejected;
    // Time spent inside the C++ estimator's feed calls, to tell the binding's
    // own cost from the estimator's (docs/python.md, overhead per frame).
    d["native_s"] = static_cast<double>(native_ns_) * 1e-9;
    return d;
  }

 private:
  bool feed_imu(const ImuSample& s) {
    const auto t0 = Clock::now();
    const bool changed = est_->feed_imu(s);
    native_ns_ += (Clock::now() - t0).count();
    return changed;
  }

  ImageView metres_to_units(const py::array& d, int w, int h) {
    auto m = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(d);
    if (!m || m.ndim() != 2 || m.shape(0) != h || m.shape(1) != w) {
      throw py::value_error("depth: expected a (" + std::to_string(h) + ", " + std::to_string(w) +
                            ") array (uint16 depth units or float metres)");
    }
    const double scale = rig_.depth.scale_m_per_unit;
    depth_units_.resize(static_cast<size_t>(w) * h);
    const double* src = m.data();
    for (size_t i = 0; i < depth_units_.size(); ++i) {
      const double u = src[i] / scale;
      depth_units_[i] = std::isfinite(u) && u > 0 && u < 65535.0 ? static_cast<uint16_t>(std::lround(u)) : 0;
    }
    return ImageView{w, h, w * 2, PixelFormat::kDepthU16,
                     reinterpret_cast<const uint8_t*>(depth_units_.data())};
  }

  Rig rig_;
  std::unique_ptr<Estimator> est_;
  tools::Trajectory poses_;
  py::function py_cb_;
  bool py_cb_imu_rate_ = false;
  uint32_t imu_seq_ = 0;
  int64_t native_ns_ = 0;
  uint64_t frames_ = 0;
  std::vector<uint16_t> depth_units_;
};

// ---- replay -----------------------------------------------------------------

constexpr const char* kReplayOptions =
    "format, rig, fps, rgb_topic, depth_topic, imu_topic, camera_info_topic, gt_topic, right_topic, topics, "
    "estimator, "
    "config, pace, mapping, loop, warmup_s, trajectory, report";

py::object replay(const std::string& path, py::kwargs kw) {
  py::dict d(std::move(kw));
  cli::ReplayOptions opt;
  opt.path = path;
  opt.open = open_options(d, opt.format);
  auto take = [&d](const char* key, std::string def) {
    if (!d.contains(key)) return def;
    py::object v = d[key];
    std::string s = v.is_none() ? def : py::str(v).cast<std::string>();
    PyDict_DelItemString(d.ptr(), key);
    return s;
  };
  const std::string estimator = take("estimator", "");
  const std::string config = take("config", "");
  const std::string pace = take("pace", "lockstep");
  const std::string mapping = take("mapping", "");
  const std::string loop = take("loop", "");
  const std::string which = take("trajectory", "odometry");
  double warmup_s = 2.0;
  if (d.contains("warmup_s")) {
    warmup_s = py::cast<double>(d["warmup_s"]);
    PyDict_DelItemString(d.ptr(), "warmup_s");
  }
  bool want_report = false;
  if (d.contains("report")) {
    want_report = py::cast<bool>(d["report"]);
    PyDict_DelItemString(d.ptr(), "report");
  }
  refuse_unknown(d, "replay", kReplayOptions);
  if (!estimator.empty() && !core::estimator_known(estimator)) {
    throw py::value_error("estimator: unknown '" + estimator +
                          "' (expected one of: " + core::estimator_names() + ")");
  }
  if (which != "odometry" && which != "map" && which != "map_final")
    throw py::value_error("trajectory: '" + which + "' is not one of odometry, map, map_final");
  if (!(warmup_s >= 0)) throw py::value_error("warmup_s must be >= 0");
  // The config file through the command line's one reader: the same checks, the same defaults.
  const tools::Config file = tools::load_config(config, estimator);
  opt.config = file.estimator;
  tools::apply_map_switches(*opt.config, mapping, loop);
  opt.estimator = opt.config->backend;
  opt.threads = file.threads;
  opt.pace = drivers::parse_replay_pace(pace);
  opt.warmup_ns = static_cast<int64_t>(warmup_s * 1e9);

  cli::ReplayReport r;
  {
    py::gil_scoped_release unlocked;
    r = cli::run_replay(opt);
  }
  const tools::Trajectory& t = which == "map"         ? r.map_trajectory
                               : which == "map_final" ? r.map_final_trajectory
                                                      : r.trajectory;
  py::array_t<double> rows = tum_array(t);
  if (!want_report) return std::move(rows);
  py::dict rep;
  rep["estimator"] = r.estimator;
  rep["log_format"] = r.log_format;
  rep["pace"] = drivers::to_string(r.pace);
  rep["log_duration_s"] = r.log_duration_s;
  rep["wall_s"] = r.wall_s;
  rep["realtime_factor"] = r.realtime_factor;
  rep["estimator_cpu_s"] = r.estimator_cpu_s;
  rep["frames_pushed"] = r.replay.frames_pushed;
  rep["imu_pushed"] = r.replay.imu_pushed;
  rep["lost_poses_withheld"] = r.counters.count("output.lost_poses_withheld");
  rep["resets"] = r.estimator_counters.resets;
  // Every count of the run by path, as the metrics JSON's `counters` (docs/threads.md, "Counters").
  py::dict counts;
  for (const rt::PerfValue& v : r.counters.all())
    if (v.kind == rt::PerfKind::kCount) counts[py::str(v.name)] = v.count;
  rep["counters"] = counts;
  rep["alloc_counting"] = r.alloc_counting;  // false here: the counting hook is not in the module
  std::vector<py::tuple> problems;
  for (const auto& p : r.problems) problems.push_back(py::make_tuple(p.where, p.kind, p.detail));
  rep["problems"] = problems;
  rep["summary"] = cli::replay_summary(r);
  return py::make_tuple(rows, rep);
}

}  // namespace
}  // namespace kestrel::python

PYBIND11_MODULE(_kestrel, m) {
  using namespace kestrel;
  using namespace kestrel::python;
  m.doc() =
      "Kestrel visual-inertial estimator: logs, backends, replay and trajectory metrics (docs/python.md)";

  py::class_<Rig>(m, "Rig", "camera intrinsics, extrinsics and IMU noise (rt/include/kestrel/msgs.hpp)")
      .def_readonly("name", &Rig::name)
      .def_property_readonly("width", [](const Rig& r) { return r.rgb.width; })
      .def_property_readonly("height", [](const Rig& r) { return r.rgb.height; })
      .def_property_readonly("K",
                             [](const Rig& r) {
                               py::array_t<double> k({3, 3});
                               const double v[9] = {r.rgb.fx, 0, r.rgb.cx, 0, r.rgb.fy, r.rgb.cy, 0, 0, 1};
                               std::memcpy(k.mutable_data(), v, sizeof v);
                               return k;
                             })
      .def_property_readonly("T_BC", [](const Rig& r) { return mat4(r.T_BC); })
      .def_property_readonly("depth_scale_m_per_unit", [](const Rig& r) { return r.depth.scale_m_per_unit; })
      .def_readonly("imu_rate_hz", &Rig::imu_rate_hz)
      .def_readonly("camera_rate_hz", &Rig::camera_rate_hz)
      .def_readonly("time_offset_cam_imu_ns", &Rig::time_offset_cam_imu_ns)
      .def("__repr__", [](const Rig& r) {
        return "<kestrel.Rig '" + r.name + "' " + std::to_string(r.rgb.width) + "x" +
               std::to_string(r.rgb.height) + ", imu " + std::to_string(r.imu_rate_hz) + " Hz>";
      });
  m.def("load_rig", &drivers::load_rig_file, py::arg("path"),
        "read a rig YAML (configs/*.yaml, docs/config.md)");

  py::class_<Record>(m, "Record", "one log record; members not of its type are None")
      .def_readonly("type", &Record::type, "imu, rgb, depth, ground_truth or event")
      .def_readonly("t_ns", &Record::t_ns)
      .def_readonly("offset", &Record::offset, "byte offset (klog) or line number (text formats)")
      .def_readonly("seq", &Record::seq)
      .def_readonly("flags", &Record::flags, "IMU flag bits (saturated, non-finite, gap before...)")
      .def_readonly("gyro_rps", &Record::gyro_rps)
      .def_readonly("acc_mps2", &Record::acc_mps2)
      .def_readonly("image", &Record::image, "(H, W) uint8 / uint16 depth units, or (H, W, 3) uint8")
      .def_readonly("format", &Record::format, "mono8, rgb8, bgr8, yuyv or depth16")
      .def_readonly("p_WB", &Record::p_WB)
      .def_readonly("q_WB_wxyz", &Record::q_WB_wxyz)
      .def_readonly("v_WB", &Record::v_WB)
      .def_readonly("code", &Record::code)
      .def_readonly("text", &Record::text)
      .def("__repr__", [](const Record& r) {
        return "<kestrel.Record " + r.type + " t_ns=" + std::to_string(r.t_ns) + ">";
      });

  py::class_<Log>(m, "Log", "a recorded log in any supported format, iterated record by record")
      .def(py::init<const std::string&, py::kwargs>(), py::arg("path"))
      .def(
          "__iter__", [](Log& l) -> Log& { return l; }, py::return_value_policy::reference_internal)
      .def("__next__", &Log::next)
      .def("rewind", &Log::rewind)
      .def_property_readonly("rig", &Log::rig, py::return_value_policy::copy)
      .def_property_readonly("format", &Log::format)
      .def_property_readonly("path", &Log::path)
      .def_property_readonly("problems", &Log::problems,
                             "(where, kind, detail) of everything wrong in the input");

  py::class_<PyState>(m, "State", "the estimate in W (gravity along -z) of body B = IMU (docs/frames.md)")
      .def_readonly("t_ns", &PyState::t_ns)
      .def_readonly("p_WB", &PyState::p_WB)
      .def_readonly("q_WB_wxyz", &PyState::q_WB_wxyz)
      .def_readonly("v_WB", &PyState::v_WB)
      .def_readonly("gyro_bias_rps", &PyState::gyro_bias_rps)
      .def_readonly("acc_bias_mps2", &PyState::acc_bias_mps2)
      .def_readonly("quality", &PyState::quality, "uninitialized, imu_only, tracking, lost or vision_only")
      .def_readonly("reset_counter", &PyState::reset_counter)
      .def_readonly("from_frame", &PyState::from_frame);

  py::class_<PyEstimator>(m, "Estimator",
                          "one backend behind add_imu / add_frame (docs/api.md, docs/python.md)")
      .def(py::init<const Rig&, const std::string&>(), py::arg("rig"), py::arg("backend") = "auto")
      .def("on_state", &PyEstimator::on_state, py::arg("callback"), py::arg("imu_rate") = false,
           "callback(State) on every frame (and IMU sample with imu_rate=True); None removes it")
      .def("add_imu", &PyEstimator::add_imu, py::arg("t_ns"), py::arg("gyro_rps"), py::arg("acc_mps2"))
      .def("add_imu_batch", &PyEstimator::add_imu_batch, py::arg("t_ns"), py::arg("gyro_rps"),
           py::arg("acc_mps2"))
      .def("add_frame", &PyEstimator::add_frame, py::arg("t_ns"), py::arg("rgb"),
           py::arg("depth") = py::none(), py::arg("rgb_format") = "rgb8")
      .def("trajectory", &PyEstimator::trajectory, "(N, 8) TUM rows, one per frame with a pose")
      .def_property_readonly("state", &PyEstimator::state)
      .def_property_readonly("backend", &PyEstimator::backend)
      .def_property_readonly("counters", &PyEstimator::counters);

  m.def("backends", [] { return std::string(core::estimator_names()); });
  m.def("replay", &replay, py::arg("path"),
        "run `kestrel replay` on a log; returns the (N, 8) TUM trajectory (with report=True: (rows, dict))");
  m.def("evaluate", &evaluate, py::arg("gt"), py::arg("est"), py::arg("align") = "posyaw",
        py::arg("max_gap_ms") = 20.0, py::arg("rpe_delta_s") = 1.0,
        "associate, align and score two (N, 8) TUM arrays (docs/evaluation.md)");
  m.def(
      "load_trajectory",
      [](const std::string& path) {
        std::vector<std::string> warnings;
        return tum_array(tools::load_trajectory(path, &warnings));
      },
      py::arg("path"), "TUM, EuRoC CSV or a log's ground truth as (N, 8) TUM rows");
  m.def(
      "write_tum",
      [](const std::string& path,
         const py::array_t<double, py::array::c_style | py::array::forcecast>& rows) {
        tools::write_tum(path, trajectory_of(rows, "rows"));
      },
      py::arg("path"), py::arg("rows"));
}

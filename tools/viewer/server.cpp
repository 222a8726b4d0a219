#include "kestrel/viewer/server.hpp"

#include <sys/resource.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <climits>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <stdexcept>
#include <thread>
#include <utility>
#include <websocketpp/config/asio_no_tls.hpp>
#include <websocketpp/server.hpp>

#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::viewer {
namespace {

using WsServer = websocketpp::server<websocketpp::config::asio>;
using Hdl = websocketpp::connection_hdl;
using json = nlohmann::json;

constexpr long kTickMs = 20;  // 50 Hz: well above the 10 Hz image rate
constexpr size_t kFrameBacklogBytes =
    256 * 1024;  // queued above this: no camera frames; for the timeout: dropped
constexpr size_t kStallBacklogBytes = 1024 * 1024;  // queued above this: nothing at all
constexpr size_t kMaxIncomingBytes = 1024;
constexpr size_t kInitialPosesMax = 20000;  // a new browser's first trajectory, decimated
constexpr size_t kAlignPairsMax = 2000;
constexpr int64_t kAlignPeriodNs = 2'000'000'000;
constexpr int64_t kStatsPeriodNs = 1'000'000'000;
constexpr int64_t kAlignMaxGapNs = 50'000'000;

// Binary messages start with a type byte (then three zero bytes, so the
// float payload that follows a 4-byte count stays 4-byte aligned for a
// Float32Array in the page).
enum class Bin : uint8_t { kFrame = 1, kPoses = 2, kMap = 3, kGroundTruth = 4, kKeyframes = 5 };
constexpr int kPoseFloats = 5;      // t [s since the first pose], x, y, z [m], quality
constexpr int kKeyframeFloats = 8;  // t, p_WC xyz, q_WC wxyz

double thread_cpu_s() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

std::string read_file(const std::string& path, const std::string& hint) {
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error("viewer: cannot read " + path + " (" + hint + ")");
  std::ostringstream s;
  s << f.rdbuf();
  return s.str();
}

void put_u32(std::string& out, size_t at, uint32_t v) { std::memcpy(&out[at], &v, 4); }

std::string float_message(Bin type, const float* v, size_t count, int stride) {
  std::string m(8 + count * static_cast<size_t>(stride) * 4, '\0');
  m[0] = static_cast<char>(type);
  put_u32(m, 4, static_cast<uint32_t>(count));
  if (count > 0) std::memcpy(&m[8], v, count * static_cast<size_t>(stride) * 4);
  return m;
}

// A whole history for a browser that just connected, every k-th item when
// there are more than kInitialPosesMax (a long flight).
std::string decimated_message(Bin type, const std::vector<float>& v, int stride) {
  const size_t count = v.size() / static_cast<size_t>(stride);
  const size_t every = std::max<size_t>(1, (count + kInitialPosesMax - 1) / kInitialPosesMax);
  if (every == 1) return float_message(type, v.data(), count, stride);
  std::vector<float> d;
  d.reserve((count / every + 1) * static_cast<size_t>(stride));
  for (size_t i = 0; i < count; i += every) {
    d.insert(d.end(), v.begin() + static_cast<std::ptrdiff_t>(i * stride),
             v.begin() + static_cast<std::ptrdiff_t>((i + 1) * stride));
  }
  return float_message(type, d.data(), d.size() / static_cast<size_t>(stride), stride);
}

const char* quality_name(core::TrackingQuality q) {
  switch (q) {
    case core::TrackingQuality::kTracking:
      return "tracking";
    case core::TrackingQuality::kImuOnly:
      return "imu-only";
    case core::TrackingQuality::kVisionOnly:
      return "vision-only";
    case core::TrackingQuality::kLost:
      return "lost";
    case core::TrackingQuality::kUninitialized:
      break;
  }
  return "uninitialized";
}

double ms(int64_t ns) { return 1e-6 * static_cast<double>(ns); }

std::vector<uchar> encode_jpeg(const cv::Mat& bgr, int quality) {
  std::vector<uchar> out;
  cv::imencode(".jpg", bgr, out, {cv::IMWRITE_JPEG_QUALITY, quality});
  return out;
}

// Depth as a colour map over the rig's range (near: red, far: blue), no
// depth black: what a person reads at a glance. Converted pixel by pixel
// through a 256-entry table, and the colour image swapped to BGR by hand:
// OpenCV's parallel loops would move the viewer's work onto worker threads
// that neither nice 10 nor the CPU figure of kst-viewer covers.
std::vector<uchar> depth_jpeg(const ViewSnapshot& s, const DepthModel& d, const cv::Mat& lut_bgr,
                              int quality) {
  const double lo = d.min_range_m, hi = std::max(d.max_range_m, d.min_range_m + 0.1);
  const double k = 255.0 * d.scale_m_per_unit / (hi - lo), k0 = 255.0 * hi / (hi - lo);
  cv::Mat colour(s.depth_height, s.depth_width, CV_8UC3);
  for (int y = 0; y < s.depth_height; ++y) {
    const uint16_t* in = s.depth + static_cast<size_t>(y) * static_cast<size_t>(s.depth_width);
    uchar* out = colour.ptr<uchar>(y);
    for (int x = 0; x < s.depth_width; ++x) {
      if (in[x] == 0) {
        out[3 * x] = out[3 * x + 1] = out[3 * x + 2] = 0;
        continue;
      }
      const int i = std::clamp(static_cast<int>(k0 - k * in[x]), 0, 255);  // near -> 255
      std::memcpy(out + 3 * x, lut_bgr.ptr<uchar>(0) + 3 * i, 3);
    }
  }
  return encode_jpeg(colour, quality);
}

std::vector<uchar> rgb_jpeg(const ViewSnapshot& s, int quality) {
  cv::Mat bgr(s.rgb_height, s.rgb_width, CV_8UC3);
  for (int y = 0; y < s.rgb_height; ++y) {
    const uint8_t* in = s.rgb + static_cast<size_t>(y) * static_cast<size_t>(s.rgb_width) * 3;
    uchar* out = bgr.ptr<uchar>(y);
    for (int x = 0; x < s.rgb_width; ++x) {
      out[3 * x] = in[3 * x + 2];
      out[3 * x + 1] = in[3 * x + 1];
      out[3 * x + 2] = in[3 * x];
    }
  }
  return encode_jpeg(bgr, quality);
}

cv::Mat turbo_table() {
  cv::Mat ramp(1, 256, CV_8UC1);
  for (int i = 0; i < 256; ++i) ramp.at<uchar>(0, i) = static_cast<uchar>(i);
  cv::Mat lut;
  cv::applyColorMap(ramp, lut, cv::COLORMAP_TURBO);
  return lut;
}

struct Client {
  Hdl hdl;
  double tokens = 0;
  int64_t refill_ns = 0;
  int64_t stalled_since_ns = 0;
  bool map_pending = false;
  bool closing = false;
  bool dense_missed = false;  // a dense message was not sent: its blocks are stale here
};

struct PendingPose {
  int64_t t_ns;
  float p[3];
  float quality;
};

}  // namespace

void parse_view_endpoint(const std::string& text, ServerOptions& opt) {
  const size_t colon = text.rfind(':');
  const std::string host = colon == std::string::npos ? std::string() : text.substr(0, colon);
  const std::string port = colon == std::string::npos ? text : text.substr(colon + 1);
  char* end = nullptr;
  errno = 0;
  const long v = port.empty() ? -1 : std::strtol(port.c_str(), &end, 10);
  if (port.empty() || errno != 0 || end == nullptr || *end != '\0' || v < 0 || v > 65535) {
    throw std::invalid_argument("'" + text +
                                "': expected [ADDR:]PORT with PORT in 0..65535 (0: any free port)");
  }
  if (colon != std::string::npos && host.empty())
    throw std::invalid_argument("'" + text + "': empty address before ':' (omit it for every interface)");
  if (!host.empty()) opt.address = host;
  opt.port = static_cast<uint16_t>(v);
}

std::string default_assets_dir() {
  if (const char* env = std::getenv("KESTREL_VIEWER_ASSETS")) return env;
  char buf[PATH_MAX];
  const ssize_t n = readlink("/proc/self/exe", buf, sizeof buf - 1);
  if (n <= 0) return "share/kestrel/viewer";
  std::string exe(buf, static_cast<size_t>(n));
  const size_t slash = exe.rfind('/');
  const std::string bin = slash == std::string::npos ? "." : exe.substr(0, slash);
  return bin + "/../share/kestrel/viewer";
}

struct Server::Impl {
  Impl(const ServerOptions& o, ViewerFeed& f, PlaybackControl* c) : opt(o), feed(f), control(c) {}

  ServerOptions opt;
  ViewerFeed& feed;
  PlaybackControl* control;
  WsServer ws;
  std::thread thread;
  std::atomic<bool> stopping{false};
  uint16_t bound_port = 0;
  std::map<std::string, std::pair<std::string, std::string>> files;  // path -> (content type, body)
  std::function<int64_t()> imu_probe;
  BinaryStream* dense = nullptr;
  const rt::PerfRegistry* counters = nullptr;
  cv::Mat turbo = turbo_table();  // depth colours, BGR, 256 entries

  // ---- viewer thread only
  std::vector<Client> clients;
  std::vector<std::weak_ptr<void>> sockets;
  std::vector<int64_t> traj_t_ns;
  std::vector<float> traj;   // kPoseFloats per pose
  size_t traj_streamed = 0;  // poses already sent to every connected browser
  int64_t t0_ns = -1;
  std::vector<float> keyframes;
  size_t keyframes_streamed = 0;
  std::vector<float> map_xyz;
  tools::Trajectory gt;  // as the replay's records passed
  std::vector<float> gt_xyz;
  size_t gt_streamed = 0;
  std::string align_msg;  // newest ground-truth alignment, "" before the first
  std::string last_state, last_frame;
  size_t aligned_at_poses = 0;
  int64_t next_align_ns = 0;
  int64_t next_stats_ns = 0;
  int64_t first_snapshot_t_ns = -1;
  bool control_paused_sent = false;
  uint64_t control_frames_sent = 0;
  bool finished_sent = false;
  double cpu_at_last_tick = 0;
  int64_t last_tick_ns = 0;
  uint64_t bytes_at_last_tick = 0;
  uint64_t rate_bytes_at = 0;  // the page's kB/s line: bytes and time at the previous one
  int64_t rate_ns_at = 0;

  // ---- shared
  // Poses from the output thread: a ring, so add_pose never allocates or
  // locks (in lockstep replay that thread is the estimator's own).
  std::unique_ptr<rt::SpscRing<PendingPose, 16384>> pending_poses =
      std::make_unique<rt::SpscRing<PendingPose, 16384>>();
  std::mutex pose_mu;  // guards `finished`
  std::string finished;
  mutable std::mutex stats_mu;
  ServerStats st;
  std::condition_variable client_cv;
  int n_clients = 0;  // under stats_mu

  // ---------------------------------------------------------------------
  void load_files() {
    const std::string dir = opt.assets_dir.empty() ? default_assets_dir() : opt.assets_dir;
    const std::string hint_assets = "the viewer's page, built into share/kestrel/viewer (tools/viewer/web)";
    const std::string hint_three =
        "Debian's libjs-three: apt-get install libjs-three (tools/install-deps.sh)";
    files["/"] = {"text/html; charset=utf-8", read_file(dir + "/index.html", hint_assets)};
    files["/index.html"] = files["/"];
    files["/viewer.js"] = {"text/javascript; charset=utf-8", read_file(dir + "/viewer.js", hint_assets)};
    files["/viewer.css"] = {"text/css; charset=utf-8", read_file(dir + "/viewer.css", hint_assets)};
    files["/js/three.min.js"] = {"text/javascript; charset=utf-8",
                                 read_file(opt.three_dir + "/three.min.js", hint_three)};
    files["/js/OrbitControls.js"] = {
        "text/javascript; charset=utf-8",
        read_file(opt.three_dir + "/examples/js/controls/OrbitControls.js", hint_three)};
  }

  template <class F>
  void with_stats(F f) {
    std::lock_guard<std::mutex> lock(stats_mu);
    f(st);
  }

  bool send(Client& c, const std::string& m, websocketpp::frame::opcode::value op) {
    websocketpp::lib::error_code ec;
    ws.send(c.hdl, m.data(), m.size(), op, ec);
    if (ec) return false;
    c.tokens -= static_cast<double>(m.size());
    with_stats([&](ServerStats& s) {
      s.bytes_sent += m.size();
      ++s.messages_sent;
    });
    return true;
  }
  bool send_text(Client& c, const std::string& m) { return send(c, m, websocketpp::frame::opcode::text); }
  bool send_binary(Client& c, const std::string& m) { return send(c, m, websocketpp::frame::opcode::binary); }

  std::string control_msg() const {
    json j;
    j["type"] = "control";
    j["available"] = control != nullptr && control->available();
    j["paused"] = control != nullptr && control->paused();
    if (control != nullptr) j["frames"] = control->frames();
    return j.dump();
  }

  std::string hello_msg() const {
    const Rig& rig = feed.rig();
    json j;
    j["type"] = "hello";
    j["estimator"] = feed.estimator_name();
    j["title"] = opt.title;
    j["camera"] = {{"width", rig.rgb.width}, {"height", rig.rgb.height}, {"fx", rig.rgb.fx},
                   {"fy", rig.rgb.fy},       {"cx", rig.rgb.cx},         {"cy", rig.rgb.cy}};
    j["depth_range_m"] = {rig.depth.min_range_m, rig.depth.max_range_m};
    j["max_kbytes_per_s"] = opt.max_kbytes_per_s;
    j["max_clients"] = opt.max_clients;
    return j.dump();
  }

  // ---------------------------------------------------------------------
  // Handlers (viewer thread).
  void on_socket_init(const Hdl& hdl, boost::asio::ip::tcp::socket& s) {
    sockets.erase(std::remove_if(sockets.begin(), sockets.end(),
                                 [](const std::weak_ptr<void>& w) { return w.expired(); }),
                  sockets.end());
    if (static_cast<int>(sockets.size()) >= opt.max_connections || stopping.load()) {
      boost::system::error_code ec;
      s.close(ec);  // the handshake read fails at once; the connection is freed
      with_stats([](ServerStats& x) { ++x.connections_refused; });
      return;
    }
    sockets.push_back(hdl);
    const int open = static_cast<int>(sockets.size());
    with_stats([&](ServerStats& x) {
      ++x.connections;
      x.connections_peak = std::max(x.connections_peak, open);
    });
  }

  void on_http(Hdl hdl) {
    WsServer::connection_ptr con = ws.get_con_from_hdl(std::move(hdl));
    with_stats([](ServerStats& x) { ++x.http_requests; });
    const std::string& method = con->get_request().get_method();
    std::string path = con->get_resource();
    const size_t q = path.find('?');
    if (q != std::string::npos) path.resize(q);
    if (method != "GET") {
      con->set_status(websocketpp::http::status_code::method_not_allowed);
      con->append_header("Allow", "GET");
      con->set_body("only GET\n");
      with_stats([](ServerStats& x) { ++x.http_errors; });
      return;
    }
    const auto it = files.find(path);
    if (it == files.end()) {
      con->set_status(websocketpp::http::status_code::not_found);
      con->append_header("Content-Type", "text/plain; charset=utf-8");
      con->set_body("not found\n");
      with_stats([](ServerStats& x) { ++x.http_errors; });
      return;
    }
    con->set_status(websocketpp::http::status_code::ok);
    con->append_header("Content-Type", it->second.first);
    con->append_header("Cache-Control", "no-cache");
    con->set_body(it->second.second);
  }

  bool on_validate(Hdl hdl) {
    WsServer::connection_ptr con = ws.get_con_from_hdl(std::move(hdl));
    std::string path = con->get_resource();
    const size_t q = path.find('?');
    if (q != std::string::npos) path.resize(q);
    if (path != "/ws") {
      con->set_status(websocketpp::http::status_code::not_found);
      with_stats([](ServerStats& x) { ++x.clients_refused; });
      return false;
    }
    if (static_cast<int>(clients.size()) >= opt.max_clients || stopping.load()) {
      con->set_status(websocketpp::http::status_code::service_unavailable);
      con->set_body("viewer: " + std::to_string(opt.max_clients) + " browsers already connected\n");
      with_stats([](ServerStats& x) { ++x.clients_refused; });
      return false;
    }
    return true;
  }

  void on_open(Hdl hdl) {
    Client c;
    c.hdl = std::move(hdl);
    c.refill_ns = rt::now_ns();
    c.tokens = burst_bytes();
    clients.push_back(c);
    Client& n = clients.back();
    send_text(n, hello_msg());
    send_text(n, control_msg());
    // What happened before this browser came: the trajectory (decimated when
    // long), every keyframe, the ground truth and its alignment, the map.
    if (!traj.empty()) send_binary(n, decimated_message(Bin::kPoses, traj, kPoseFloats));
    if (!keyframes.empty()) {
      send_binary(n, float_message(Bin::kKeyframes, keyframes.data(), keyframes.size() / kKeyframeFloats,
                                   kKeyframeFloats));
    }
    if (!gt_xyz.empty()) send_binary(n, decimated_message(Bin::kGroundTruth, gt_xyz, 3));
    if (!align_msg.empty()) send_text(n, align_msg);
    // The newest state and frame: a replay paused before this browser came shows them.
    if (!last_state.empty()) send_text(n, last_state);
    if (!last_frame.empty()) send_binary(n, last_frame);
    n.map_pending = !map_xyz.empty();
    std::string fin;
    {
      std::lock_guard<std::mutex> lock(pose_mu);
      if (!finished.empty()) fin = finished_msg();
    }
    if (!fin.empty()) send_text(n, fin);
    feed.request_map();
    if (dense != nullptr) {
      // The blocks sent before this browser came: all again (to every browser; the others just redraw them).
      dense->request_resend();
      dense->set_wanted(true);
    }
    const int count = static_cast<int>(clients.size());
    {
      std::lock_guard<std::mutex> lock(stats_mu);
      ++st.clients;
      st.clients_peak = std::max(st.clients_peak, count);
      n_clients = count;
    }
    client_cv.notify_all();
    feed.set_wanted(true);
  }

  void on_close(const Hdl& hdl) {
    WsServer::connection_ptr con = ws.get_con_from_hdl(hdl);
    const auto code = con->get_local_close_code();
    if (code == websocketpp::close::status::protocol_error ||
        code == websocketpp::close::status::message_too_big ||
        code == websocketpp::close::status::invalid_payload)
      with_stats([](ServerStats& x) { ++x.protocol_errors; });
    remove_client(hdl);
  }

  void on_fail(Hdl hdl) {
    remove_client(std::move(hdl));
    with_stats([](ServerStats& x) { ++x.handshakes_failed; });
  }

  void remove_client(Hdl hdl) {
    const auto same = [&](const Client& c) { return !c.hdl.owner_before(hdl) && !hdl.owner_before(c.hdl); };
    clients.erase(std::remove_if(clients.begin(), clients.end(), same), clients.end());
    {
      std::lock_guard<std::mutex> lock(stats_mu);
      n_clients = static_cast<int>(clients.size());
    }
    if (clients.empty()) {
      feed.set_wanted(false);
      if (dense != nullptr) dense->set_wanted(false);
    }
  }

  void on_message(const Hdl& hdl, const WsServer::message_ptr& msg) {
    std::string reply;
    bool ok = false;
    if (msg->get_opcode() == websocketpp::frame::opcode::text) {
      const json j = json::parse(msg->get_payload(), nullptr, false);
      const std::string cmd =
          j.is_object() && j.contains("cmd") && j["cmd"].is_string() ? j["cmd"].get<std::string>() : "";
      if (cmd == "pause" || cmd == "resume" || cmd == "step") {
        if (control != nullptr && control->available()) {
          if (cmd == "pause") control->pause();
          if (cmd == "resume") control->resume();
          if (cmd == "step") control->step();
          ok = true;
        } else {
          reply = "replay controls need --pace lockstep (this run cannot pause)";
        }
      } else {
        reply = "unknown command (expected {\"cmd\": \"pause\" | \"resume\" | \"step\"})";
      }
    } else {
      reply = "binary messages are not understood";
    }
    with_stats([&](ServerStats& x) { ok ? ++x.commands : ++x.bad_commands; });
    if (!ok) {
      for (Client& c : clients) {
        if (!c.hdl.owner_before(hdl) && !hdl.owner_before(c.hdl))
          send_text(c, json{{"type", "error"}, {"message", reply}}.dump());
      }
    }
  }

  // ---------------------------------------------------------------------
  double burst_bytes() const { return std::max(opt.max_kbytes_per_s * 1000.0, 128.0 * 1024.0); }

  std::string finished_msg() const { return json{{"type", "end"}, {"summary", finished}}.dump(); }

  std::string state_msg(const StateSnapshot& s) {
    if (first_snapshot_t_ns < 0) first_snapshot_t_ns = s.t_ns;
    json j;
    j["type"] = "state";
    j["t"] = 1e-9 * static_cast<double>(s.t_ns - first_snapshot_t_ns);
    j["seq"] = s.seq;
    j["frames"] = s.frames_fed;
    j["estimator"] = feed.estimator_name();
    j["quality"] = quality_name(s.quality);
    j["reset_counter"] = s.reset_counter;
    j["p"] = {s.p_WB[0], s.p_WB[1], s.p_WB[2]};
    j["q"] = {s.q_WB[0], s.q_WB[1], s.q_WB[2], s.q_WB[3]};
    j["v"] = {s.v_WB[0], s.v_WB[1], s.v_WB[2]};
    if (s.has_tracker) {
      j["track"] = {{"status", core::to_string(s.track_status)},
                    {"keyframe", s.keyframe},
                    {"detected", s.detected},
                    {"with_depth", s.with_depth},
                    {"matched", s.matched},
                    {"inliers", s.inliers},
                    {"map_inliers", s.map_inliers},
                    {"rms_px", s.inlier_rms_px},
                    {"area_ratio", s.area_ratio}};
    }
    int64_t imu_ns = s.imu_to_pose_max_ns;
    if (imu_probe) imu_ns = imu_probe();
    j["latency_ms"] = {{"tracking", ms(s.tracking_ns)},
                       {"tracking_max", ms(s.tracking_max_ns)},
                       {"imu_to_pose_max", ms(imu_ns)},
                       {"optimizer", s.has_window ? json(ms(s.optimizer_solve_ns)) : json(nullptr)}};
    if (s.has_window) {
      j["window"] = {{"jobs", s.window_jobs},
                     {"applied", s.window_applied},
                     {"failures", s.window_failures},
                     {"skipped_busy", s.window_skipped_busy},
                     {"resets", s.window_resets}};
    }
    j["counters"] = {{"imu_in", s.imu_in},
                     {"frames_in", s.frames_in},
                     {"frames_used", s.frames_used},
                     {"resets", s.resets},
                     {"imu_rejected", s.imu_rejected}};
    // The pipeline's counts, read from its registry by path as they are now
    // (single fields, each untorn; rt/perf.hpp).
    auto count = [this](const char* path) -> uint64_t {
      const rt::PerfCounter* c = counters != nullptr ? counters->find(path) : nullptr;
      return c != nullptr ? c->snapshot().count : 0;
    };
    j["drops"] = {{"imu_ring", count("rings.imu_drops")},
                  {"frame_ring", count("rings.frame_drops")},
                  {"viewer_snapshots", s.snapshots_skipped},
                  {"viewer_keyframes", feed.keyframes_dropped()}};
    j["faults"] = {{"frames_missing", count("input.frames_missing")},
                   {"out_of_order", count("input.frames_out_of_order")},
                   {"repeated", count("input.frames_repeated")},
                   {"no_depth", count("input.frames_no_depth")},
                   {"imu_gaps", count("input.imu_gaps")}};
    if (counters != nullptr) {
      json all = json::object();
      for (std::size_t i = 0; i < counters->size(); ++i) {
        const rt::PerfCounter::Snapshot c = counters->at(i).snapshot();
        if (c.kind == rt::PerfKind::kCount) {
          all[c.name] = c.count;
        } else {
          all[c.name] = {{"count", c.count}, {"mean_ms", 1e-6 * c.mean_ns()}, {"max_ms", ms(c.max_ns)}};
        }
      }
      j["perf"] = std::move(all);
    }
    return j.dump();
  }

  std::string frame_msg(const ViewSnapshot& s) {
    json meta;
    meta["t"] = 1e-9 * static_cast<double>(s.state.t_ns - first_snapshot_t_ns);
    meta["seq"] = s.state.seq;
    meta["frames"] = s.state.frames_fed;
    meta["width"] = s.rgb_width * s.rgb_step;  // the pixel frame of the features
    meta["height"] = s.rgb_height * s.rgb_step;
    std::vector<int> f;
    f.reserve(static_cast<size_t>(s.n_features) * 3);
    for (int i = 0; i < s.n_features; ++i) {
      f.push_back(static_cast<int>(std::lround(s.features[i].x_px)));
      f.push_back(static_cast<int>(std::lround(s.features[i].y_px)));
      f.push_back(s.features[i].flags);
    }
    meta["features"] = f;
    const std::string m = meta.dump();
    std::vector<uchar> rgb, depth;
    if (s.rgb_width > 0) rgb = rgb_jpeg(s, opt.jpeg_quality);
    if (s.depth_width > 0) depth = depth_jpeg(s, feed.rig().depth, turbo, opt.jpeg_quality);
    std::string out(16, '\0');
    out[0] = static_cast<char>(Bin::kFrame);
    put_u32(out, 4, static_cast<uint32_t>(m.size()));
    put_u32(out, 8, static_cast<uint32_t>(rgb.size()));
    put_u32(out, 12, static_cast<uint32_t>(depth.size()));
    out += m;
    out.append(reinterpret_cast<const char*>(rgb.data()), rgb.size());
    out.append(reinterpret_cast<const char*>(depth.data()), depth.size());
    return out;
  }

  // Position + yaw alignment of the ground truth onto the estimate so far
  // (the 4 DoF VIO cannot observe; docs/evaluation.md), as the matrix the
  // page applies to the ground-truth line: x_E = R^T (x_G - t).
  void update_alignment() {
    const size_t n = traj_t_ns.size();
    if (gt.empty() || n < 10 || n == aligned_at_poses) return;
    aligned_at_poses = n;
    std::vector<Eigen::Vector3d> est, ref;
    const size_t stride = std::max<size_t>(1, n / kAlignPairsMax);
    for (size_t i = 0; i < n; i += stride) {
      const auto g = tools::pose_at(gt, traj_t_ns[i], kAlignMaxGapNs);
      if (!g) continue;
      const float* p = &traj[i * kPoseFloats + 1];
      est.emplace_back(p[0], p[1], p[2]);
      ref.push_back(g->p);
    }
    if (est.size() < 3) return;
    tools::Sim3 S;
    try {
      S = tools::align_positions(est, ref, tools::Alignment::kPosYaw);
    } catch (const std::exception&) {
      return;
    }
    const Eigen::Matrix3d Rt = S.R.transpose();
    const Eigen::Vector3d t = -Rt * S.t;
    json j;
    j["type"] = "align";
    j["R"] = {Rt(0, 0), Rt(0, 1), Rt(0, 2), Rt(1, 0), Rt(1, 1), Rt(1, 2), Rt(2, 0), Rt(2, 1), Rt(2, 2)};
    j["t"] = {t.x(), t.y(), t.z()};
    j["pairs"] = est.size();
    align_msg = j.dump();
    for (Client& c : clients) send_text(c, align_msg);
  }

  void drain_inputs() {
    PendingPose p{};
    while (pending_poses->try_pop(p)) {
      if (t0_ns < 0) t0_ns = p.t_ns;
      traj_t_ns.push_back(p.t_ns);
      traj.insert(traj.end(), {static_cast<float>(1e-9 * static_cast<double>(p.t_ns - t0_ns)), p.p[0], p.p[1],
                               p.p[2], p.quality});
    }
    GroundTruthPose g;
    while (feed.ground_truth_ring().try_pop(g)) {
      tools::TimedPose tp;
      tp.t_ns = g.t_ns;
      tp.p = Eigen::Vector3d(g.p_WB[0], g.p_WB[1], g.p_WB[2]);
      tp.q = Eigen::Quaterniond(g.q_WB[0], g.q_WB[1], g.q_WB[2], g.q_WB[3]);
      if (!gt.empty() && tp.t_ns <= gt.back().t_ns) continue;  // pose_at needs time order
      gt.push_back(tp);
      gt_xyz.insert(gt_xyz.end(), {static_cast<float>(g.p_WB[0]), static_cast<float>(g.p_WB[1]),
                                   static_cast<float>(g.p_WB[2])});
    }
    KeyframeMark k;
    while (feed.pop_keyframe(k)) {
      keyframes.insert(keyframes.end(),
                       {static_cast<float>(1e-9 * static_cast<double>(k.t_ns - std::max<int64_t>(t0_ns, 0))),
                        k.p_WC[0], k.p_WC[1], k.p_WC[2], k.q_WC[0], k.q_WC[1], k.q_WC[2], k.q_WC[3]});
    }
  }

  void tick() {
    const int64_t now = rt::now_ns();
    drain_inputs();
    // Everything new, encoded once for every browser.
    std::string poses_msg, kf_msg, state, frame, map;
    const size_t n_poses = traj.size() / kPoseFloats;
    if (n_poses > traj_streamed) {
      poses_msg = float_message(Bin::kPoses, &traj[traj_streamed * kPoseFloats], n_poses - traj_streamed,
                                kPoseFloats);
    }
    traj_streamed = n_poses;
    const size_t n_kf = keyframes.size() / kKeyframeFloats;
    if (n_kf > keyframes_streamed) {
      kf_msg = float_message(Bin::kKeyframes, &keyframes[keyframes_streamed * kKeyframeFloats],
                             n_kf - keyframes_streamed, kKeyframeFloats);
    }
    keyframes_streamed = n_kf;
    std::string gt_msg;
    const size_t n_gt = gt_xyz.size() / 3;
    if (n_gt > gt_streamed)
      gt_msg = float_message(Bin::kGroundTruth, &gt_xyz[3 * gt_streamed], n_gt - gt_streamed, 3);
    gt_streamed = n_gt;
    rt::PoolHandle h = rt::kInvalidHandle;
    if (const ViewSnapshot* s = feed.take_newest(&h)) {
      with_stats([](ServerStats& x) { ++x.snapshots; });
      if (!clients.empty()) {
        state = last_state = state_msg(s->state);
        frame = last_frame = frame_msg(*s);
      }
      if (s->has_map) {
        map_xyz.assign(s->map_xyz, s->map_xyz + 3 * s->n_map);
        for (Client& c : clients) c.map_pending = true;
      }
      feed.release(h);
    }
    if (!map_xyz.empty() &&
        std::any_of(clients.begin(), clients.end(), [](const Client& c) { return c.map_pending; }))
      map = float_message(Bin::kMap, map_xyz.data(), map_xyz.size() / 3, 3);
    if (now >= next_align_ns) {
      next_align_ns = now + kAlignPeriodNs;
      update_alignment();
    }
    // While paused the held frame is part of the control state (a step moves it).
    const bool paused = control != nullptr && control->paused();
    const uint64_t held = paused ? control->frames() : 0;
    const bool control_changed = paused != control_paused_sent || held != control_frames_sent;
    control_paused_sent = paused;
    control_frames_sent = held;
    std::string stats_line;
    if (now >= next_stats_ns) {
      next_stats_ns = now + kStatsPeriodNs;
      stats_line = stats_msg(now);
    }
    std::string fin;
    {
      std::lock_guard<std::mutex> lock(pose_mu);
      if (!finished.empty() && !finished_sent) {
        finished_sent = true;
        fin = finished_msg();
      }
    }

    const double rate = opt.max_kbytes_per_s * 1000.0;
    for (Client& c : clients) {
      if (c.closing) continue;
      websocketpp::lib::error_code ec;
      WsServer::connection_ptr con = ws.get_con_from_hdl(c.hdl, ec);
      if (ec || !con) continue;
      c.tokens = std::min(burst_bytes(), c.tokens + rate * 1e-9 * static_cast<double>(now - c.refill_ns));
      c.refill_ns = now;
      const size_t queued = con->get_buffered_amount();
      // A socket that stays backed up (frames already held back) is a browser
      // that drains nothing: after the timeout it goes, so it cannot hold a
      // client slot and server memory for ever.
      if (queued > kFrameBacklogBytes) {
        if (c.stalled_since_ns == 0) c.stalled_since_ns = now;
        if (now - c.stalled_since_ns > opt.client_timeout_ns) {
          c.closing = true;
          con->close(websocketpp::close::status::policy_violation, "not reading", ec);
          with_stats([](ServerStats& x) { ++x.clients_dropped; });
          continue;
        }
      } else {
        c.stalled_since_ns = 0;
      }
      if (queued > kStallBacklogBytes) {
        if (!frame.empty()) with_stats([](ServerStats& x) { ++x.frames_skipped_backlog; });
        continue;  // not even the small messages: memory stays bounded
      }
      if (control_changed) send_text(c, control_msg());
      if (!poses_msg.empty()) send_binary(c, poses_msg);
      if (!kf_msg.empty()) send_binary(c, kf_msg);
      if (!gt_msg.empty()) send_binary(c, gt_msg);
      if (!state.empty()) send_text(c, state);
      if (!stats_line.empty()) send_text(c, stats_line);
      if (!fin.empty()) send_text(c, fin);
      if (c.map_pending && !map.empty() && c.tokens >= static_cast<double>(map.size())) {
        send_binary(c, map);
        c.map_pending = false;
      }
      if (!frame.empty()) {
        if (queued > kFrameBacklogBytes) {
          with_stats([](ServerStats& x) { ++x.frames_skipped_backlog; });
        } else if (c.tokens < static_cast<double>(frame.size())) {
          with_stats([](ServerStats& x) { ++x.frames_skipped_budget; });
        } else if (send_binary(c, frame)) {
          with_stats([](ServerStats& x) { ++x.frames_sent; });
        }
      }
    }
    forward_dense();
    account(now);
  }

  // Every dense message to every browser whose socket drains; one that
  // misses a message would keep stale blocks, so it is sent everything again
  // once it drains (the request goes to the producer: it encodes, not us).
  void forward_dense() {
    if (dense == nullptr) return;
    const uint8_t* data = nullptr;
    std::size_t size = 0;
    uint32_t slot = 0;
    while (dense->take(&data, &size, &slot)) {
      const std::string m(reinterpret_cast<const char*>(data), size);
      dense->release(slot);
      for (Client& c : clients) {
        if (c.closing) continue;
        websocketpp::lib::error_code ec;
        WsServer::connection_ptr con = ws.get_con_from_hdl(c.hdl, ec);
        if (ec || !con || con->get_buffered_amount() > kStallBacklogBytes || !send_binary(c, m)) {
          c.dense_missed = true;
          continue;
        }
        with_stats([&](ServerStats& x) {
          ++x.dense_messages;
          x.dense_bytes += m.size();
        });
      }
    }
    for (Client& c : clients) {
      if (!c.dense_missed || c.closing) continue;
      websocketpp::lib::error_code ec;
      WsServer::connection_ptr con = ws.get_con_from_hdl(c.hdl, ec);
      if (ec || !con || con->get_buffered_amount() > kFrameBacklogBytes) continue;
      c.dense_missed = false;
      dense->request_resend();
      with_stats([](ServerStats& x) { ++x.dense_resyncs; });
    }
  }

  // CPU and bytes while at least one browser is connected.
  void account(int64_t now) {
    const double cpu = thread_cpu_s();
    std::lock_guard<std::mutex> lock(stats_mu);
    if (!clients.empty() && last_tick_ns != 0) {
      st.streaming_s += 1e-9 * static_cast<double>(now - last_tick_ns);
      st.streaming_cpu_s += cpu - cpu_at_last_tick;
      st.streaming_bytes += st.bytes_sent - bytes_at_last_tick;
    }
    bytes_at_last_tick = st.bytes_sent;
    st.cpu_s = cpu;
    cpu_at_last_tick = cpu;
    last_tick_ns = now;
  }

  std::string stats_msg(int64_t now) {
    std::lock_guard<std::mutex> lock(stats_mu);
    const double dt = rate_ns_at > 0 ? 1e-9 * static_cast<double>(now - rate_ns_at) : 0;
    json j;
    j["type"] = "stats";
    j["clients"] = clients.size();
    j["kbytes_per_s"] = dt > 0 ? 1e-3 * static_cast<double>(st.bytes_sent - rate_bytes_at) / dt : 0.0;
    j["cpu_ms_per_s"] = st.streaming_s > 0 ? 1000.0 * st.streaming_cpu_s / st.streaming_s : 0.0;
    j["frames_sent"] = st.frames_sent;
    j["frames_skipped"] = st.frames_skipped_budget + st.frames_skipped_backlog;
    rate_bytes_at = st.bytes_sent;
    rate_ns_at = now;
    return j.dump();
  }

  void schedule_tick() {
    ws.set_timer(kTickMs, [this](const websocketpp::lib::error_code& ec) {
      if (ec || stopping.load()) return;
      tick();
      schedule_tick();
    });
  }

  void shutdown_io() {
    tick();  // the last poses and the "finished" line still go out
    websocketpp::lib::error_code ec;
    ws.stop_listening(ec);
    for (Client& c : clients) {
      c.closing = true;
      ws.close(c.hdl, websocketpp::close::status::going_away, "estimator stopped", ec);
    }
  }
};

Server::Server(const ServerOptions& opt, ViewerFeed& feed, PlaybackControl* control)
    : impl_(std::make_unique<Impl>(opt, feed, control)) {
  if (opt.max_clients < 1) throw std::invalid_argument("viewer: max_clients must be >= 1");
  if (opt.max_connections < opt.max_clients + 1) {
    throw std::invalid_argument(
        "viewer: max_connections must exceed max_clients (page loads need sockets too)");
  }
  if (!(opt.max_kbytes_per_s > 0)) throw std::invalid_argument("viewer: max_kbytes_per_s must be > 0");
}

Server::~Server() { stop(); }

void Server::set_imu_latency_probe(std::function<int64_t()> probe) { impl_->imu_probe = std::move(probe); }

void Server::set_dense_stream(BinaryStream* stream) { impl_->dense = stream; }
void Server::set_counters(const rt::PerfRegistry* counters) { impl_->counters = counters; }

rt::ThreadSetupReport Server::start(const rt::ThreadSpec& spec) {
  Impl& m = *impl_;
  m.load_files();
  WsServer& ws = m.ws;
  ws.clear_access_channels(websocketpp::log::alevel::all);
  ws.clear_error_channels(websocketpp::log::elevel::all);
  ws.init_asio();
  ws.set_reuse_addr(true);
  ws.set_listen_backlog(64);
  ws.set_open_handshake_timeout(static_cast<long>(m.opt.handshake_timeout_ms));
  ws.set_close_handshake_timeout(1000);
  ws.set_max_message_size(kMaxIncomingBytes);
  ws.set_max_http_body_size(kMaxIncomingBytes);
  ws.set_socket_init_handler([&m](const Hdl& h, boost::asio::ip::tcp::socket& s) { m.on_socket_init(h, s); });
  ws.set_http_handler([&m](const Hdl& h) { m.on_http(h); });
  ws.set_validate_handler([&m](const Hdl& h) { return m.on_validate(h); });
  ws.set_open_handler([&m](const Hdl& h) { m.on_open(h); });
  ws.set_close_handler([&m](const Hdl& h) { m.on_close(h); });
  ws.set_fail_handler([&m](const Hdl& h) { m.on_fail(h); });
  ws.set_message_handler([&m](const Hdl& h, const WsServer::message_ptr& msg) { m.on_message(h, msg); });
  websocketpp::lib::error_code ec;
  ws.listen(m.opt.address, std::to_string(m.opt.port), ec);
  if (ec) {
    throw std::runtime_error("viewer: cannot listen on " + m.opt.address + ":" + std::to_string(m.opt.port) +
                             ": " + ec.message());
  }
  ws.start_accept(ec);
  if (ec) throw std::runtime_error("viewer: cannot accept on " + m.opt.address + ": " + ec.message());
  boost::system::error_code aec;
  m.bound_port = ws.get_local_endpoint(aec).port();
  m.schedule_tick();
  rt::ThreadSetupReport report;
  m.thread = rt::start_thread(
      spec,
      [&m] {
        // Below every pipeline thread: the viewer takes what CPU is left.
        setpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)), 10);
        for (;;) {
          try {
            m.ws.run();
            break;
          } catch (const std::exception&) {
            // A handler threw (a socket vanished mid-call): serve on.
            if (m.stopping.load()) break;
          }
        }
      },
      &report);
  std::lock_guard<std::mutex> lock(m.stats_mu);
  m.st.thread = rt::to_string(report) + ", nice 10";
  return report;
}

void Server::stop() {
  Impl& m = *impl_;
  if (!m.thread.joinable()) return;
  m.stopping.store(true);
  m.ws.get_io_service().post([&m] { m.shutdown_io(); });
  // Let the close frames go out, then stop whatever is still open.
  const int64_t deadline = rt::now_ns() + 500'000'000;
  while (clients() > 0 && rt::now_ns() < deadline) rt::sleep_for_ns(10'000'000);
  m.ws.stop();
  m.thread.join();
}

uint16_t Server::port() const { return impl_->bound_port; }

std::string Server::url() const {
  const std::string host =
      impl_->opt.address == "0.0.0.0" || impl_->opt.address == "::" ? "<this machine>" : impl_->opt.address;
  return "http://" + host + ":" + std::to_string(impl_->bound_port) + "/";
}

void Server::add_pose(int64_t t_ns, const Eigen::Vector3d& p, const Eigen::Quaterniond& /*q*/,
                      core::TrackingQuality quality) {
  PendingPose pp{t_ns,
                 {static_cast<float>(p.x()), static_cast<float>(p.y()), static_cast<float>(p.z())},
                 static_cast<float>(quality)};
  (void)impl_->pending_poses->try_push(pp);  // full (viewer thread stalled for seconds): dropped, counted
}

void Server::mark_finished(const std::string& summary) {
  std::lock_guard<std::mutex> lock(impl_->pose_mu);
  impl_->finished = summary.empty() ? std::string("finished") : summary;
}

bool Server::wait_for_client(int64_t timeout_ns) {
  Impl& m = *impl_;
  std::unique_lock<std::mutex> lock(m.stats_mu);
  return m.client_cv.wait_for(lock, std::chrono::nanoseconds(timeout_ns), [&m] { return m.n_clients > 0; });
}

int Server::clients() const {
  std::lock_guard<std::mutex> lock(impl_->stats_mu);
  return impl_->n_clients;
}

ServerStats Server::stats() const {
  std::lock_guard<std::mutex> lock(impl_->stats_mu);
  ServerStats s = impl_->st;
  s.poses_dropped = impl_->pending_poses->drops();
  return s;
}

std::string stats_summary(const ServerStats& s) {
  char buf[512];
  const double kbps = s.streaming_s > 0 ? 1e-3 * static_cast<double>(s.streaming_bytes) / s.streaming_s : 0;
  const double cpu = s.streaming_s > 0 ? 1000.0 * s.streaming_cpu_s / s.streaming_s : 0;
  std::snprintf(
      buf, sizeof buf,
      "viewer: %llu browser(s) (peak %d), streamed %.1f s at %.1f kB/s, kst-viewer %.1f ms CPU per s; "
      "frames sent %llu, skipped %llu (budget) %llu (backlog); refused %llu connections %llu browsers\n",
      static_cast<unsigned long long>(s.clients), s.clients_peak, s.streaming_s, kbps, cpu,
      static_cast<unsigned long long>(s.frames_sent),
      static_cast<unsigned long long>(s.frames_skipped_budget),
      static_cast<unsigned long long>(s.frames_skipped_backlog),
      static_cast<unsigned long long>(s.connections_refused),
      static_cast<unsigned long long>(s.clients_refused));
  std::string out = buf;
  if (s.dense_messages > 0 || s.dense_resyncs > 0) {
    std::snprintf(buf, sizeof buf,
                  "viewer dense map: %llu messages, %.1f kB sent (summed over browsers), %llu resyncs\n",
                  static_cast<unsigned long long>(s.dense_messages),
                  1e-3 * static_cast<double>(s.dense_bytes),
                  static_cast<unsigned long long>(s.dense_resyncs));
    out += buf;
  }
  return out;
}

}  // namespace kestrel::viewer

// The live viewer's server (docs/viewer.md): HTTP for one page and its
// scripts, a WebSocket stream of the estimator's snapshots, on one thread of
// its own (kst-viewer, SCHED_OTHER at nice 10) built on websocketpp's
// asynchronous asio transport. Nothing here runs on a real-time thread: it
// reads what ViewerFeed publishes, and it never makes the feed wait.
//
// Bounded cost: at most max_clients browsers stream at once and at most
// max_connections sockets are open (more are closed at once); each browser's
// stream is held under max_kbytes_per_s by skipping camera frames, a browser
// whose socket stops draining gets no frames, and one that reads nothing for
// client_timeout_ns is disconnected. Incoming messages are limited to 1 KiB
// (the page sends only pause/resume/step).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/core/estimator.hpp"
#include "kestrel/rt/perf.hpp"
#include "kestrel/rt/thread_setup.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "kestrel/viewer/binary_stream.hpp"
#include "kestrel/viewer/feed.hpp"

namespace kestrel::viewer {

struct ServerOptions {
  std::string address = "0.0.0.0";  // every interface: the browser runs on a laptop
  uint16_t port = 0;                // 0: any free port (tests; port() tells which)
  int max_clients = 4;              // browsers streaming at once; more get HTTP 503
  int max_connections = 32;         // open sockets of any kind; more are closed at once
  double max_kbytes_per_s = 1000;   // per browser [kB/s, 1 kB = 1000 bytes]
  int jpeg_quality = 75;
  int64_t client_timeout_ns = 10'000'000'000;  // a browser that drains nothing this long is dropped
  int64_t handshake_timeout_ms = 3000;  // an HTTP request or WebSocket handshake must arrive within this
  // index.html, viewer.js, viewer.css; "" = share/kestrel/viewer beside the executable's bin/.
  std::string assets_dir;
  // Debian's libjs-three: three.min.js and examples/js/controls/OrbitControls.js.
  std::string three_dir = "/usr/share/javascript/three";
  std::string title;  // what runs, shown on the page ("replay flight.klog")
};

// "[ADDR:]PORT" (PORT 0..65535, 0: any free port; ADDR a numeric address or a host name) into
// opt.address / opt.port. Throws std::invalid_argument quoting the text.
void parse_view_endpoint(const std::string& text, ServerOptions& opt);
// Where the page's files are looked for when ServerOptions::assets_dir is empty.
std::string default_assets_dir();

struct ServerStats {
  uint64_t connections = 0;          // sockets accepted
  uint64_t connections_refused = 0;  // closed at once: max_connections open
  int connections_peak = 0;
  uint64_t http_requests = 0;
  uint64_t http_errors = 0;        // 404, 405
  uint64_t handshakes_failed = 0;  // timed out, malformed, closed early
  uint64_t clients = 0;            // WebSocket viewers accepted
  uint64_t clients_refused = 0;    // max_clients reached (503) or wrong path (404)
  uint64_t clients_dropped = 0;    // read nothing for client_timeout_ns
  uint64_t protocol_errors = 0;    // malformed frames: connection failed by the server
  int clients_peak = 0;
  uint64_t commands = 0, bad_commands = 0;
  uint64_t snapshots = 0;               // taken from the feed
  uint64_t poses_dropped = 0;           // add_pose found its ring full
  uint64_t frames_sent = 0;             // camera frames, summed over browsers
  uint64_t frames_skipped_budget = 0;   // over max_kbytes_per_s
  uint64_t frames_skipped_backlog = 0;  // the browser's socket was not draining
  uint64_t bytes_sent = 0;
  uint64_t messages_sent = 0;
  // The dense map's block messages (set_dense_stream), summed over browsers; a
  // browser whose socket was backed up misses one and is sent everything again.
  uint64_t dense_messages = 0, dense_bytes = 0, dense_resyncs = 0;
  // The viewer thread's CPU and the bytes queued, over the time at least one
  // browser was connected: the figures docs/viewer.md quotes.
  double streaming_s = 0;
  double streaming_cpu_s = 0;
  uint64_t streaming_bytes = 0;
  double cpu_s = 0;    // viewer thread, whole run
  std::string thread;  // scheduling the thread got
};

class Server {
 public:
  // feed and control (nullptr: no replay controls) must outlive the server.
  Server(const ServerOptions& opt, ViewerFeed& feed, PlaybackControl* control = nullptr);
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  // Before start(): polled on the viewer thread for the IMU -> pose latency
  // panel when another thread (kst-propagate) owns that figure; it returns the
  // max since the previous call [ns].
  void set_imu_latency_probe(std::function<int64_t()> probe);
  // Before start(): the dense map's messages (docs/dense.md), forwarded as
  // they come to every browser; a browser that connects asks for all of it.
  void set_dense_stream(BinaryStream* stream);
  // Before start(): the pipeline's perf registry (rt/perf.hpp), read on the
  // viewer thread for the drops-and-faults panel and the page's table of every
  // counter; it must outlive the server. nullptr: neither.
  void set_counters(const rt::PerfRegistry* counters);

  // Loads the page's files, binds and starts the viewer thread (spec: the
  // thread table's kst-viewer). Throws std::runtime_error naming the file or
  // the address (in use, not local). Returns how the thread was set up.
  rt::ThreadSetupReport start(const rt::ThreadSpec& spec);
  // Closes every connection and joins the thread; idempotent.
  void stop();
  uint16_t port() const;
  std::string url() const;

  // ONE thread (the replay's output thread): one pose of the trajectory.
  // Lock- and allocation-free (a ring; if the viewer thread is seconds
  // behind, poses are dropped and counted in ServerStats::poses_dropped).
  void add_pose(int64_t t_ns, const Eigen::Vector3d& p_WB, const Eigen::Quaterniond& q_WB,
                core::TrackingQuality quality);
  // The run is over: the page says so and keeps what it shows.
  void mark_finished(const std::string& summary);
  // Blocks until a browser is connected or timeout_ns passed; true if one is.
  bool wait_for_client(int64_t timeout_ns);
  int clients() const;
  ServerStats stats() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// The cost figures of a run, for the replay summary ("viewer: 1 browser, ...").
std::string stats_summary(const ServerStats& s);

}  // namespace kestrel::viewer

// `kestrel run`: live drivers into the sensor rings; the IMU ring is consumed
// by the IMU-rate propagation thread (kst-propagate, imu_rate_stage.hpp, the
// same stage as realtime replay), which publishes the IMU-rate pose at once and
// forwards every sample to the estimator thread running the backend the
// config names (`estimator: backend:`, or --estimator; default window, as in
// replay). The estimator sees IMU and frames merged in time order, as in replay.
#include <atomic>
#include <iostream>
#include <csignal>
#include <cstdio>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "kestrel/commands.hpp"
#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"
#include "kestrel/drivers/camera_time_shift.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/drivers/sensor_rings.hpp"
#include "kestrel/imu_rate_stage.hpp"
#include "kestrel/recording.hpp"
#include "kestrel/mavlink/odometry_stream.hpp"
#include "kestrel/map_threads.hpp"
#include "kestrel/tools/map_files.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/mailbox.hpp"
#include "kestrel/rt/spsc_ring.hpp"
#include "kestrel/rt/thread_setup.hpp"
#include "kestrel/view_cli.hpp"
#include "kestrel/viewer/feed.hpp"
#include "kestrel/viewer/server.hpp"

namespace kestrel::cli {
namespace {

std::atomic<bool> g_run_stop{false};
extern "C" void run_on_signal(int) { g_run_stop.store(true); }

// Frames into the estimator's rings, their stamps moved onto the IMU's clock
// (the rig's time_offset_cam_imu_ns) as every log reader does; a recording
// keeps them as the driver stamped them, beside the rig that says the offset.
class RingFrameSink final : public drivers::FrameSink {
 public:
  RingFrameSink(drivers::SensorRings& r, const Rig& rig) : rings_(r), rig_(rig) {}
  bool push_frame(const drivers::CameraFrame& f) noexcept override {
    RgbdFrameMsg m;
    m.t_ns = drivers::camera_stamp_on_imu_clock(rig_, f.t_ns);
    m.t_recv_ns = f.t_recv_ns;
    m.seq = f.seq;
    m.exposure_us = f.exposure_us;
    if (!copy(*f.rgb, m.rgb_handle)) return drop();
    if (f.depth != nullptr && !copy(*f.depth, m.depth_handle)) {
      rings_.images.release(m.rgb_handle);
      return drop();
    }
    if (rings_.frames.try_push(m)) return true;
    rings_.images.release(m.rgb_handle);
    if (m.depth_handle != rt::kInvalidHandle) rings_.images.release(m.depth_handle);
    return false;
  }
  uint64_t drops = 0;

 private:
  bool drop() {
    ++drops;
    return false;
  }
  bool copy(const drivers::ImageBuffer& src, uint32_t& handle) {
    handle = rings_.images.acquire();
    if (handle == rt::kInvalidHandle) return false;
    drivers::ImageBuffer* dst = rings_.images.get(handle);
    if (dst == nullptr || src.pixels.size() > dst->pixels.capacity()) {
      rings_.images.release(handle);
      handle = rt::kInvalidHandle;
      return false;
    }
    dst->t_ns = drivers::camera_stamp_on_imu_clock(rig_, src.t_ns);
    dst->width = src.width;
    dst->height = src.height;
    dst->format = src.format;
    dst->pixels.assign(src.pixels.begin(), src.pixels.end());   // within capacity: no allocation
    return true;
  }
  drivers::SensorRings& rings_;
  const Rig& rig_;
};

struct RunArgs {
  std::string config;
  std::string estimator;
  double duration_s = 0;
  std::string mavlink_udp;
  ViewArgs view;
  std::string mavlink_serial;
  std::string record;
  std::string traj_out;
  double record_buffer_s = 4.0;
  bool print_config = false;
  std::string mapping, loop;
  std::string map_in, map_out;
};


// A frame waits for the IMU up to its time at most this long (wall clock):
// an IMU that stopped must not stall the camera.
constexpr int64_t kFrameWaitForImuNs = 50'000'000;
// Latency statistics start after this much sample time (start-up is not steady state).
constexpr int64_t kWarmupNs = 2'000'000'000;

}  // namespace

Subcommand add_run_command(CLI::App& parent) {
  auto a = std::make_shared<RunArgs>();
  CLI::App* app = parent.add_subcommand("run", "start the live drivers and the estimator");
  app->add_option("--config", a->config, "rig + drivers config (configs/*.yaml)")->required();
  app->add_option("--estimator", a->estimator,
                  std::string("backend: ") + core::estimator_names() +
                      " (default: the config's estimator.backend, else window)");
  app->add_flag("--print-config", a->print_config,
                "print the effective estimator settings as YAML (the config's estimator sections on the backend's "
                "defaults, docs/config.md) and exit");
  app->add_option("--duration", a->duration_s, "seconds to run (0 = until Ctrl-C)")->capture_default_str();
  app->add_option("--mapping", a->mapping,
                  "on|off: the map beside the backend (default on for window, off for ekf; docs/map.md)");
  app->add_option("--loop", a->loop, "on|off: loop closing and relocalisation (default on)");
  app->add_option("--map-in", a->map_in,
                  "start from this map file: nothing is mapped until the camera relocalises in it (docs/map.md)");
  app->add_option("--map-out", a->map_out, "write the map here when the run stops (docs/map.md)");
  app->add_option("--mavlink-udp", a->mavlink_udp,
                  "MAVLink v2 to the flight controller at HOST:PORT: ODOMETRY per pose, HEARTBEAT 1 Hz, TIMESYNC "
                  "(over the config's mavlink: link; docs/px4.md)");
  app->add_option("--mavlink-serial", a->mavlink_serial,
                  "the same over a serial port, DEVICE[:BAUD] (baud default: the config's mavlink.serial_baud)");
  app->add_option("--record", a->record,
                  "also record the sensors into this .klog while estimating (replay it afterwards with kestrel replay)");
  app->add_option("--record-buffer-s", a->record_buffer_s,
                  "seconds of camera frames the recorder holds while the disk stalls")
      ->capture_default_str();
  app->add_option("--traj-out", a->traj_out, "write the estimated trajectory here (TUM: t[s] x y z qx qy qz qw)");
  add_view_options(app, a->view, false);
  app->footer("Runs: live drivers -> sensor rings -> kst-propagate (IMU-rate pose at once) -> estimator thread (IMU and\n"
              "frames in time order) -> kst-optimizer; thread scheduling from the config's threads: table.\n"
              "Without the sensors it exits with 1 naming what is missing.");
  Subcommand s;
  s.app = app;
  s.run = [a] {
    const drivers::LiveConfig cfg = drivers::load_live_config(a->config, tools::estimator_config_sections());
    if (!a->estimator.empty() && !core::estimator_known(a->estimator))
      throw UsageError("unknown --estimator '" + a->estimator + "' (expected one of: " + core::estimator_names() + ")");
    // The default backend is replay's (window) unless the config or --estimator names one.
    core::EstimatorConfig est_cfg = tools::load_estimator_config(a->config, a->estimator);
    try {
      tools::apply_map_switches(est_cfg, a->mapping, a->loop);
      if (!a->map_in.empty()) tools::set_map_in(est_cfg, a->map_in);
      if (!a->map_out.empty() && !tools::may_have_map(est_cfg))
        throw std::invalid_argument(
            "--map-out needs a backend with the map (window, or ekf with --mapping on)");
    } catch (const std::invalid_argument& e) {
      throw UsageError(e.what());
    }
    if (a->print_config) {
      std::cout << tools::estimator_config_to_yaml(est_cfg);
      return 0;
    }
    std::optional<mavlink::OdometryStreamOptions> mo;
    try {
      mo = mavlink_options(cfg.mavlink, a->mavlink_udp, a->mavlink_serial);
    } catch (const std::invalid_argument& e) {
      throw UsageError(e.what());
    }
    viewer::ServerOptions view_options;
    if (!a->view.endpoint.empty()) view_options = view_server_options(a->view, "run " + a->config);
    if (!a->record.empty() && !(a->record_buffer_s > 0 && a->record_buffer_s <= 60))
      throw UsageError("--record-buffer-s must be in (0, 60] seconds");
    drivers::LiveSensors sensors(cfg);  // missing sensors are named first
    std::unique_ptr<mavlink::OdometryStream> odometry;
    if (mo) odometry = std::make_unique<mavlink::OdometryStream>(*mo);
    const size_t max_image = static_cast<size_t>(cfg.drivers.camera.width_px) * cfg.drivers.camera.height_px * 3;
    auto rings = std::make_unique<drivers::SensorRings>(max_image);
    drivers::RingImuSink<decltype(rings->imu)> imu(rings->imu);
    RingFrameSink frames(*rings, cfg.rig);
    std::unique_ptr<core::Estimator> est = core::make_estimator(est_cfg, cfg.rig);
    if (odometry && !est->world_levelled()) throw UsageError(mavlink_needs_levelled_world(est->name()));
    // Live, the optimizer always has its own thread: a solve must never hold
    // up the IMU-rate pose (docs/threads.md).
    est->set_threaded_optimizer(est->has_optimizer());
    std::printf("running %s -> estimator '%s' (%s)\n", sensors.description().c_str(), est->name(),
                a->estimator.empty() && !cfg.estimator.backend.empty() ? "from the config" : "");
    // --record: every sample also goes to the recorder (its own rings and disk
    // thread), with the stamps the drivers gave it, so the flight replays.
    std::unique_ptr<drivers::KlogLogger> recorder;
    std::unique_ptr<LoggerImuSink> rec_imu;
    std::unique_ptr<LoggerFrameSink> rec_frames;
    std::unique_ptr<TeeImuSink> tee_imu;
    std::unique_ptr<TeeFrameSink> tee_frames;
    drivers::ImuSink* imu_sink = &imu;
    drivers::FrameSink* frame_sink = &frames;
    if (!a->record.empty()) {
      recorder = make_recording_logger(cfg, a->record, a->record_buffer_s, 0);
      rec_imu = std::make_unique<LoggerImuSink>(*recorder);
      rec_frames = std::make_unique<LoggerFrameSink>(*recorder);
      tee_imu = std::make_unique<TeeImuSink>(imu, *rec_imu);
      tee_frames = std::make_unique<TeeFrameSink>(frames, *rec_frames);
      imu_sink = tee_imu.get();
      frame_sink = tee_frames.get();
      std::printf("recording the sensors to %s\n", a->record.c_str());
    }
    tools::Trajectory trajectory;
    g_run_stop.store(false);
    std::signal(SIGINT, run_on_signal);
    std::signal(SIGTERM, run_on_signal);
    std::atomic<bool> consumer_stop{false};
    std::atomic<uint64_t> frames_seen{0}, imu_seen{0};
    // Poses and the 1 Hz status leave the estimator thread without a lock or
    // an allocation; the main thread sends and prints them.
    auto poses = std::make_unique<rt::SpscRing<OutPose, 1024>>();
    auto status = std::make_unique<rt::Mailbox<PipelineStatus>>();
    // The IMU-rate pose must not wait while the estimator thread tracks a frame.
    auto est_imu = std::make_unique<ImuRing>();
    auto anchor = std::make_unique<rt::Mailbox<Anchor>>();
    auto imu_pose = std::make_unique<rt::Mailbox<OutPose>>();
    ImuRateStage propagation(rings->imu, *est_imu, *anchor, cfg.rig, kWarmupNs, *imu_pose);
    std::atomic<bool> propagation_stop{false};
    // The live viewer (docs/viewer.md): snapshots from the estimator thread, served on kst-viewer.
    std::unique_ptr<viewer::ViewerFeed> feed;
    std::unique_ptr<viewer::Server> view;
    if (!a->view.endpoint.empty()) {
      feed = std::make_unique<viewer::ViewerFeed>(*est, cfg.rig);
      view = std::make_unique<viewer::Server>(view_options, *feed);
      view->set_imu_latency_probe([&propagation] { return propagation.take_recent_max_ns(); });
    }
    // The config's thread table (`threads:`, or the defaults): a refused
    // SCHED_FIFO or CPU pin leaves the thread running, and the summary says so.
    using drivers::PipelineThread;
    std::vector<AppliedThread> applied;
    rt::ThreadSetupReport sched;
    std::thread optimizer;
    if (est->has_optimizer()) {
      optimizer = rt::start_thread(
          cfg.threads[PipelineThread::kOptimizer],
          [&] {
            while (!consumer_stop.load(std::memory_order_relaxed))
              if (!est->optimizer_step()) rt::sleep_for_ns(500'000);
          },
          &sched);
      applied.push_back(applied_thread(cfg.threads[PipelineThread::kOptimizer], sched));
    }
    // The map, when the backend has one: kst-mapping and kst-loop (never waited for live).
    MapThreads map_threads(*est, cfg.threads, applied);
    std::thread consumer = rt::start_thread(cfg.threads[PipelineThread::kEstimator], [&] {
      int64_t last_imu_t_ns = -1;
      int64_t frame_waiting_since_ns = -1;
      int64_t last_frame_t_ns = -1, last_pose_t_ns = -1, first_t_ns = -1, next_status_ns = 0;
      int64_t track_max_ns = 0, imu_max_ns = 0;
      uint64_t frames_at_status = 0;
      Eigen::Vector3d gyro = Eigen::Vector3d::Zero();
      auto emit = [&](int64_t now_t_ns) {
        const core::EstimatorOutput& o = est->output();
        if (o.quality == core::TrackingQuality::kUninitialized) return;
        OutPose p{};
        p.t_ns = o.state.t_ns;
        for (int i = 0; i < 3; ++i) {
          p.p[i] = o.state.p_WB[i];
          p.v[i] = o.state.v_WB[i];
          p.w[i] = gyro[i] - o.state.bg_rps[i];
        }
        p.q[0] = o.state.q_WB.w();
        p.q[1] = o.state.q_WB.x();
        p.q[2] = o.state.q_WB.y();
        p.q[3] = o.state.q_WB.z();
        p.quality = o.quality;
        // No frame for 150 ms: the pose is IMU propagation, whatever the backend last said.
        if (p.quality == core::TrackingQuality::kTracking && (last_frame_t_ns < 0 || now_t_ns - last_frame_t_ns > 150'000'000))
          p.quality = core::TrackingQuality::kImuOnly;
        p.reset_counter = o.reset_counter;
        set_covariance(p, o.pose_cov);
        (void)poses->try_push(p);   // full: counted in drops(), reported at the end
        last_pose_t_ns = now_t_ns;
      };
      auto maybe_status = [&](int64_t t_ns) {
        if (first_t_ns < 0) {
          first_t_ns = t_ns;
          next_status_ns = t_ns + 1'000'000'000;
        }
        if (t_ns < next_status_ns) return;
        while (next_status_ns <= t_ns) next_status_ns += 1'000'000'000;
        PipelineStatus st;
        st.t_ns = t_ns;
        st.t_s = 1e-9 * static_cast<double>(t_ns - first_t_ns);
        st.quality = est->output().quality;
        st.reset_counter = est->output().reset_counter;
        st.map = est->output().map;
        frame_stats(*est, st.features, st.inliers);
        st.frames_total = frames_seen.load(std::memory_order_relaxed);
        st.frames_in_window = st.frames_total - frames_at_status;
        frames_at_status = st.frames_total;
        st.tracking_max_ns = track_max_ns;
        st.imu_to_output_max_ns = imu_max_ns;
        track_max_ns = imu_max_ns = 0;
        st.imu_ring_drops = rings->imu.drops();
        st.frame_ring_drops = rings->frames.drops() + frames.drops;
        const core::ImuRejectCounts& r = est->counters().imu_rejects;
        st.imu_rejected = r.non_finite + r.saturated + r.out_of_order;
        st.imu_gaps = r.gaps;
        st.input_faults.imu_gaps = r.gaps;
        status->publish(st);
      };
      while (!consumer_stop.load(std::memory_order_relaxed)) {
        bool any = false;
        for (;;) {
          ImuSample* s = est_imu->front();
          RgbdFrameMsg* m = rings->frames.front();
          if (s != nullptr && (m == nullptr || s->t_ns <= m->t_ns)) {
            maybe_status(s->t_ns);
            if (est->add_imu(*s)) {
              anchor->publish(to_anchor(est->output()));
              // From the driver's receive stamp to the estimator's own pose
              // (the IMU-rate pose of kst-propagate is faster: summary).
              const int64_t lat = rt::now_ns() - s->t_recv_ns;
              if (lat > imu_max_ns) imu_max_ns = lat;
              gyro = Eigen::Vector3d(s->gyro_rps[0], s->gyro_rps[1], s->gyro_rps[2]);
              if ((last_frame_t_ns < 0 || s->t_ns - last_frame_t_ns > 150'000'000) &&
                  (last_pose_t_ns < 0 || s->t_ns - last_pose_t_ns >= 50'000'000))
                emit(s->t_ns);
            }
            imu_seen.fetch_add(1, std::memory_order_relaxed);
            last_imu_t_ns = s->t_ns;
            est_imu->pop();
            any = true;
            continue;
          }
          if (m == nullptr) break;
          // The frame goes once the IMU has passed its time (the estimator
          // propagates to the exposure), or after a bounded wait.
          const int64_t now = rt::now_ns();
          if (frame_waiting_since_ns < 0) frame_waiting_since_ns = now;
          if (s == nullptr && last_imu_t_ns < m->t_ns && now - frame_waiting_since_ns < kFrameWaitForImuNs) break;
          frame_waiting_since_ns = -1;
          core::RgbdFrame f;
          f.t_ns = m->t_ns;
          f.seq = m->seq;
          if (const auto* b = rings->images.get(m->rgb_handle)) f.rgb = b->view();
          if (const auto* b = rings->images.get(m->depth_handle)) f.depth = b->view();
          const int64_t t_track0 = rt::now_ns();
          est->add_frame(f);
          anchor->publish(to_anchor(est->output()));
          const int64_t t_track = rt::now_ns() - t_track0;
          if (t_track > track_max_ns) track_max_ns = t_track;
          if (feed) {
            viewer::FrameInfo vi;
            vi.tracking_ns = t_track;
            vi.frames_fed = frames_seen.load(std::memory_order_relaxed) + 1;
            vi.imu_ring_drops = rings->imu.drops();
            vi.frame_ring_drops = rings->frames.drops() + frames.drops;
            vi.imu_gaps = est->counters().imu_rejects.gaps;
            feed->on_frame(f, vi);
          }
          last_frame_t_ns = m->t_ns;
          emit(m->t_ns);
          rings->images.release(m->rgb_handle);
          if (m->depth_handle != rt::kInvalidHandle) rings->images.release(m->depth_handle);
          rings->frames.pop();
          frames_seen.fetch_add(1, std::memory_order_relaxed);
          any = true;
        }
        if (!any) rt::sleep_for_ns(1'000'000);
      }
    }, &sched);
    applied.push_back(applied_thread(cfg.threads[PipelineThread::kEstimator], sched));
    std::thread propagator = rt::start_thread(
        cfg.threads[PipelineThread::kPropagate],
        [&] {
          // Sleeps 100 us when idle rather than spinning (docs/threads.md).
          while (!propagation_stop.load(std::memory_order_relaxed))
            if (!propagation.step()) rt::sleep_for_ns(100'000);
          propagation.finish();
        },
        &sched);
    applied.push_back(applied_thread(cfg.threads[PipelineThread::kPropagate], sched));
    if (view) {
      applied.push_back(
          applied_thread(cfg.threads[PipelineThread::kViewer], view->start(cfg.threads[PipelineThread::kViewer])));
      print_view_ready(*view, a->view);
    }
    uint64_t imu_rate_poses = 0, imu_pose_version = 0;
    const int64_t t0 = rt::now_ns();
    sensors.start(*imu_sink, *frame_sink);
    for (const auto& [spec, rep] : sensors.thread_reports()) applied.push_back(applied_thread(spec, rep));
    std::printf("thread table (%s):\n%s", cfg.threads.from_config ? "from the config" : "built-in defaults",
                threads_summary(applied).c_str());
    int64_t next_print = t0 + 1'000'000'000;
    uint64_t status_version = 0;
    while (!g_run_stop.load() && (a->duration_s <= 0 || rt::now_ns() - t0 < static_cast<int64_t>(a->duration_s * 1e9))) {
      rt::sleep_for_ns(2'000'000);
      if (imu_pose->version() != imu_pose_version) {
        OutPose o{};
        if (imu_pose->read(o, &imu_pose_version)) ++imu_rate_poses;
      }
      if (odometry) odometry->service(rt::now_ns());
      OutPose p;
      while (poses->try_pop(p)) {
        const PoseSample ps = pose_sample_of(p);
        if (view) view->add_pose(ps.t_ns, ps.p_WB, ps.q_WB, ps.quality);
        if (!a->traj_out.empty() && ps.quality != core::TrackingQuality::kLost) {  // as replay: lost poses are not estimates
          tools::TimedPose tp;
          tp.t_ns = ps.t_ns;
          tp.p = ps.p_WB;
          tp.q = ps.q_WB;
          trajectory.push_back(tp);
        }
        if (odometry) odometry->publish(odometry_input_of(ps));
      }
      if (rt::now_ns() >= next_print) {
        next_print += 1'000'000'000;
        PipelineStatus st;
        uint64_t v = 0;
        if (status->read(st, &v) && v != status_version) {
          status_version = v;
          std::printf("%s\n", format_status(st).c_str());
        } else {
          // No sample reached the estimator in the last second: say what arrives at all.
          std::printf("t=%5.1f s  imu %llu  frames %llu  ring drops imu %llu frames %llu\n", (rt::now_ns() - t0) * 1e-9,
                      (unsigned long long)imu_seen.load(), (unsigned long long)frames_seen.load(),
                      (unsigned long long)rings->imu.drops(), (unsigned long long)(rings->frames.drops() + frames.drops));
        }
        std::fflush(stdout);
      }
    }
    sensors.stop();
    if (recorder) {
      recorder->stop();
      applied.push_back(applied_thread(recorder->thread_spec(), recorder->thread_report()));
    }
    propagation_stop.store(true);
    propagator.join();
    consumer_stop.store(true);
    consumer.join();
    if (optimizer.joinable()) optimizer.join();
    if (view) {
      view->mark_finished("kestrel run stopped");
      view->stop();
    }
    map_threads.stop();
    if (!a->map_out.empty()) {
      tools::write_map_file(a->map_out, est->save_map());
      std::printf("map: %s\n", a->map_out.c_str());
    }
    std::signal(SIGINT, SIG_DFL);
    std::signal(SIGTERM, SIG_DFL);
    std::printf("%s", sensors.report().c_str());
    std::printf("%s", threads_summary(applied).c_str());
    const ImuRateStats& ps = propagation.stats();
    if (ps.imu_to_output.count() > 0) {
      std::printf("IMU-rate pose (kst-propagate): %llu published, %llu taken by the output thread; driver receive -> "
                  "pose p50 %.3f ms, p99 %.3f ms, max %.3f ms; %llu forward drops\n",
                  (unsigned long long)ps.poses, (unsigned long long)imu_rate_poses,
                  1e-6 * static_cast<double>(ps.imu_to_output.percentile(50)),
                  1e-6 * static_cast<double>(ps.imu_to_output.percentile(99)),
                  1e-6 * static_cast<double>(ps.imu_to_output.max()), (unsigned long long)ps.forward_drops);
    } else {
      std::printf("IMU-rate pose (kst-propagate): %llu published (none after the %.0f s warm-up); %llu forward drops\n",
                  (unsigned long long)ps.poses, 1e-9 * static_cast<double>(kWarmupNs),
                  (unsigned long long)ps.forward_drops);
    }
    if (view) std::printf("%s", viewer::stats_summary(view->stats()).c_str());
    if (odometry)
      std::printf("MAVLink to %s: ODOMETRY %llu sent, %llu failed, %llu pose-ring drops; HEARTBEAT %llu; TIMESYNC %s "
                  "(%llu requests answered)\n",
                  odometry->endpoint().c_str(), (unsigned long long)odometry->stream_stats().odometry_sent,
                  (unsigned long long)odometry->stats().failed, (unsigned long long)poses->drops(),
                  (unsigned long long)odometry->stream_stats().heartbeats_sent,
                  odometry->time_sync().converged()
                      ? ("converged, autopilot clock - ours " +
                         std::to_string(1e-6 * static_cast<double>(odometry->time_sync().offset_ns())) + " ms")
                            .c_str()
                      : "no answer from an autopilot",
                  (unsigned long long)odometry->time_sync().stats().requests_answered);
    if (odometry && odometry->signing_stats() != nullptr)
      std::printf("MAVLink signing on: %llu signed frames sent, %llu frames from the autopilot refused\n",
                  (unsigned long long)odometry->signing_stats()->signed_sent,
                  (unsigned long long)odometry->decoder_stats().unauthenticated);
    if (recorder) {
      std::printf("%s", recording_summary(*recorder).c_str());
      if (!recorder->error().empty()) std::fprintf(stderr, "kestrel run: recording: %s\n", recorder->error().c_str());
    }
    if (!a->traj_out.empty()) {
      tools::write_tum(a->traj_out, trajectory);
      std::printf("trajectory: %s (%zu poses)\n", a->traj_out.c_str(), trajectory.size());
    }
    const auto& c = est->counters();
    const auto& o = est->output();
    std::printf("estimator %s: imu %llu used of %llu, frames %llu used of %llu, resets %llu; last pose t=%.3f s "
                "p_WB (%.3f, %.3f, %.3f) m\n",
                est->name(), (unsigned long long)c.imu_used, (unsigned long long)c.imu_in,
                (unsigned long long)c.frames_used, (unsigned long long)c.frames_in, (unsigned long long)c.resets,
                o.state.t_ns * 1e-9, o.state.p_WB.x(), o.state.p_WB.y(), o.state.p_WB.z());
    if (!est->backend_summary().empty()) std::printf("%s\n", est->backend_summary().c_str());
    return 0;
  };
  return s;
}

}  // namespace kestrel::cli

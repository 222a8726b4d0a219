#include "kestrel/replay_runner.hpp"

#include <sys/resource.h>
#include <time.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <memory>
#include <stdexcept>
#include <thread>

#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/core/frontend_odometry.hpp"
#include "kestrel/core/rgbd_estimator.hpp"
#include "kestrel/core/stereo_matcher.hpp"
#include "kestrel/core/tracker.hpp"
#include "kestrel/core/window_estimator.hpp"
#include "kestrel/dense/dense_files.hpp"
#include "kestrel/drivers/camera_time_shift.hpp"
#include "kestrel/drivers/mavlink/serial_link.hpp"
#include "kestrel/drivers/mavlink/udp_sender.hpp"
#include "kestrel/drivers/open_log.hpp"
#include "kestrel/drivers/stereo_rectifier.hpp"
#include "kestrel/imu_rate_stage.hpp"
#include "kestrel/map_threads.hpp"
#include "kestrel/mavlink/odometry_stream.hpp"
#include "kestrel/pipeline_counters.hpp"
#include "kestrel/rt/alloc_counter.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/history_ring.hpp"
#include "kestrel/rt/mailbox.hpp"
#include "kestrel/rt/spsc_ring.hpp"
#include "kestrel/rt/thread_setup.hpp"
#include "kestrel/tools/map_files.hpp"
#include "kestrel/tools/report_json.hpp"

namespace kestrel::cli {

namespace {
// kst-dense's messages into the viewer's stream: the two libraries know
// nothing of each other, the pipeline joins them here.
class DenseToViewer final : public dense::DenseViewSink {
 public:
  explicit DenseToViewer(viewer::BinaryStream& s) : s_(s) {}
  bool wanted() override { return s_.wanted(); }
  bool take_resend_request() override { return s_.take_resend_request(); }
  uint8_t* acquire(std::size_t* capacity) override { return s_.acquire(capacity); }
  void publish(std::size_t bytes) override { s_.publish(bytes); }

 private:
  viewer::BinaryStream& s_;
};
// A viewer message slot: the encoder stops a round at this size (the largest
// block is ~9 kB), so one message is a few blocks to a few hundred.
constexpr std::size_t kDenseViewSlotBytes = 64 * 1024;
}  // namespace

namespace {

constexpr std::size_t kOutRingCapacity = 16384;
// Live, the output thread also services MAVLink (HEARTBEAT, TIMESYNC) and
// watches for the stop: it sleeps at most this long.
constexpr int64_t kLiveOutputWaitNs = 20'000'000;

double thread_cpu_s() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

double process_cpu_s() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

double peak_rss_mb() {
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  return static_cast<double>(ru.ru_maxrss) / 1024.0;  // ru_maxrss is in KiB on Linux
}

std::size_t max_image_bytes_for(const Rig& rig) {
  // Three bytes a pixel covers colour and (two-byte) depth alike. A rig without
  // a size (some public datasets) gets VGA; bigger images are counted and dropped.
  const std::size_t w = rig.rgb.width > 0 ? static_cast<std::size_t>(rig.rgb.width) : 640;
  const std::size_t h = rig.rgb.height > 0 ? static_cast<std::size_t>(rig.rgb.height) : 480;
  return w * h * 3;
}

// A cheap fingerprint of an image: 256 bytes spread over it. Equal
// fingerprints on consecutive frames mean a frozen camera (sensor noise makes
// two real exposures differ).
uint64_t image_fingerprint(const ImageView& v) {
  if (v.data == nullptr || v.height <= 0 || v.stride_bytes <= 0) return 0;
  uint64_t h = 1469598103934665603ull;
  const int64_t total = static_cast<int64_t>(v.height) * v.stride_bytes;
  for (int i = 0; i < 256; ++i) {
    const int64_t off = (total * (2 * i + 1)) / 512;
    h = (h ^ v.data[off]) * 1099511628211ull;
  }
  return h;
}

// Share of valid depth in a sparse sample of the image.
double depth_valid_share(const ImageView& v) {
  if (v.data == nullptr || v.format != PixelFormat::kDepthU16 || v.width <= 0 || v.height <= 0) return 0;
  int valid = 0, n = 0;
  for (int y = v.height / 16; y<v.height; y += v.height / 8> 0 ? v.height / 8 : 1) {
    const auto* row = reinterpret_cast<const uint16_t*>(v.data + static_cast<int64_t>(y) * v.stride_bytes);
    for (int x = v.width / 32; x<v.width; x += v.width / 16> 0 ? v.width / 16 : 1) {
      valid += row[x] != 0;
      ++n;
    }
  }
  return n > 0 ? static_cast<double>(valid) / n : 0;
}

// The estimator side of the harness. In lockstep it is called from the
// feeder's thread after every step; otherwise it is the estimator thread.
class EstimatorStage {
 public:
  // imu: the ring this stage takes IMU samples from (the sensor ring, or the
  // propagation stage's forward ring); anchor: where to publish the state for
  // the propagation stage (nullptr: no such stage, this thread is the output).
  // feed: the live viewer's hand-off (nullptr: no viewer).
  EstimatorStage(core::Estimator& est, drivers::SensorRings& rings, ImuRing& imu,
                 rt::SpscRing<core::PoseSample, kOutRingCapacity>& out, rt::Mailbox<PipelineStatus>& status,
                 rt::Mailbox<Anchor>* anchor, const ReplayOptions& opt, const Rig& rig, ReplayReport& report,
                 PipelineCounters& counters, viewer::ViewerFeed* feed, MapTopicsFeed* map_feed)
      : est_(est),
        rings_(rings),
        imu_(imu),
        out_(out),
        status_(status),
        anchor_(anchor),
        opt_(opt),
        report_(report),
        c_(counters),
        feed_(feed),
        map_feed_(map_feed) {
    frame_period_ns_ = rig.camera_rate_hz > 0 ? static_cast<int64_t>(1e9 / rig.camera_rate_hz) : 0;
    imu_gap_ns_ = rig.imu_rate_hz > 0 ? static_cast<int64_t>(5e9 / rig.imu_rate_hz) : 50'000'000;
    has_imu_ = rig.imu_rate_hz > 0;
  }

  // A stereo rig: each pair is rectified here, on this thread, before tracking.
  void set_stereo(drivers::StereoRectifier* s) { stereo_ = s; }

  // Processes what the rings hold; true when it took anything. `feeder_done`
  // lets a frame go ahead of the IMU samples that would normally follow it.
  bool drain(bool feeder_done, bool lockstep) {
    bool took = false;
    for (;;) {
      ImuSample* s = imu_.front();
      RgbdFrameMsg* f = rings_.frames.front();
      if (s != nullptr && (f == nullptr || s->t_ns <= f->t_ns)) {
        on_imu(*s);
        imu_.pop();
        took = true;
        continue;
      }
      if (f != nullptr) {
        // A frame waits for the IMU up to its time, so the estimator sees
        // the two streams merged in time order. The wait ends as soon as a
        // newer frame is queued (records come in time order: no sample can
        // still come before this frame; an IMU that stopped in flight must
        // not hold the camera back), and never starts for a log without an
        // IMU (the rgbd backend).
        // Live, it also ends after opt_.max_frame_wait_for_imu_ns on the wall
        // clock: an IMU that stopped must not hold the last frame either.
        bool waited_enough = false;
        if (opt_.live) {
          const int64_t now = rt::now_ns();
          if (frame_wait_since_ns_ < 0) frame_wait_since_ns_ = now;
          waited_enough = now - frame_wait_since_ns_ >= opt_.max_frame_wait_for_imu_ns;
        }
        if (s != nullptr || lockstep || feeder_done || last_imu_t_ns_ >= f->t_ns || !has_imu_ ||
            rings_.frames.size() > 1 || waited_enough) {
          frame_wait_since_ns_ = -1;
          on_frame(*f);
          rings_.frames.pop();
          took = true;
          continue;
        }
      }
      // A fast-pace feeder may be asleep on a full ring.
      if (took) rings_.space_bell.ring();
      return took;
    }
  }

  void finish() {
    if (counting_)
      report_.steady_allocs = static_cast<int64_t>(rt::alloc_count_this_thread() - allocs_at_warmup_);
    c_.mirror_estimator(est_.counters(), est_.view());
  }

  uint64_t frames_fed() const { return frames_fed_; }
  PipelineCounters& counters() { return c_; }
  // The map's threads, woken after each frame (set before any frame).
  void set_map_threads(MapThreads* m) { map_ = m; }
  // The dense map's hand-off, offered every tracked frame (set before any frame).
  void set_dense(dense::DenseMapper* d) { dense_ = d->enabled() ? d : nullptr; }
  // CPU the backend's own calls took on this thread. The thread's total also
  // holds the harness: the fast pace's busy-yield while the feeder decodes,
  // the deterministic paces' wait for the map, the lockstep's log reading.
  double work_cpu_s() const { return work_cpu_s_; }

 private:
  void maybe_start_steady_state(int64_t t_ns) {
    if (t_ns > newest_t_ns_) newest_t_ns_ = t_ns;
    if (first_t_ns_ < 0) {
      first_t_ns_ = t_ns;
      next_status_t_ns_ = t_ns + kStatusPeriodNs;
    }
    if (t_ns >= next_status_t_ns_) publish_status(t_ns);
    if (!counting_ && t_ns - first_t_ns_ >= opt_.warmup_ns) {
      counting_ = true;
      allocs_at_warmup_ = rt::alloc_count_this_thread();
    }
  }

  // Plain data copied into a mailbox: no allocation, no lock.
  void publish_status(int64_t t_ns) {
    while (next_status_t_ns_ <= t_ns) next_status_t_ns_ += kStatusPeriodNs;
    PipelineStatus st;
    st.t_ns = t_ns;
    st.t_s = 1e-9 * static_cast<double>(t_ns - first_t_ns_);
    const core::EstimatorOutput& o = est_.output();
    st.quality = o.quality;
    st.reset_counter = o.reset_counter;
    st.map = o.map;
    frame_stats(est_, st.features, st.inliers);
    st.frames_total = frames_fed_;
    st.frames_in_window = frames_fed_ - frames_at_last_status_;
    frames_at_last_status_ = frames_fed_;
    st.tracking_max_ns = window_tracking_max_ns_;
    st.imu_to_output_max_ns = window_imu_max_ns_;
    window_tracking_max_ns_ = window_imu_max_ns_ = 0;
    // The rings' refused pushes so far (the final figure, set after the run,
    // is what the feeder lost: pipeline_counters.hpp).
    c_.imu_ring_drops->set(rings_.imu.drops());
    c_.frame_ring_drops->set(rings_.frames.drops());
    c_.mirror_estimator(est_.counters(), est_.view());
    status_.publish(st);
  }

  void emit(const core::EstimatorOutput& o) {
    core::PoseSample p = core::pose_sample_of(o.state, last_gyro_rps_);
    p.quality = o.quality;
    // A backend that tracked the last frame it saw says kTracking until the
    // next one; when frames stop reaching it (camera silent, frozen, withheld)
    // the pipeline says what is true: the pose is IMU propagation.
    const int64_t stale_ns =
        frame_period_ns_ > 0 ? std::max<int64_t>(3 * frame_period_ns_, 150'000'000) : 150'000'000;
    if (p.quality == core::TrackingQuality::kTracking && last_frame_t_ns_ >= 0 &&
        newest_t_ns_ - last_frame_t_ns_ > stale_ns)
      p.quality = core::TrackingQuality::kImuOnly;
    p.reset_counter = o.reset_counter;
    p.set_covariance(o.pose_cov);
    p.map = o.map;
    if (!out_.try_push(p)) c_.output_ring_drops->inc();
    last_out_t_ns_ = p.t_ns;
  }

  void on_imu(const ImuSample& s) {
    maybe_start_steady_state(s.t_ns);
    if (last_imu_t_ns_ >= 0 && s.t_ns - last_imu_t_ns_ > imu_gap_ns_) c_.imu_gaps->inc();
    if (s.t_ns > last_imu_t_ns_) last_imu_t_ns_ = s.t_ns;
    // In realtime pace the sample waited in the ring only as long as a live
    // one would, so latency counts from the push. In fast and lockstep pace
    // the feeder runs ahead on purpose; there only the estimator's own time
    // from taking the sample to its pose means anything.
    // The CPU clock is a system call: read outside the latency's span.
    const double cpu0 = thread_cpu_s();
    const int64_t t_start = opt_.pace == drivers::ReplayPace::kRealtime ? s.t_recv_ns : rt::now_ns();
    const bool posed = est_.add_imu(s);
    const int64_t latency = rt::now_ns() - t_start;
    work_cpu_s_ += thread_cpu_s() - cpu0;
    if (!posed) return;
    if (anchor_ != nullptr) {
      anchor_->publish(to_anchor(est_.output()));
      if (counting_) report_.estimator_imu_latency.record(latency);
    } else if (counting_) {
      report_.imu_to_output.record(latency);
    }
    if (latency > window_imu_max_ns_) window_imu_max_ns_ = latency;
    if (latency > imu_max_since_frame_ns_) imu_max_since_frame_ns_ = latency;
    last_gyro_rps_ = s.gyro_rps;
    // Without a camera the trajectory is sampled from the IMU-rate output.
    const bool camera_silent =
        last_frame_t_ns_ < 0 || s.t_ns - last_frame_t_ns_ > opt_.camera_silent_after_ns;
    if (camera_silent && (last_out_t_ns_ < 0 || s.t_ns - last_out_t_ns_ >= opt_.imu_only_output_period_ns)) {
      emit(est_.output());
    }
  }

  void on_frame(const RgbdFrameMsg& m) {
    maybe_start_steady_state(m.t_ns);
    core::RgbdFrame f;
    f.t_ns = m.t_ns;
    f.seq = m.seq;
    if (const drivers::ImageBuffer* b = rings_.images.get(m.rgb_handle)) f.rgb = b->view();
    if (const drivers::ImageBuffer* b = rings_.images.get(m.depth_handle)) f.depth = b->view();
    if (const drivers::ImageBuffer* b = rings_.images.get(m.right_handle)) f.right = b->view();
    if (screen(f)) {
      last_frame_t_ns_ = m.t_ns;
      const double cpu0 = thread_cpu_s();
      const int64_t t0 = rt::now_ns();
      if (stereo_ != nullptr) {
        // Rectification is part of the frame's tracking cost (it runs here, as it will on the vehicle).
        ImageView l, r;
        stereo_->rectify(f.rgb, f.right, &l, &r);
        f.rgb = l;
        f.right = r;
      }
      est_.add_frame(f);
      const int64_t t1 = rt::now_ns();
      work_cpu_s_ += thread_cpu_s() - cpu0;
      c_.add_frame->add_elapsed(t1 - t0);
      c_.mirror_estimator(est_.counters(), est_.view());
      // Deterministic paces let the map finish the keyframe just handed over
      // (the mapping and loop threads run it), so the next frame sees its
      // result at the same point on every run; realtime never waits.
      if (map_ != nullptr) {
        map_->wake();
        if (opt_.pace != drivers::ReplayPace::kRealtime) map_->wait_idle();
      }
      if (anchor_ != nullptr) anchor_->publish(to_anchor(est_.output()));
      if (dense_ != nullptr && est_.output().map.active && est_.output().map.localized)
        dense_->note_correction(m.t_ns, est_.output().map.alignment, est_.output().map.T_map_odom());
      if (dense_ != nullptr && (est_.output().quality == core::TrackingQuality::kTracking ||
                                est_.output().quality == core::TrackingQuality::kVisionOnly)) {
        // The pose --traj-out gets for this frame: the map is in the trajectory's frame W.
        const core::NavState& st = est_.output().state;
        Eigen::Isometry3d T_WB = Eigen::Isometry3d::Identity();
        T_WB.linear() = st.q_WB.normalized().toRotationMatrix();
        T_WB.translation() = st.p_WB;
        dense_->offer(m.t_ns, f.rgb, f.depth, T_WB);
      }
      ++frames_fed_;
      if (t1 - t0 > window_tracking_max_ns_) window_tracking_max_ns_ = t1 - t0;
      if (counting_) {
        report_.tracking.record(t1 - t0);
        ++report_.steady_frames;
      }
      if (feed_ != nullptr) publish_view(f, t1 - t0);
      if (map_feed_ != nullptr) map_feed_->on_frame(f.t_ns);
    }
    if (m.rgb_handle != rt::kInvalidHandle) rings_.images.release(m.rgb_handle);
    if (m.depth_handle != rt::kInvalidHandle) rings_.images.release(m.depth_handle);
    if (m.right_handle != rt::kInvalidHandle) rings_.images.release(m.right_handle);
    if (est_.output().quality != core::TrackingQuality::kUninitialized) emit(est_.output());
  }

  // The live viewer's snapshot: copies only, into memory sized at start-up.
  void publish_view(const core::RgbdFrame& f, int64_t tracking_ns) {
    viewer::FrameInfo vi;
    vi.tracking_ns = tracking_ns;
    vi.imu_to_pose_max_ns = imu_max_since_frame_ns_;
    imu_max_since_frame_ns_ = 0;
    vi.frames_fed = frames_fed_;
    feed_->on_frame(f, vi);
  }

  // Counts camera faults; false withholds the frame from the estimator.
  bool screen(const core::RgbdFrame& f) {
    if (last_frame_t_ns_ >= 0 && f.t_ns <= last_frame_t_ns_) {
      c_.frames_out_of_order->inc();
      return false;
    }
    const uint64_t fp = image_fingerprint(f.rgb);
    if (fp != 0 && fp == last_fingerprint_) {
      c_.frames_repeated->inc();
      return false;
    }
    last_fingerprint_ = fp;
    if (last_frame_t_ns_ >= 0 && frame_period_ns_ > 0 &&
        f.t_ns - last_frame_t_ns_ > frame_period_ns_ * 3 / 2) {
      c_.frames_missing->inc(
          static_cast<uint64_t>((f.t_ns - last_frame_t_ns_ + frame_period_ns_ / 2) / frame_period_ns_) - 1);
    }
    // A stereo frame's depth is its right image.
    if (stereo_ != nullptr ? f.right.data == nullptr : depth_valid_share(f.depth) < 0.01)
      c_.frames_no_depth->inc();
    return true;
  }

  static constexpr int64_t kStatusPeriodNs = 1'000'000'000;
  core::Estimator& est_;
  drivers::StereoRectifier* stereo_ = nullptr;
  drivers::SensorRings& rings_;
  ImuRing& imu_;
  rt::SpscRing<core::PoseSample, kOutRingCapacity>& out_;
  rt::Mailbox<PipelineStatus>& status_;
  rt::Mailbox<Anchor>* anchor_;
  const ReplayOptions& opt_;
  ReplayReport& report_;
  PipelineCounters& c_;
  viewer::ViewerFeed* feed_;
  MapTopicsFeed* map_feed_;
  MapThreads* map_ = nullptr;
  dense::DenseMapper* dense_ = nullptr;
  int64_t frame_wait_since_ns_ = -1;  // live: when the frame at the front began waiting for the IMU
  int64_t imu_max_since_frame_ns_ = 0;
  int64_t frame_period_ns_ = 0;
  int64_t imu_gap_ns_ = 50'000'000;
  bool has_imu_ = true;
  int64_t newest_t_ns_ = -1;  // newest record time seen (log time)
  uint64_t last_fingerprint_ = 0;
  uint64_t frames_fed_ = 0;
  double work_cpu_s_ = 0;
  uint64_t frames_at_last_status_ = 0;
  int64_t next_status_t_ns_ = 0;
  int64_t window_tracking_max_ns_ = 0;
  int64_t window_imu_max_ns_ = 0;
  Vec3d last_gyro_rps_{};
  int64_t first_t_ns_ = -1;
  int64_t last_imu_t_ns_ = -1;
  int64_t last_frame_t_ns_ = -1;
  int64_t last_out_t_ns_ = -1;
  bool counting_ = false;
  uint64_t allocs_at_warmup_ = 0;
};

// The output side: trajectory, pose callback, MAVLink, status line. Runs on
// the calling thread (never the estimator thread), so it may block or allocate.
class OutputStage {
 public:
  OutputStage(rt::SpscRing<core::PoseSample, kOutRingCapacity>& out,
              const rt::Mailbox<PipelineStatus>& status, const ReplayOptions& opt, ReplayReport& report,
              PipelineCounters& counters, const rt::Mailbox<core::PoseSample>* imu_pose, viewer::Server* view,
              MapTopicsFeed* map_feed)
      : out_(out),
        status_(status),
        opt_(opt),
        report_(report),
        c_(counters),
        imu_pose_(imu_pose),
        view_(view),
        map_feed_(map_feed) {
    if (opt.mavlink) {
      mavlink::OdometryStreamOptions mo = *opt.mavlink;
      mo.stamps_on_host_clock = opt.live != nullptr;  // a log's time is not CLOCK_MONOTONIC
      mavlink_ = std::make_unique<mavlink::OdometryStream>(mo);
    }
  }

  void drain() {
    if (mavlink_) mavlink_->service(rt::now_ns());
    if (imu_pose_ != nullptr && imu_pose_->version() != imu_pose_version_) {
      core::PoseSample o;
      if (imu_pose_->read(o, &imu_pose_version_)) {
        c_.imu_rate_poses->inc();
        if (opt_.on_imu_pose) opt_.on_imu_pose(o);
      }
    }
    while (core::PoseSample* p = out_.front()) {
      const core::PoseSample s = *p;
      out_.pop();
      // A pose the backend says is lost is a placeholder, not an estimate:
      // the flight controller gets it flagged (quality -1), the trajectories
      // that are scored and written leave it out (pose_share shows the gap).
      const bool lost = s.quality == core::TrackingQuality::kLost;
      if (lost) {
        c_.lost_poses_withheld->inc();
      } else {
        tools::TimedPose tp;
        tp.t_ns = s.t_ns;
        tp.p = s.p_WB();
        tp.q = s.q_WB();
        report_.trajectory.push_back(tp);
      }
      if (s.map.active) {
        const Eigen::Isometry3d T = s.T_map_body();
        if (!lost) {
          tools::TimedPose mp;
          mp.t_ns = s.t_ns;
          mp.p = T.translation();
          mp.q = Eigen::Quaterniond(T.linear());
          report_.map_trajectory.push_back(mp);
        }
        if (s.map.alignment != map_alignment_) {
          map_alignment_ = s.map.alignment;
          c_.map_corrections->inc();
          if (opt_.on_map_correction) opt_.on_map_correction(s);
        }
        report_.map = s.map;
        c_.mirror_map(s.map);
      }
      if (opt_.on_pose) opt_.on_pose(s);
      if (mavlink_) mavlink_->publish(s);
      if (view_ != nullptr) view_->add_pose(s.t_ns, s.p_WB(), s.q_WB(), s.quality);
    }
    // After the poses: a cloud or keyframe goes out with the T_map_odom of
    // the poses up to its frame.
    if (map_feed_ != nullptr) {
      KeyframePose k;
      while (map_feed_->pop_keyframe(k))
        if (opt_.on_keyframe) opt_.on_keyframe(k);
      rt::PoolHandle h = rt::kInvalidHandle;
      while (const MapCloud* c = map_feed_->take_cloud(&h)) {
        if (opt_.on_map_cloud) opt_.on_map_cloud(*c);
        map_feed_->release(h);
      }
    }
    if (mavlink_) mirror_mavlink();
    if (opt_.status_line) {
      PipelineStatus st;
      uint64_t version = 0;
      if (status_.read(st, &version) && version != status_version_) {
        status_version_ = version;
        c_.status_lines->inc();
        const std::string line = format_status(st, c_.registry.values());
        if (opt_.on_status) {
          opt_.on_status(st, line);
        } else {
          std::printf("%s\n", line.c_str());
          std::fflush(stdout);
        }
      }
    }
  }

  void finish() {
    drain();
    if (mavlink_) {
      report_.mavlink_timesync_converged = mavlink_->time_sync().converged();
      report_.mavlink_timesync_offset_ms = 1e-6 * static_cast<double>(mavlink_->time_sync().offset_ns());
      report_.mavlink_signing = mavlink_->signing_stats() != nullptr;
    }
  }

 private:
  rt::SpscRing<core::PoseSample, kOutRingCapacity>& out_;
  const rt::Mailbox<PipelineStatus>& status_;
  const ReplayOptions& opt_;
  // The link's own counts, into the registry after every drain.
  void mirror_mavlink() noexcept {
    c_.mavlink_odometry->set(mavlink_->stream_stats().odometry_sent);
    c_.mavlink_heartbeats->set(mavlink_->stream_stats().heartbeats_sent);
    c_.mavlink_frames->set(mavlink_->stats().sent);
    c_.mavlink_failed->set(mavlink_->stats().failed);
    c_.mavlink_unauthenticated->set(mavlink_->decoder_stats().unauthenticated);
    c_.mavlink_timesync->set(mavlink_->time_sync().stats().requests_answered);
  }

  ReplayReport& report_;
  PipelineCounters& c_;
  std::unique_ptr<mavlink::OdometryStream> mavlink_;
  uint64_t status_version_ = 0;
  uint32_t map_alignment_ = 0;
  const rt::Mailbox<core::PoseSample>* imu_pose_ = nullptr;
  uint64_t imu_pose_version_ = 0;
  viewer::Server* view_ = nullptr;
  MapTopicsFeed* map_feed_ = nullptr;
};

}  // namespace

AppliedThread applied_thread(const rt::ThreadSpec& spec, const rt::ThreadSetupReport& r) {
  AppliedThread a;
  a.name = spec.name;
  a.cpu = spec.cpu;
  a.policy = spec.priority > 0 ? "fifo" : "other";
  a.priority = spec.priority;
  a.applied = r.fully_granted();
  if (r.granted_priority != r.requested_priority) a.error = std::string("scheduling: ") + r.sched_note;
  if (spec.cpu >= 0 && !r.pinned) {
    a.error +=
        std::string(a.error.empty() ? "" : "; ") + "cpu " + std::to_string(spec.cpu) + ": " + r.affinity_note;
  }
  if (!r.name_set) a.error += std::string(a.error.empty() ? "" : "; ") + "thread name not set";
  return a;
}

std::string threads_summary(const std::vector<AppliedThread>& t) {
  std::string s;
  for (const AppliedThread& a : t) {
    s += "thread " + a.name + ": " + a.policy + (a.priority > 0 ? " " + std::to_string(a.priority) : "") +
         ", cpu " + (a.cpu < 0 ? std::string("any") : std::to_string(a.cpu)) +
         (a.applied ? " - applied\n" : " - NOT applied, runs anyway (" + a.error + ")\n");
  }
  return s;
}

namespace {

// The keyframes as the map ends the flight, and each closed loop drawn
// between its two keyframes there (the closure's own camera positions when a
// keyframe left the map since). After the map threads stopped: it allocates.
MapFinal map_final_of(core::Estimator& est) {
  MapFinal f;
  if (est.map_system() == nullptr) return f;
  for (const core::MapKeyframePose& k : est.map_system()->keyframe_poses())
    f.keyframes.push_back({k.t_ns, k.T_MB});
  auto position_at = [&f](int64_t t_ns, const Eigen::Vector3d& fallback) {
    const auto it = std::lower_bound(f.keyframes.begin(), f.keyframes.end(), t_ns,
                                     [](const MapFinal::Keyframe& k, int64_t t) { return k.t_ns < t; });
    return it != f.keyframes.end() && it->t_ns == t_ns ? Eigen::Vector3d(it->T_MB.translation()) : fallback;
  };
  for (const core::LoopCandidateRecord& c : est.map_system()->loop_closer().log().candidates) {
    if (!c.closed) continue;
    MapFinal::Loop l;
    l.query_t_ns = c.query_t_ns;
    l.candidate_t_ns = c.candidate_t_ns;
    l.p_M_query = position_at(c.query_t_ns, c.T_MC_query.translation());
    l.p_M_candidate = position_at(c.candidate_t_ns, c.T_MC_candidate.translation());
    f.loops.push_back(l);
  }
  return f;
}

}  // namespace

namespace {

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
    if (f.right != nullptr && !copy(*f.right, m.right_handle)) {
      rings_.images.release(m.rgb_handle);
      if (m.depth_handle != rt::kInvalidHandle) rings_.images.release(m.depth_handle);
      return drop();
    }
    if (rings_.push_frame(m)) return true;
    rings_.images.release(m.rgb_handle);
    if (m.depth_handle != rt::kInvalidHandle) rings_.images.release(m.depth_handle);
    if (m.right_handle != rt::kInvalidHandle) rings_.images.release(m.right_handle);
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
    dst->pixels.assign(src.pixels.begin(), src.pixels.end());  // within capacity: no allocation
    return true;
  }
  drivers::SensorRings& rings_;
  const Rig& rig_;
};

}  // namespace

namespace {

// The input (a log, read by kst-replay or stepped in lockstep, or the live
// sensors) and, for a stereo rig, its rectifier: the estimator runs on the
// rectified left camera, with the depth model of the disparity search
// (docs/stereo.md).
struct PipelineInput {
  std::unique_ptr<drivers::LogSource> log;
  const Rig* input_rig = nullptr;
  std::unique_ptr<drivers::StereoRectifier> stereo;
  Rig stereo_rig;
  const Rig& rig() const { return stereo ? stereo_rig : *input_rig; }
};

PipelineInput open_input(const ReplayOptions& opt, ReplayReport& report) {
  PipelineInput in;
  if (opt.live) {
    if (opt.pace != drivers::ReplayPace::kRealtime)
      throw std::invalid_argument("live sensors run at realtime pace only");
    report.log_path = opt.live->description;
    report.log_format = "live";
  } else {
    drivers::LogOpenOptions open = opt.open;
    open.format = opt.format;
    in.log = opt.open_source ? opt.open_source() : drivers::open_log(opt.path, open);
    report.log_path = opt.path;
    report.log_format = in.log->format_name();
  }
  in.input_rig = in.log ? &in.log->rig() : &opt.live->rig;
  if (!in.input_rig->stereo.present) return in;
  // Camera settings that deliver no right image would make every frame depth-less: say so at start.
  if (opt.live && !opt.live->stereo_problem.empty()) {
    throw std::invalid_argument("the rig has a stereo: right camera, but " + opt.live->stereo_problem +
                                " (docs/stereo.md, \"Live stereo\")");
  }
  try {
    in.stereo = std::make_unique<drivers::StereoRectifier>(*in.input_rig);
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(report.log_path + ": " + e.what());
  }
  in.stereo_rig = in.stereo->rectified_rig();
  const core::StereoMatchOptions so =
      opt.config ? opt.config->tracker.stereo : core::EstimatorConfig::defaults(opt.estimator).tracker.stereo;
  in.stereo_rig.depth = core::stereo_depth_model(in.stereo_rig.rgb.fx, in.stereo_rig.stereo.baseline_m, so);
  report.stereo = true;
  report.stereo_baseline_m = in.stereo_rig.stereo.baseline_m;
  return in;
}

// After the map's threads stopped: the map file, the map's final word on this
// flight's keyframes and trajectory, the loop log and the global BA's figures.
void finish_map(const ReplayOptions& opt, core::Estimator& estimator, ReplayReport& report) {
  if (!opt.map_out.empty()) {
    tools::write_map_file(opt.map_out,
                          report.has_map ? estimator.map_system()->save() : std::vector<uint8_t>{});
  }
  if (!report.has_map) return;
  const core::MapSystem& ms = *estimator.map_system();
  std::vector<tools::KeyframeAnchor>& anchors = report.map_final_keyframes;
  for (const core::MapKeyframePose& k : ms.keyframe_poses()) anchors.push_back({k.t_ns, k.T_MB, k.T_WB});
  if (!anchors.empty()) report.map_final_trajectory = tools::anchor_to_keyframes(report.trajectory, anchors);
  if (opt.loop_log) report.loop_log = ms.loop_closer().log();
  if (ms.global_ba() != nullptr) {
    report.global_ba = ms.global_ba()->stats();
    report.global_ba_solve.merge(ms.global_ba_latency());
  }
  if (opt.on_map_final) opt.on_map_final(map_final_of(estimator));
}

// A keyframe's correction comes from a trajectory pose at most this far in
// time (a dense keyframe is a frame of the trajectory; farther: a lost stretch).
constexpr int64_t kDenseCorrectionMaxGapNs = 100'000'000;

// C_MW at t_ns: the map-frame trajectory M against the odometry's W at the
// pose nearest t_ns (they are the same frames; the nearest also absorbs a stamp
// the backend moved by its time-offset estimate). Without a map M = W and it
// is the identity.
std::function<bool(int64_t, Eigen::Isometry3d&)> correction_along(const tools::Trajectory& W,
                                                                  const tools::Trajectory& M) {
  auto iso = [](const tools::TimedPose& p) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = p.q.normalized().toRotationMatrix();
    T.translation() = p.p;
    return T;
  };
  return [&W, &M, iso](int64_t t_ns, Eigen::Isometry3d& C_MW) {
    if (W.empty() || M.size() != W.size()) return false;
    auto it = std::lower_bound(W.begin(), W.end(), t_ns,
                               [](const tools::TimedPose& p, int64_t t) { return p.t_ns < t; });
    if (it == W.end() || (it != W.begin() && t_ns - std::prev(it)->t_ns < it->t_ns - t_ns)) --it;
    if (std::llabs(it->t_ns - t_ns) > kDenseCorrectionMaxGapNs) return false;
    const std::size_t i = static_cast<std::size_t>(it - W.begin());
    C_MW = iso(M[i]) * iso(W[i]).inverse();
    return true;
  };
}

// After kst-dense stopped: the dense outputs, in W (--dense-out, OctoMap, the
// callbacks), then re-integrated along the map's final poses (--dense-map-out).
void finish_dense(const ReplayOptions& opt, const dense::DenseOptions& dense_opt,
                  dense::DenseMapper& dense_mapper, ReplayReport& report) {
  const core::TsdfMap& dm = dense_mapper.map();
  report.dense = true;
  report.dense_stats = dense_mapper.stats();
  report.dense_live_reanchor = dense_opt.live_reanchor;
  report.dense_live_blocks = dm.blocks_in_use();
  if (opt.on_dense_map_live) opt.on_dense_map_live(dm);
  if (dense_opt.live_reanchor && (!opt.dense_out.empty() || !opt.dense_octomap_out.empty() ||
                                  opt.on_dense_map || opt.on_dense_finished)) {
    // In flight the map was in the map frame; the contract of --dense-out
    // is W: the archive fused again along the odometry (the identity).
    dense_mapper.rebuild_along([](int64_t, Eigen::Isometry3d& C_MW) {
      C_MW = Eigen::Isometry3d::Identity();
      return true;
    });
    report.dense_w_rebuild = dense_mapper.stats().rebuild;
  }
  report.dense_counters = dm.counters();
  report.dense_blocks = dm.blocks_in_use();
  report.dense_block_capacity = dm.block_capacity();
  report.dense_memory_mb = static_cast<double>(dm.memory_bytes()) / 1048576.0;
  if (!opt.dense_out.empty()) {
    std::vector<core::SurfacePoint> pts;
    dm.extract_surface(pts);
    dense::write_ply(opt.dense_out, pts);
    report.dense_points = pts.size();
  }
  if (!opt.dense_octomap_out.empty())
    report.dense_octomap_leaves = dense::write_octomap_bt(opt.dense_octomap_out, dm);
  if (opt.on_dense_map) opt.on_dense_map(dm);
  if (opt.on_dense_finished) opt.on_dense_finished(dm);
  if (opt.dense_map_out.empty() && !opt.on_dense_map_rebuilt) return;
  // The map's final word on every keyframe's pose; the map's memory is
  // reused, so this runs after everything W needed was written.
  if (dense_mapper.archive() == nullptr)
    throw std::invalid_argument("--dense-map-out needs the keyframe archive (dense.archive_budget_mb > 0)");
  const tools::Trajectory& M =
      report.map_final_trajectory.empty() ? report.trajectory : report.map_final_trajectory;
  dense_mapper.rebuild_along(correction_along(report.trajectory, M));
  report.dense_stats = dense_mapper.stats();
  report.dense_archive_capacity = dense_mapper.archive()->capacity();
  report.dense_archive_overwritten = dense_mapper.archive()->counters().overwritten;
  if (!opt.dense_map_out.empty()) {
    std::vector<core::SurfacePoint> pts;
    dm.extract_surface(pts);
    dense::write_ply(opt.dense_map_out, pts);
    report.dense_map_points = pts.size();
  }
  if (opt.on_dense_map_rebuilt) opt.on_dense_map_rebuilt(dm);
}

// The estimator's and the workers' figures once every thread stopped.
void collect_estimator_report(core::Estimator& estimator, const core::EstimatorWorkers& workers,
                              const Rig& rig, ReplayReport& report) {
  for (const core::EstimatorWorker* w : workers) {
    const rt::LatencyHistogram* h = w->latency();
    if (h == nullptr) continue;
    if (w->kind() == core::EstimatorWorker::Kind::kMapping) report.mapping = *h;
    if (w->kind() == core::EstimatorWorker::Kind::kLoop) report.loop = *h;
    if (w->kind() == core::EstimatorWorker::Kind::kOptimizer) report.optimizer = *h;
  }
  report.estimator_counters = estimator.counters();
  report.backend_summary = estimator.backend_summary();
  double td_s = 0.0;
  report.time_offset_estimated = estimator.estimated_time_offset_s(&td_s);
  report.time_offset_ms = 1e-6 * static_cast<double>(rig.time_offset_cam_imu_ns) + 1e3 * td_s;
}

// Live: the drivers push through these sinks (made when the threads are up);
// done once the sensors stopped.
struct LiveSinks {
  std::unique_ptr<drivers::ImuSink> imu;
  std::unique_ptr<RingFrameSink> frames;
  std::atomic<bool> done{false};
};

// Fast and realtime paces: the feeder, kst-propagate (realtime), the estimator
// and the optimizer (when it has a thread: `optimizer` non-null) each on a
// thread of the table; this thread drains the output until the estimator is
// done, and live it stops the sensors when asked.
void run_threads(const ReplayOptions& opt, ReplayReport& report, drivers::SensorRings& rings,
                 ImuRing& est_imu, drivers::ReplaySource* source, LiveSinks& live, ImuRateStage& propagator,
                 EstimatorStage& stage, OutputStage& output, core::EstimatorWorker* optimizer,
                 const Rig& rig) {
  const bool realtime = opt.pace == drivers::ReplayPace::kRealtime;
  auto input_finished = [&] {
    return source != nullptr ? source->finished() : live.done.load(std::memory_order_acquire);
  };
  std::atomic<bool> stop{false};
  std::atomic<bool> estimator_done{false};
  std::atomic<bool> imu_forwarded{!realtime};
  double est_cpu = 0, opt_cpu = 0;
  // Who sleeps on what (issue 45: no thread polls). Realtime: the feeder wakes
  // kst-propagate for IMU and the estimator for frames, kst-propagate wakes
  // the estimator for the IMU it forwarded. Fast: the estimator takes both
  // rings. The estimator wakes the optimizer and the output after its work.
  rt::Doorbell est_bell, prop_bell, opt_bell, out_bell;
  rings.imu_bell = realtime ? &prop_bell : &est_bell;
  rings.frame_bell = &est_bell;
  // The config's table in realtime pace (as it will fly); fast pace is a
  // throughput run and keeps the defaults.
  const drivers::ThreadTable table = realtime ? opt.threads : drivers::default_thread_table();
  using drivers::PipelineThread;
  rt::ThreadSetupReport sched;
  std::thread feeder;
  if (source) {
    feeder = rt::start_thread(
        table[PipelineThread::kReplay], [&] { source->run(stop); }, &sched);
    report.threads.push_back(applied_thread(table[PipelineThread::kReplay], sched));
  }
  std::thread prop_thread;
  if (realtime) {
    rt::ThreadSetupReport prop_sched;
    prop_thread = rt::start_thread(
        table[PipelineThread::kPropagate],
        [&] {
          for (;;) {
            const bool done = input_finished();
            if (propagator.step()) {
              est_bell.ring();
              out_bell.ring();
            } else {
              if (done && rings.imu.empty()) break;
              prop_bell.wait_for_ns(kIdleWaitNs);
            }
          }
          propagator.finish();
          imu_forwarded.store(true, std::memory_order_release);
          est_bell.ring();
        },
        &prop_sched);
    report.propagator_thread = rt::to_string(prop_sched);
    report.threads.push_back(applied_thread(table[PipelineThread::kPropagate], prop_sched));
  }
  ImuRing& est_in = realtime ? est_imu : rings.imu;
  std::thread est_thread = rt::start_thread(
      table[PipelineThread::kEstimator],
      [&] {
        for (;;) {
          const bool done = input_finished() && imu_forwarded.load(std::memory_order_acquire);
          if (stage.drain(done, false)) {
            opt_bell.ring();
            out_bell.ring();
            continue;
          }
          if (done && est_in.empty() && rings.frames.empty()) break;
          est_bell.wait_for_ns(kIdleWaitNs);
        }
        stage.finish();
        est_cpu = thread_cpu_s();
        estimator_done.store(true, std::memory_order_release);
        opt_bell.ring();
        out_bell.ring();
      },
      &sched);
  report.threads.push_back(applied_thread(table[PipelineThread::kEstimator], sched));
  std::thread opt_thread;
  if (optimizer != nullptr) {
    opt_thread = rt::start_thread(
        table[PipelineThread::kOptimizer],
        [&] {
          while (!estimator_done.load(std::memory_order_acquire)) {
            // A job is handed over only while the estimator works, and it
            // rings after each piece of work: a spurious wake costs one look.
            if (!optimizer->step()) opt_bell.wait_for_ns(kIdleWaitNs);
          }
          opt_cpu = thread_cpu_s();
        },
        &sched);
    report.threads.push_back(applied_thread(table[PipelineThread::kOptimizer], sched));
  }
  if (opt.live) {
    // The sensors start last: every consumer is waiting for them.
    live.imu = std::make_unique<drivers::RingImuSink<ImuRing>>(rings.imu, rings.imu_bell);
    live.frames = std::make_unique<RingFrameSink>(rings, rig);
    opt.live->start(*live.imu, *live.frames, report.threads);
  }
  while (!estimator_done.load(std::memory_order_acquire)) {
    output.drain();
    if (opt.live && !live.done.load(std::memory_order_relaxed) && opt.live->should_stop()) {
      opt.live->stop();
      live.done.store(true, std::memory_order_release);
      prop_bell.ring();
      est_bell.ring();
    }
    out_bell.wait_for_ns(opt.live ? kLiveOutputWaitNs : kIdleWaitNs);
  }
  if (feeder.joinable()) feeder.join();
  if (prop_thread.joinable()) prop_thread.join();
  est_thread.join();
  if (opt_thread.joinable()) opt_thread.join();
  output.finish();
  report.estimator_thread_cpu_s = est_cpu;
  report.estimator_thread_overhead_cpu_s = est_cpu - stage.work_cpu_s();
  // The solve is the backend's work wherever it runs; its thread's polling
  // between solves is a few wake-ups a second.
  report.estimator_cpu_s = stage.work_cpu_s() + opt_cpu;
  if (realtime) {
    report.imu_to_output = propagator.stats().imu_to_output;
    stage.counters().propagator_forward_drops->set(propagator.stats().forward_drops);
    report.steady_allocs += propagator.stats().steady_allocs;
  }
}

// After every thread stopped: what the rings lost. Replayed, what the feeder
// lost, not the rings' refused pushes: in fast pace the feeder retries a full
// ring (back-pressure), and every retry is a refusal. Live there is no
// back-pressure: every refused push is a lost sample.
void count_ring_losses(PipelineCounters& c, bool live_input, const drivers::ReplayStats& replay,
                       drivers::SensorRings& rings, const LiveSinks& live) {
  c.imu_ring_drops->set(live_input ? rings.imu.drops() : replay.imu_dropped);
  c.frame_ring_drops->set(live_input ? rings.frames.drops() + live.frames->drops : replay.frames_dropped);
  c.image_pool_exhausted->set(rings.images.failed_acquires());
}

}  // namespace

ReplayReport run_replay(const ReplayOptions& opt) {
  ReplayReport report;
  const PipelineInput input = open_input(opt, report);
  const std::unique_ptr<drivers::LogSource>& log = input.log;
  const std::unique_ptr<drivers::StereoRectifier>& stereo = input.stereo;
  const Rig& input_rig = *input.input_rig;
  const Rig& rig = input.rig();
  report.pace = opt.pace;
  report.alloc_counting = rt::alloc_hook_linked();

  // Everything sized here, before any thread starts.
  auto rings = std::make_unique<drivers::SensorRings>(
      opt.live && opt.live->max_image_bytes > 0 ? opt.live->max_image_bytes : max_image_bytes_for(input_rig));
  auto out = std::make_unique<rt::SpscRing<core::PoseSample, kOutRingCapacity>>();
  auto status = std::make_unique<rt::Mailbox<PipelineStatus>>();
  const bool realtime = opt.pace == drivers::ReplayPace::kRealtime;
  auto est_imu = std::make_unique<ImuRing>();
  auto anchor = std::make_unique<rt::Mailbox<Anchor>>();
  std::unique_ptr<core::Estimator> estimator_ptr =
      opt.config ? core::make_estimator(*opt.config, rig) : core::make_estimator(opt.estimator, rig);
  core::Estimator& estimator = *estimator_ptr;
  report.estimator = estimator.name();
  report.world_levelled = estimator.world_levelled();
  if (opt.mavlink && !report.world_levelled)
    throw std::invalid_argument(mavlink_needs_levelled_world(estimator.name()));
  if (opt.check_before_start) opt.check_before_start(estimator);
  report.trajectory.reserve(1 << 16);
  report.has_map = estimator.has_map();
  if (report.has_map) report.map_trajectory.reserve(1 << 16);
  // The final loop markers are read from the loop closer's log.
  if ((opt.loop_log || opt.on_map_final) && estimator.map_system() != nullptr)
    estimator.map_system()->set_loop_logging(true);

  // At realtime pace the optimizer gets its own thread, as it will fly; fast
  // and lockstep run it inline, so both give the lockstep trajectory bit for
  // bit whatever the machine's load.
  const core::EstimatorWorkers workers = estimator.workers();
  core::EstimatorWorker* optimizer = workers.find(core::EstimatorWorker::Kind::kOptimizer);
  const bool optimizer_thread = opt.pace == drivers::ReplayPace::kRealtime && optimizer != nullptr;
  if (optimizer != nullptr) optimizer->set_threaded(optimizer_thread);

  std::unique_ptr<drivers::ReplaySource> source;
  if (log) source = std::make_unique<drivers::ReplaySource>(*log, *rings, opt.pace);
  LiveSinks live;
  // Every count of the run, by path (pipeline_counters.hpp); before the
  // viewer, whose thread reads it until the viewer is gone.
  auto registry = std::make_unique<rt::PerfRegistry>();
  PipelineCounters counters(*registry, estimator.view().has_optimizer);
  if (estimator.has_map()) {
    counters.register_map();
    estimator.map_system()->register_counters(*registry);
  }
  // The dense map's stream to the viewer, declared before the server that reads
  // it and the mapper that writes it, so both are gone before it is.
  std::unique_ptr<viewer::BinaryStream> dense_stream;
  std::unique_ptr<DenseToViewer> dense_sink;
  // The live viewer: its snapshot pool is sized here with the rest.
  std::unique_ptr<viewer::ViewerFeed> feed;
  std::unique_ptr<viewer::PlaybackControl> control;
  std::unique_ptr<viewer::Server> view;
  // The dense map's thread runs when dense.enabled or one of its outputs is asked for.
  const bool dense_on = opt.dense.enabled || !opt.dense_out.empty() || !opt.dense_octomap_out.empty() ||
                        !opt.dense_map_out.empty() || opt.on_dense_map || opt.on_dense_map_rebuilt ||
                        opt.on_dense_map_live;
  if (dense_on) counters.register_dense();
  if (opt.view) {
    feed = std::make_unique<viewer::ViewerFeed>(estimator, rig);
    control =
        std::make_unique<viewer::PlaybackControl>(opt.pace == drivers::ReplayPace::kLockstep, feed.get());
    view = std::make_unique<viewer::Server>(opt.view_options, *feed, control.get());
    if (dense_on) {
      dense_stream = std::make_unique<viewer::BinaryStream>(kDenseViewSlotBytes);
      dense_sink = std::make_unique<DenseToViewer>(*dense_stream);
      view->set_dense_stream(dense_stream.get());
    }
    if (source) source->set_ground_truth_ring(&feed->ground_truth_ring());
  }
  // The ROS outputs' map (sized here with the rest; nothing for a backend without a tracker).
  std::unique_ptr<MapTopicsFeed> map_feed;
  if (opt.on_map_cloud || opt.on_keyframe) {
    map_feed = std::make_unique<MapTopicsFeed>(estimator, opt.on_map_cloud ? opt.map_points_rate_hz : 0.0);
    if (!map_feed->active()) map_feed.reset();
  }
  if (view) view->set_counters(registry.get());
  EstimatorStage stage(estimator, *rings, realtime ? *est_imu : rings->imu, *out, *status,
                       realtime ? anchor.get() : nullptr, opt, rig, report, counters, feed.get(),
                       map_feed.get());
  auto imu_pose = std::make_unique<rt::Mailbox<core::PoseSample>>();
  ImuRateStage propagator(rings->imu, *est_imu, *anchor, rig, opt.warmup_ns, *imu_pose);
  OutputStage output(*out, *status, opt, report, counters, imu_pose.get(), view.get(), map_feed.get());
  if (view) {
    // In realtime pace kst-propagate owns the IMU -> pose figure.
    if (realtime) view->set_imu_latency_probe([&propagator] { return propagator.take_recent_max_ns(); });
    const rt::ThreadSpec& spec = opt.threads[drivers::PipelineThread::kViewer];
    report.threads.push_back(applied_thread(spec, view->start(spec)));
    report.view = true;
    if (opt.on_view_ready) opt.on_view_ready(*view);
    if (opt.view_wait_s > 0) view->wait_for_client(static_cast<int64_t>(opt.view_wait_s * 1e9));
  }

  // The map's two threads, in every pace: the deterministic paces wait for
  // them per keyframe (EstimatorStage::on_frame), realtime does not.
  MapThreads map_threads(
      estimator, opt.pace == drivers::ReplayPace::kRealtime ? opt.threads : drivers::default_thread_table(),
      report.threads);
  stage.set_map_threads(&map_threads);
  stage.set_stereo(stereo.get());
  // The dense map's thread (off unless asked for): the deterministic paces
  // wait for a free slot, realtime drops and counts.
  dense::DenseOptions dense_opt = opt.dense;
  dense_opt.enabled = dense_on;
  // The keyframe archive costs its budget in memory; only a re-integration reads it.
  if (opt.dense_map_out.empty() && !opt.on_dense_map_rebuilt && !dense_opt.live_reanchor)
    dense_opt.archive.budget_mb = 0;
  dense::DenseMapper dense_mapper(dense_opt, rig, !realtime);
  if (dense_sink) dense_mapper.attach_view(dense_sink.get(), opt.dense_view);
  stage.set_dense(&dense_mapper);
  if (dense_mapper.enabled())
    report.threads.push_back(applied_thread(dense::DenseMapper::thread_spec(), dense_mapper.thread_report()));
  // With live re-anchoring the map's keyframes reach kst-dense whenever the
  // map moves them; the hook is removed before the mapper goes, on every path out.
  struct MapMovedHook {
    MapThreads* threads = nullptr;
    ~MapMovedHook() {
      if (threads != nullptr) threads->set_on_map_moved(nullptr);
    }
  } map_moved_hook;
  if (dense_mapper.enabled() && dense_opt.live_reanchor && map_threads.running()) {
    map_moved_hook.threads = &map_threads;
    map_threads.set_on_map_moved([&dense_mapper](const std::vector<core::MapKeyframePose>& poses) {
      std::vector<dense::MapCorrection> c(poses.size());
      for (std::size_t i = 0; i < poses.size(); ++i)
        c[i] = {poses[i].t_ns, poses[i].T_MB * poses[i].T_WB.inverse()};
      dense_mapper.note_map_keyframes(c);
    });
  }
  // The planner's handle is withdrawn before the mapper goes, on every path out.
  struct DenseLiveHandle {
    const std::function<void(const dense::DenseMapper*)>* fn = nullptr;
    void withdraw() {
      if (fn != nullptr && *fn) (*fn)(nullptr);
      fn = nullptr;
    }
    ~DenseLiveHandle() { withdraw(); }
  } dense_live;
  if (opt.on_dense_live && dense_mapper.enabled()) {
    dense_live.fn = &opt.on_dense_live;
    opt.on_dense_live(&dense_mapper);
  }

  const int64_t wall0 = rt::now_ns();
  const double cpu0 = process_cpu_s();
  if (opt.pace == drivers::ReplayPace::kLockstep) {
    // One thread, strictly alternating: the same log and config give the same
    // trajectory bit for bit. A paused viewer holds it between records.
    for (;;) {
      while (control && !control->may_proceed(stage.frames_fed())) {
        output.drain();
        rt::sleep_for_ns(5'000'000);
      }
      if (!source->step()) break;
      stage.drain(false, true);
      output.drain();
    }
    stage.drain(true, true);
    stage.finish();
    report.estimator_thread_cpu_s = thread_cpu_s();
    report.estimator_cpu_s = stage.work_cpu_s();
    output.finish();
  } else {
    run_threads(opt, report, *rings, *est_imu, source.get(), live, propagator, stage, output,
                optimizer_thread ? optimizer : nullptr, rig);
  }
  map_threads.stop();
  if (estimator.has_map()) estimator.map_system()->mirror_counters();
  finish_map(opt, estimator, report);
  if (dense_mapper.enabled()) {
    dense_mapper.stop();
    dense_live.withdraw();
    finish_dense(opt, dense_opt, dense_mapper, report);
    counters.mirror_dense(dense_mapper.stats());
  }
  if (map_feed) {
    counters.map_clouds->set(map_feed->clouds_published());
    counters.map_clouds_dropped->set(map_feed->clouds_dropped());
    counters.map_keyframes_dropped->set(map_feed->keyframes_dropped());
  }
  report.mapping_cpu_s = map_threads.mapping_cpu_s();
  report.loop_cpu_s = map_threads.loop_cpu_s();
  const int64_t wall1 = rt::now_ns();

  if (source) {
    report.replay = source->stats();
  } else {
    // Live: what the estimator was handed (the drivers' own counts are in their report).
    report.replay.imu_pushed = estimator.counters().imu_in;
    report.replay.frames_pushed = estimator.counters().frames_in;
  }
  collect_estimator_report(estimator, workers, rig, report);
  report.optimizer_threaded = optimizer_thread;

  count_ring_losses(counters, opt.live != nullptr, report.replay, *rings, live);
  if (log) report.problems = log->problems();
  report.wall_s = 1e-9 * static_cast<double>(wall1 - wall0);
  report.cpu_s = process_cpu_s() - cpu0;
  if (report.replay.first_t_ns >= 0) {
    report.log_duration_s = 1e-9 * static_cast<double>(report.replay.last_t_ns - report.replay.first_t_ns);
  } else if (report.trajectory.size() > 1) {
    report.log_duration_s =
        1e-9 * static_cast<double>(report.trajectory.back().t_ns - report.trajectory.front().t_ns);
  }
  report.realtime_factor = report.wall_s > 0 ? report.log_duration_s / report.wall_s : 0;
  report.peak_rss_mb = peak_rss_mb();
  if (view) {
    counters.viewer_snapshots->set(feed->published());
    counters.viewer_snapshots_skipped->set(feed->skipped_busy());
    char line[160];
    std::snprintf(line, sizeof line, "replay finished: %zu poses, %.1f s of log in %.1f s",
                  report.trajectory.size(), report.log_duration_s, report.wall_s);
    view->mark_finished(line);
    view->stop();
    report.viewer = view->stats();
  }
  report.counters = registry->values();
  return report;
}

namespace {
using tools::Json;
using tools::json_figure;

// Every counter of the run by path; elapsed and interval counters as
// samples and microseconds.
Json counters_json(const rt::PerfValues& values) {
  Json all = Json::object();
  for (const rt::PerfValue& v : values.all()) {
    if (v.kind == rt::PerfKind::kCount) {
      all[v.name] = v.count;
      continue;
    }
    const double mean_ns = v.count > 0 ? static_cast<double>(v.total_ns) / static_cast<double>(v.count) : 0.0;
    all[v.name] = Json{{"count", v.count},
                       {"mean_us", 1e-3 * mean_ns},
                       {"min_us", 1e-3 * static_cast<double>(v.min_ns)},
                       {"max_us", 1e-3 * static_cast<double>(v.max_ns)}};
  }
  return all;
}

Json histogram_json(const rt::LatencyHistogram& h) {
  Json j = Json::object();
  j["count"] = static_cast<uint64_t>(h.count());
  const bool empty = h.count() == 0;
  const double nan = std::nan("");
  j["p50_ms"] = json_figure(empty ? nan : 1e-6 * static_cast<double>(h.percentile(50)));
  j["p90_ms"] = json_figure(empty ? nan : 1e-6 * static_cast<double>(h.percentile(90)));
  j["p99_ms"] = json_figure(empty ? nan : 1e-6 * static_cast<double>(h.percentile(99)));
  j["max_ms"] = json_figure(empty ? nan : 1e-6 * static_cast<double>(h.max()));
  // The whole distribution, for `kestrel eval --report --metrics`: the
  // non-empty bins as [lower bound ns, width ns, count].
  Json bins = Json::array();
  for (size_t i = 0; i < rt::LatencyHistogram::kBins; ++i) {
    const uint64_t n = h.bin_count(i);
    if (n == 0) continue;
    bins.push_back(Json::array({static_cast<int64_t>(rt::LatencyHistogram::bin_lower(i)),
                                static_cast<int64_t>(rt::LatencyHistogram::bin_width(i)), n}));
  }
  j["bins"] = std::move(bins);
  return j;
}
}  // namespace

namespace {
// A setting's YAML text as a typed JSON value: true/false, integers exactly,
// other numbers as doubles, names as strings.
Json config_value_json(const std::string& v) {
  if (v == "true" || v == "false") return v == "true";
  char* end = nullptr;
  if (!v.empty() && v.find_first_of(".eEn") == std::string::npos) {
    errno = 0;
    const long long i = std::strtoll(v.c_str(), &end, 10);
    if (end == v.c_str() + v.size() && errno == 0) return static_cast<int64_t>(i);
    const unsigned long long u = std::strtoull(v.c_str(), &end, 10);
    if (end == v.c_str() + v.size() && v[0] != '-') return static_cast<uint64_t>(u);
  }
  const double d = std::strtod(v.c_str(), &end);
  if (!v.empty() && end == v.c_str() + v.size()) return d;
  return v;
}
}  // namespace

std::string mavlink_needs_levelled_world(const std::string& backend) {
  return "--mavlink-udp/--mavlink-serial: the " + backend +
         " backend has no IMU, so its world frame is its first camera pose, not levelled; a flight "
         "controller "
         "takes ODOMETRY's z for down (docs/px4.md). Use a backend with an IMU (window, ekf, vo)";
}

std::optional<mavlink::OdometryStreamOptions> mavlink_options(const drivers::MavlinkSettings& cfg,
                                                              const std::string& udp,
                                                              const std::string& serial) {
  if (!udp.empty() && !serial.empty())
    throw std::invalid_argument("--mavlink-udp and --mavlink-serial: one link at a time");
  mavlink::OdometryStreamOptions o;
  o.endpoint = cfg.udp;
  o.serial_device = cfg.serial_device;
  o.serial_baud = cfg.serial_baud;
  if (!udp.empty()) {
    o.endpoint = udp;
    o.serial_device.clear();
  }
  if (!serial.empty()) {
    o.endpoint.clear();
    if (!mavlink::parse_serial_spec(serial, cfg.serial_baud, o.serial_device, o.serial_baud))
      throw std::invalid_argument("--mavlink-serial '" + serial + "': expected DEVICE[:BAUD]");
  }
  if (o.endpoint.empty() && o.serial_device.empty()) return std::nullopt;
  std::string host;
  uint16_t port = 0;
  if (!o.endpoint.empty() && !mavlink::parse_endpoint(o.endpoint, host, port))
    throw std::invalid_argument("MAVLink UDP '" + o.endpoint + "': expected HOST:PORT with PORT in 1..65535");
  o.sysid = static_cast<uint8_t>(cfg.sysid);
  o.compid = static_cast<uint8_t>(cfg.compid);
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) o.adapter.R_FB(r, c) = cfg.R_FB[3 * r + c];
  o.odometry_rate_hz = cfg.odometry_rate_hz;
  o.heartbeat_rate_hz = cfg.heartbeat_rate_hz;
  o.timesync = cfg.timesync;
  o.timesync_options.max_rtt_ns = static_cast<int64_t>(cfg.timesync_max_rtt_ms * 1e6);
  o.signing = cfg.signing;
  o.signing_key = cfg.signing_key;
  o.signing_link_id = static_cast<uint8_t>(cfg.signing_link_id);
  return o;
}

std::string replay_metrics_json(const ReplayReport& r) {
  Json j = Json::object();
  j["estimator"] = r.estimator;
  j["stereo"] = r.stereo ? Json{{"baseline_m", r.stereo_baseline_m}} : Json(nullptr);
  j["log"] = r.log_path;
  j["log_format"] = r.log_format;
  j["pace"] = drivers::to_string(r.pace);
  j["log_duration_s"] = json_figure(r.log_duration_s);
  j["wall_s"] = json_figure(r.wall_s);
  j["realtime_factor"] = json_figure(r.realtime_factor);
  j["cpu_s"] = json_figure(r.cpu_s);
  j["estimator_cpu_s"] = json_figure(r.estimator_cpu_s);
  j["estimator_thread_cpu_s"] = json_figure(r.estimator_thread_cpu_s);
  j["estimator_thread_overhead_cpu_s"] = json_figure(r.estimator_thread_overhead_cpu_s);
  j["peak_rss_mb"] = json_figure(r.peak_rss_mb);
  j["poses_out"] = static_cast<uint64_t>(r.trajectory.size());
  if (!r.config.empty()) {
    Json c = Json::object();
    for (const auto& [k, v] : r.config) c[k] = config_value_json(v);
    j["config"] = std::move(c);
  }
  j["latency"] = Json{{"imu_to_output", histogram_json(r.imu_to_output)},
                      {"tracking", histogram_json(r.tracking)},
                      {"estimator_imu", histogram_json(r.estimator_imu_latency)},
                      {"optimizer", histogram_json(r.optimizer)},
                      {"mapping", histogram_json(r.mapping)},
                      {"loop", histogram_json(r.loop)}};
  // The map (docs/map.md): null when the backend has none.
  if (r.has_map) {
    j["loop_closures"] = r.map.loop_closures;
    j["relocalisations"] = r.map.relocalisations;
    j["keyframes_in_map"] = r.map.keyframes;
    j["map_points"] = r.map.points;
    j["map_correction_m"] = r.map.T_map_odom().translation().norm();
    j["map_localized"] = r.map.localized;
    j["map_corrections"] = r.counters.count("output.map_corrections");
    j["mapping_cpu_s"] = r.mapping_cpu_s;
    j["loop_cpu_s"] = r.loop_cpu_s;
    if (r.global_ba) {
      const core::GlobalBaStats& g = *r.global_ba;
      j["global_ba"] = Json{{"runs", g.runs},
                            {"failures", g.failures},
                            {"keyframes", g.keyframes},
                            {"fixed_keyframes", g.fixed_keyframes},
                            {"points", g.points},
                            {"observations", g.observations},
                            {"outliers", g.outliers},
                            {"followed_keyframes", g.followed_keyframes},
                            {"followed_points", g.followed_points},
                            {"max_keyframe_move_m", g.max_keyframe_move_m},
                            {"solve", histogram_json(r.global_ba_solve)}};
    }
    if (r.loop_truth && r.loop_truth->available) {
      const LoopTruth& t = *r.loop_truth;
      j["loop_truth"] = Json{{"keyframes", t.keyframes},
                             {"revisit_keyframes", t.revisit_keyframes},
                             {"revisit_pairs", t.revisit_pairs},
                             {"candidates", t.candidates},
                             {"candidates_true", t.candidates_true},
                             {"revisit_keyframes_with_candidate", t.revisit_keyframes_candidate},
                             {"recognised", t.recognised},
                             {"recognised_true", t.recognised_true},
                             {"verified", t.verified},
                             {"verified_true", t.verified_true},
                             {"revisit_keyframes_recognised", t.revisit_keyframes_recognised},
                             {"revisit_keyframes_linked", t.revisit_keyframes_linked},
                             {"revisit_keyframes_found", t.revisit_keyframes_found},
                             {"closed", t.closed},
                             {"false", t.closed_false},
                             {"loop_recall", t.loop_recall},
                             {"map_recall", t.map_recall}};
    }
  } else {
    for (const char* k :
         {"loop_closures", "relocalisations", "keyframes_in_map", "map_points", "map_correction_m"})
      j[k] = nullptr;
  }
  if (r.dense) {
    const dense::DenseStats& d = r.dense_stats;
    j["dense"] = Json{{"keyframes", d.keyframes},
                      {"integrated", d.integrated},
                      {"dropped", d.dropped},
                      {"wrong_size", d.wrong_size},
                      {"cpu_s", d.cpu_s},
                      {"latency", histogram_json(d.latency)},
                      {"integrate", histogram_json(d.integrate)},
                      {"blocks", r.dense_blocks},
                      {"block_capacity", r.dense_block_capacity},
                      {"memory_mb", r.dense_memory_mb},
                      {"blocks_evicted", r.dense_counters.blocks_evicted},
                      {"blocks_refused", r.dense_counters.blocks_refused},
                      {"surface_points", r.dense_points},
                      {"map_frame_rebuilt", d.rebuilt},
                      {"map_frame_keyframes", d.rebuild.fused},
                      {"map_frame_no_pose", d.rebuild.no_pose},
                      {"map_frame_rebuild_cpu_s", 1e-9 * static_cast<double>(d.rebuild.cpu_ns)},
                      {"map_frame_surface_points", r.dense_map_points},
                      {"live_reanchor", r.dense_live_reanchor},
                      {"live_blocks", r.dense_live_blocks},
                      {"corrections", d.corrections},
                      {"corrections_dropped", d.corrections_dropped},
                      {"reanchored", d.reanchored},
                      {"reanchor_cpu_s", d.reanchor_cpu_s},
                      {"reanchor_pending_max", d.reanchor_pending_max},
                      {"reanchor_left", d.reanchor_left},
                      {"map_keyframe_lists", d.map_moves},
                      {"reanchor_catch_up", histogram_json(d.reanchor_catch_up)},
                      {"w_rebuild_keyframes", r.dense_w_rebuild.fused},
                      {"w_rebuild_cpu_s", 1e-9 * static_cast<double>(r.dense_w_rebuild.cpu_ns)},
                      {"view_messages", d.view_messages},
                      {"view_bytes", d.view_bytes},
                      {"view_no_slot", d.view_no_slot},
                      {"archive_capacity", r.dense_archive_capacity},
                      {"archive_overwritten", r.dense_archive_overwritten}};
  } else {
    j["dense"] = nullptr;
  }
  j["optimizer_threaded"] = r.optimizer_threaded;
  const rt::PerfValues& n = r.counters;
  j["imu_rate_poses"] = n.count("output.imu_rate_poses");
  j["records"] = Json{{"imu", r.replay.imu_pushed},
                      {"frames", r.replay.frames_pushed},
                      {"ground_truth", r.replay.ground_truth},
                      {"events", r.replay.events}};
  j["drops"] = Json{{"imu_ring", n.count("rings.imu_drops")},
                    {"frame_ring", n.count("rings.frame_drops")},
                    {"output_ring", n.count("rings.output_drops")},
                    {"image_pool_exhausted", n.count("rings.image_pool_exhausted")},
                    {"propagator_forward", n.count("rings.propagator_forward_drops")},
                    {"images_too_large", r.replay.images_too_large},
                    {"depth_unpaired", r.replay.depth_unpaired},
                    {"right_unpaired", r.replay.right_unpaired}};
  j["input_faults"] = Json{{"missing", n.count("input.frames_missing")},
                           {"out_of_order", n.count("input.frames_out_of_order")},
                           {"repeated", n.count("input.frames_repeated")},
                           {"no_depth", n.count("input.frames_no_depth")},
                           {"imu_gaps", n.count("input.imu_gaps")}};
  j["mavlink"] = Json{{"sent", n.count("mavlink.odometry_sent")},
                      {"failed", n.count("mavlink.send_failed")},
                      {"heartbeats", n.count("mavlink.heartbeats_sent")},
                      {"frames", n.count("mavlink.frames_sent")},
                      {"timesync_answered", n.count("mavlink.timesync_answered")},
                      {"timesync_converged", r.mavlink_timesync_converged},
                      {"timesync_offset_ms", json_figure(r.mavlink_timesync_offset_ms)},
                      {"signing", r.mavlink_signing},
                      {"unauthenticated", n.count("mavlink.unauthenticated")}};
  j["time_offset_ms"] = json_figure(r.time_offset_ms);
  j["time_offset_estimated"] = r.time_offset_estimated;
  const auto& c = r.estimator_counters;
  // Contract keys (issue 17): how often the backend said it had lost the
  // truth, and how long it coasted on the IMU alone.
  const core::DivergenceCounts& dv = c.divergence;
  j["divergences"] = dv.divergences;
  j["coast_seconds"] = 1e-9 * static_cast<double>(dv.coast_ns);
  {
    Json causes = Json::object();
    for (int k = 1; k < core::kDivergenceCauseCount; ++k)
      causes[core::to_string(static_cast<core::DivergenceCause>(k))] = dv.by_cause[static_cast<size_t>(k)];
    j["divergence"] = Json{{"causes", std::move(causes)},
                           {"restarts_while_lost", dv.restarts_while_lost},
                           {"coast_timeouts", dv.coast_timeouts},
                           {"lost_seconds", 1e-9 * static_cast<double>(dv.lost_ns)},
                           {"lost_poses_withheld", n.count("output.lost_poses_withheld")}};
  }
  j["estimator_counters"] = Json{{"imu_in", c.imu_in},
                                 {"imu_used", c.imu_used},
                                 {"frames_in", c.frames_in},
                                 {"frames_used", c.frames_used},
                                 {"resets", c.resets},
                                 {"imu_non_finite", c.imu_rejects.non_finite},
                                 {"imu_saturated", c.imu_rejects.saturated},
                                 {"imu_out_of_order", c.imu_rejects.out_of_order},
                                 {"imu_gaps", c.imu_rejects.gaps}};
  Json alloc = Json::object();
  alloc["counting"] = r.alloc_counting;
  alloc["estimator_thread_steady"] = r.alloc_counting ? Json(r.steady_allocs) : Json(nullptr);
  alloc["steady_frames"] = r.steady_frames;
  alloc["per_frame"] =
      json_figure(r.alloc_counting && r.steady_frames > 0
                      ? static_cast<double>(r.steady_allocs) / static_cast<double>(r.steady_frames)
                      : std::nan(""));
  j["allocations"] = std::move(alloc);
  Json threads = Json::array();
  for (const AppliedThread& t : r.threads) {
    threads.push_back(Json{{"name", t.name},
                           {"cpu", static_cast<int64_t>(t.cpu)},
                           {"policy", t.policy},
                           {"priority", static_cast<int64_t>(t.priority)},
                           {"applied", t.applied},
                           {"error", t.error}});
  }
  j["threads"] = std::move(threads);
  const uint64_t map_clouds = n.count("ros2.map_clouds");
  const uint64_t map_clouds_dropped = n.count("ros2.map_clouds_dropped");
  const uint64_t map_keyframes_dropped = n.count("ros2.map_keyframes_dropped");
  if (map_clouds + map_clouds_dropped + map_keyframes_dropped > 0) {
    j["ros2_map_topics"] = Json{{"clouds", map_clouds},
                                {"clouds_dropped", map_clouds_dropped},
                                {"keyframes_dropped", map_keyframes_dropped}};
  }
  if (r.view) {
    const viewer::ServerStats& v = r.viewer;
    const bool streamed = v.streaming_s > 0;
    j["viewer"] =
        Json{{"browsers", v.clients},
             {"browsers_peak", static_cast<int64_t>(v.clients_peak)},
             {"streaming_s", json_figure(v.streaming_s)},
             {"kbytes_per_s", streamed ? 1e-3 * static_cast<double>(v.streaming_bytes) / v.streaming_s : 0.0},
             {"cpu_ms_per_s", streamed ? 1e3 * v.streaming_cpu_s / v.streaming_s : 0.0},
             {"cpu_s", json_figure(v.cpu_s)},
             {"bytes_sent", v.bytes_sent},
             {"snapshots_published", n.count("viewer.snapshots_published")},
             {"snapshots_skipped", n.count("viewer.snapshots_skipped")},
             {"frames_sent", v.frames_sent},
             {"frames_skipped_budget", v.frames_skipped_budget},
             {"frames_skipped_backlog", v.frames_skipped_backlog},
             {"connections", v.connections},
             {"connections_refused", v.connections_refused},
             {"browsers_refused", v.clients_refused},
             {"browsers_dropped", v.clients_dropped},
             {"http_requests", v.http_requests},
             {"http_errors", v.http_errors},
             {"protocol_errors", v.protocol_errors},
             {"commands", v.commands},
             {"bad_commands", v.bad_commands}};
  }
  j["counters"] = counters_json(n);
  Json problems = Json::array();
  for (const auto& p : r.problems)
    problems.push_back(Json{{"where", p.where}, {"kind", p.kind}, {"detail", p.detail}});
  j["problems"] = std::move(problems);
  return tools::json_text(j);
}

void frame_stats(const core::Estimator& est, int& features, int& inliers) {
  features = inliers = -1;
  if (const core::Tracker* t = core::tracker_of(est)) {
    features = t->last().detected;
    inliers = t->last().inliers;
  }
}

std::string format_status(const PipelineStatus& s, const rt::PerfValues& n) {
  const char* state = "uninit";
  switch (s.quality) {
    case core::TrackingQuality::kTracking:
      state = "tracking";
      break;
    case core::TrackingQuality::kImuOnly:
      state = "imu-only";
      break;
    case core::TrackingQuality::kLost:
      state = "lost";
      break;
    case core::TrackingQuality::kVisionOnly:
      state = "vision";
      break;
    case core::TrackingQuality::kUninitialized:
      break;
  }
  char buf[512];
  std::snprintf(
      buf, sizeof buf,
      "[%7.1f s] %-8s resets %u | feat %d inl %d | frames %llu/s | track max %.1f ms | imu->estimator max "
      "%.2f ms | drops imu %llu frame %llu | imu rej %llu gaps %llu | cam miss %llu ooo %llu frozen %llu "
      "nodepth %llu",
      s.t_s, state, s.reset_counter, s.features, s.inliers,
      static_cast<unsigned long long>(s.frames_in_window), 1e-6 * static_cast<double>(s.tracking_max_ns),
      1e-6 * static_cast<double>(s.imu_to_output_max_ns),
      static_cast<unsigned long long>(n.count("rings.imu_drops")),
      static_cast<unsigned long long>(n.count("rings.frame_drops")),
      static_cast<unsigned long long>(n.count("estimator.imu_rejects.non_finite") +
                                      n.count("estimator.imu_rejects.saturated") +
                                      n.count("estimator.imu_rejects.out_of_order")),
      static_cast<unsigned long long>(n.count("input.imu_gaps")),
      static_cast<unsigned long long>(n.count("input.frames_missing")),
      static_cast<unsigned long long>(n.count("input.frames_out_of_order")),
      static_cast<unsigned long long>(n.count("input.frames_repeated")),
      static_cast<unsigned long long>(n.count("input.frames_no_depth")));
  std::string line = buf;
  // The map's state: a lost map (after a loss, or a loaded map not found yet) maps nothing until it
  // relocalises.
  if (s.map.active) {
    std::snprintf(buf, sizeof buf, " | map %s, %u kf, loops %llu, relocs %llu",
                  s.map.localized ? "localized" : "LOST", s.map.keyframes,
                  static_cast<unsigned long long>(s.map.loop_closures),
                  static_cast<unsigned long long>(s.map.relocalisations));
    line += buf;
  }
  return line;
}

std::string replay_summary(const ReplayReport& r) {
  const rt::PerfValues& n = r.counters;
  char buf[512];
  std::string s;
  std::snprintf(buf, sizeof buf, "estimator: %s (pace %s)\nlog: %s [%s], %.2f s of data\n",
                r.estimator.c_str(), drivers::to_string(r.pace), r.log_path.c_str(), r.log_format.c_str(),
                r.log_duration_s);
  s += buf;
  std::snprintf(
      buf, sizeof buf,
      "records: %llu IMU, %llu frames; poses out: %zu\nwall %.3f s, real-time factor %.1fx, cpu %.3f s "
      "(the estimator's work %.3f s), peak RSS %.1f MB\n",
      static_cast<unsigned long long>(r.replay.imu_pushed),
      static_cast<unsigned long long>(r.replay.frames_pushed), r.trajectory.size(), r.wall_s,
      r.realtime_factor, r.cpu_s, r.estimator_cpu_s, r.peak_rss_mb);
  s += buf;
  if (r.stereo) {
    // Stereo: how many frames lost their right image, by cause (docs/stereo.md).
    std::snprintf(
        buf, sizeof buf,
        "stereo: rectified at start-up, baseline %.4f m; frames without a right image %llu (right images "
        "unpaired: %llu)\n",
        r.stereo_baseline_m, static_cast<unsigned long long>(n.count("input.frames_no_depth")),
        static_cast<unsigned long long>(r.replay.right_unpaired));
    s += buf;
  }
  if (r.imu_to_output.count() > 0) {
    std::snprintf(buf, sizeof buf, "imu->output latency: p50 %.3f ms, p99 %.3f ms, max %.3f ms\n",
                  1e-6 * static_cast<double>(r.imu_to_output.percentile(50)),
                  1e-6 * static_cast<double>(r.imu_to_output.percentile(99)),
                  1e-6 * static_cast<double>(r.imu_to_output.max()));
    s += buf;
  }
  const auto& c = r.estimator_counters.imu_rejects;
  std::snprintf(
      buf, sizeof buf,
      "drops: imu ring %llu, frame ring %llu, output %llu; imu rejected: %llu non-finite, %llu saturated, "
      "%llu out of order, %llu gaps\n",
      static_cast<unsigned long long>(n.count("rings.imu_drops")),
      static_cast<unsigned long long>(n.count("rings.frame_drops")),
      static_cast<unsigned long long>(n.count("rings.output_drops")),
      static_cast<unsigned long long>(c.non_finite), static_cast<unsigned long long>(c.saturated),
      static_cast<unsigned long long>(c.out_of_order), static_cast<unsigned long long>(c.gaps));
  s += buf;
  if (r.optimizer.count() > 0) {
    std::snprintf(buf, sizeof buf, "optimizer (%s): %llu solves, p50 %.2f ms, p99 %.2f ms, max %.2f ms\n",
                  r.optimizer_threaded ? "own thread" : "inline",
                  static_cast<unsigned long long>(r.optimizer.count()),
                  1e-6 * static_cast<double>(r.optimizer.percentile(50)),
                  1e-6 * static_cast<double>(r.optimizer.percentile(99)),
                  1e-6 * static_cast<double>(r.optimizer.max()));
    s += buf;
  }
  if (!r.backend_summary.empty()) s += r.backend_summary + "\n";
  if (r.loop_truth) s += loop_truth_summary(*r.loop_truth) + "\n";
  {
    const core::DivergenceCounts& dv = r.estimator_counters.divergence;
    std::string causes;
    for (int k = 1; k < core::kDivergenceCauseCount; ++k) {
      const uint64_t n = dv.by_cause[static_cast<size_t>(k)];
      if (n == 0) continue;
      causes += (causes.empty() ? " (" : ", ") +
                std::string(core::to_string(static_cast<core::DivergenceCause>(k))) + " " + std::to_string(n);
    }
    if (!causes.empty()) causes += ")";
    std::snprintf(
        buf, sizeof buf,
        "divergences: %llu%s; coasting %.2f s, %llu coast timeouts, lost %.2f s (%llu restarts while lost, "
        "%llu lost poses left out of the trajectory)\n",
        static_cast<unsigned long long>(dv.divergences), causes.c_str(),
        1e-9 * static_cast<double>(dv.coast_ns), static_cast<unsigned long long>(dv.coast_timeouts),
        1e-9 * static_cast<double>(dv.lost_ns), static_cast<unsigned long long>(dv.restarts_while_lost),
        static_cast<unsigned long long>(n.count("output.lost_poses_withheld")));
    s += buf;
  }
  std::snprintf(buf, sizeof buf, "camera-IMU time offset: %.3f ms (%s)\n", r.time_offset_ms,
                r.time_offset_estimated ? "the rig's plus the online estimate" : "the rig's; not estimated");
  s += buf;
  if (r.has_map) {
    std::snprintf(
        buf, sizeof buf,
        "map threads: mapping %llu keyframes, p50 %.1f ms, p99 %.1f ms, cpu %.1f s; loop p50 %.1f ms, "
        "p99 %.1f ms, cpu %.1f s; loop closures %llu, relocalisations %llu, |t(T_map_odom)| %.3f m\n",
        static_cast<unsigned long long>(r.mapping.count()),
        1e-6 * static_cast<double>(r.mapping.percentile(50)),
        1e-6 * static_cast<double>(r.mapping.percentile(99)), r.mapping_cpu_s,
        1e-6 * static_cast<double>(r.loop.percentile(50)), 1e-6 * static_cast<double>(r.loop.percentile(99)),
        r.loop_cpu_s, static_cast<unsigned long long>(r.map.loop_closures),
        static_cast<unsigned long long>(r.map.relocalisations), r.map.T_map_odom().translation().norm());
    s += buf;
    if (r.global_ba && r.global_ba->runs > 0) {
      std::snprintf(
          buf, sizeof buf,
          "global BA after loops: %llu runs (%llu failed), last %llu keyframes, %llu points; solve p50 %.0f "
          "ms, max %.0f ms; largest keyframe move %.3f m\n",
          static_cast<unsigned long long>(r.global_ba->runs),
          static_cast<unsigned long long>(r.global_ba->failures),
          static_cast<unsigned long long>(r.global_ba->keyframes),
          static_cast<unsigned long long>(r.global_ba->points),
          1e-6 * static_cast<double>(r.global_ba_solve.percentile(50)),
          1e-6 * static_cast<double>(r.global_ba_solve.max()), r.global_ba->max_keyframe_move_m);
      s += buf;
    }
  }
  const uint64_t missing = n.count("input.frames_missing"),
                 out_of_order = n.count("input.frames_out_of_order"),
                 repeated = n.count("input.frames_repeated"), no_depth = n.count("input.frames_no_depth"),
                 imu_gaps = n.count("input.imu_gaps");
  if (missing + out_of_order + repeated + no_depth + imu_gaps > 0) {
    std::snprintf(
        buf, sizeof buf,
        "input faults: %llu frames missing, %llu out of order (withheld), %llu repeated (withheld), %llu "
        "without depth; %llu IMU gaps\n",
        static_cast<unsigned long long>(missing), static_cast<unsigned long long>(out_of_order),
        static_cast<unsigned long long>(repeated), static_cast<unsigned long long>(no_depth),
        static_cast<unsigned long long>(imu_gaps));
    s += buf;
  }
  s += threads_summary(r.threads);
  if (!r.propagator_thread.empty()) {
    s += "IMU-rate propagation " + r.propagator_thread + ", " +
         std::to_string(n.count("output.imu_rate_poses")) + " IMU-rate poses published\n";
  }
  if (n.count("mavlink.frames_sent") + n.count("mavlink.send_failed") > 0) {
    std::snprintf(buf, sizeof buf, "MAVLink ODOMETRY: %llu sent, %llu failed; %llu HEARTBEAT; TIMESYNC %s\n",
                  static_cast<unsigned long long>(n.count("mavlink.odometry_sent")),
                  static_cast<unsigned long long>(n.count("mavlink.send_failed")),
                  static_cast<unsigned long long>(n.count("mavlink.heartbeats_sent")),
                  r.mavlink_timesync_converged ? "converged" : "no answer from an autopilot");
    s += buf;
    if (r.mavlink_signing) {
      std::snprintf(buf, sizeof buf,
                    "MAVLink signing on: %llu frames from the autopilot refused (unsigned, wrongly "
                    "signed or replayed)\n",
                    static_cast<unsigned long long>(n.count("mavlink.unauthenticated")));
      s += buf;
    }
  }
  if (r.view) s += viewer::stats_summary(r.viewer);
  const uint64_t map_clouds = n.count("ros2.map_clouds");
  const uint64_t map_clouds_dropped = n.count("ros2.map_clouds_dropped");
  const uint64_t map_keyframes_dropped = n.count("ros2.map_keyframes_dropped");
  if (map_clouds + map_clouds_dropped + map_keyframes_dropped > 0) {
    std::snprintf(buf, sizeof buf,
                  "ros2 map topics: %llu point clouds; dropped %llu clouds, %llu keyframes (output behind)\n",
                  static_cast<unsigned long long>(map_clouds),
                  static_cast<unsigned long long>(map_clouds_dropped),
                  static_cast<unsigned long long>(map_keyframes_dropped));
    s += buf;
  }
  if (r.dense) {
    const dense::DenseStats& d = r.dense_stats;
    std::snprintf(
        buf, sizeof buf,
        "dense map: %llu keyframes fused, %llu dropped, %llu wrong size; keyframe->map p50 %.1f ms, "
        "p99 %.1f ms; cpu %.2f s; %d of %d blocks (%.0f MB), %llu evicted, %llu refused; %llu surface "
        "points\n",
        static_cast<unsigned long long>(d.integrated), static_cast<unsigned long long>(d.dropped),
        static_cast<unsigned long long>(d.wrong_size), 1e-6 * static_cast<double>(d.latency.percentile(50)),
        1e-6 * static_cast<double>(d.latency.percentile(99)), d.cpu_s, r.dense_blocks, r.dense_block_capacity,
        r.dense_memory_mb, static_cast<unsigned long long>(r.dense_counters.blocks_evicted),
        static_cast<unsigned long long>(r.dense_counters.blocks_refused),
        static_cast<unsigned long long>(r.dense_points));
    s += buf;
    if (r.dense_live_reanchor) {
      std::snprintf(
          buf, sizeof buf,
          "dense map live re-anchoring: %llu corrections (%llu dropped), %llu map keyframe lists, "
          "%llu keyframes re-fused, %.2f CPU-s, at most %d waiting, %d left at the end, caught up p50 "
          "%.0f ms max %.0f ms; --dense-out along W: %d keyframes %.2f s\n",
          static_cast<unsigned long long>(d.corrections),
          static_cast<unsigned long long>(d.corrections_dropped),
          static_cast<unsigned long long>(d.map_moves), static_cast<unsigned long long>(d.reanchored),
          d.reanchor_cpu_s, d.reanchor_pending_max, d.reanchor_left,
          1e-6 * static_cast<double>(d.reanchor_catch_up.percentile(50)),
          1e-6 * static_cast<double>(d.reanchor_catch_up.max()), r.dense_w_rebuild.fused,
          1e-9 * static_cast<double>(r.dense_w_rebuild.cpu_ns));
      s += buf;
    }
    if (d.view_messages > 0 || d.view_no_slot > 0) {
      std::snprintf(
          buf, sizeof buf,
          "dense map to the viewer: %llu messages, %.1f kB encoded, %llu rounds without a free slot\n",
          static_cast<unsigned long long>(d.view_messages), 1e-3 * static_cast<double>(d.view_bytes),
          static_cast<unsigned long long>(d.view_no_slot));
      s += buf;
    }
    if (d.rebuilt) {
      std::snprintf(
          buf, sizeof buf,
          "dense map in the map frame: %d keyframes re-fused (%d without a pose, %llu overwritten in "
          "the archive of %d), %.2f s; %llu surface points\n",
          d.rebuild.fused, d.rebuild.no_pose, static_cast<unsigned long long>(r.dense_archive_overwritten),
          r.dense_archive_capacity, 1e-9 * static_cast<double>(d.rebuild.cpu_ns),
          static_cast<unsigned long long>(r.dense_map_points));
      s += buf;
    }
  }
  if (r.alloc_counting) {
    std::snprintf(buf, sizeof buf, "estimator-thread heap allocations after warm-up: %lld\n",
                  static_cast<long long>(r.steady_allocs));
    s += buf;
  }
  if (!r.problems.empty()) {
    std::snprintf(buf, sizeof buf, "log problems: %zu (first: %s %s %s)\n", r.problems.size(),
                  r.problems.front().where.c_str(), r.problems.front().kind.c_str(),
                  r.problems.front().detail.c_str());
    s += buf;
  }
  return s;
}

}  // namespace kestrel::cli

// The dense map's thread (kst-dense, not real time) and its hand-off from the
// estimator thread. The estimator thread offers every tracked frame; the
// mapper keeps those that moved enough since the last one kept (its
// keyframes), copies depth and colour into one of a few slots sized at
// start-up and rings the thread. No slot free: the frame is dropped and
// counted in realtime pace (the estimator never waits for the map); the
// deterministic paces wait, so the map is the same on every run. docs/dense.md.
#pragma once

#include <Eigen/Geometry>
#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <shared_mutex>
#include <thread>
#include <vector>

#include "kestrel/core/keyframe_archive.hpp"
#include "kestrel/core/tsdf_map.hpp"
#include "kestrel/dense/dense_view.hpp"
#include "kestrel/msgs.hpp"
#include "kestrel/rt/doorbell.hpp"
#include "kestrel/rt/latency_histogram.hpp"
#include "kestrel/rt/spsc_ring.hpp"
#include "kestrel/rt/thread_setup.hpp"

namespace kestrel::dense {

struct DenseOptions {
  bool enabled = false;
  core::TsdfOptions tsdf;
  // A frame becomes a dense keyframe when it moved this far from the last one,
  // turned this much, or this long passed.
  double keyframe_distance_m = 0.10;
  double keyframe_angle_deg = 10.0;
  double keyframe_interval_s = 1.0;
  // Frames waiting for the thread (each a depth and a colour image of the rig's size).
  int handoff_slots = 4;
  // The keyframes' depth kept for a re-integration along the map's corrected
  // poses (--dense-map-out); budget 0 turns it off.
  core::KeyframeArchiveOptions archive;
  // Live re-anchoring (docs/dense.md): keyframes are fused from the archive in
  // the map frame M (the correction T_map_odom the pipeline passes), and when
  // the correction moves them they are taken out and fused again where they
  // now are, within a CPU budget. Needs the archive (archive.budget_mb > 0).
  bool live_reanchor = false;
  double reanchor_min_shift_m = 0.02;   // a keyframe is re-fused when its camera moved this far ...
  double reanchor_min_angle_deg = 0.5;  // ... or turned this much
  double reanchor_cpu_s_per_s = 0.05;   // CPU-seconds of re-fusion per second of wall time, at most
  double reanchor_burst_cpu_s = 0.25;   // unspent budget is kept up to this [CPU-s]
  void validate() const;                // throws std::invalid_argument naming the key
};

// The map's word on one of its keyframes: the correction C_MW = T_MB * T_WB^-1
// that takes the odometry's pose at t_ns to the map's.
struct MapCorrection {
  int64_t t_ns = 0;
  Eigen::Isometry3d C_MW = Eigen::Isometry3d::Identity();
};

struct DenseStats {
  uint64_t offered = 0;     // tracked frames the estimator thread offered
  uint64_t keyframes = 0;   // selected as dense keyframes
  uint64_t dropped = 0;     // selected, no free slot (realtime pace only)
  uint64_t wrong_size = 0;  // images not of the rig's size: not fused, counted
  uint64_t integrated = 0;
  double cpu_s = 0;                // the thread's, after stop()
  rt::LatencyHistogram latency;    // hand-off -> fused in the map
  rt::LatencyHistogram integrate;  // per keyframe, the fusion alone
  // The re-integration in the map frame (rebuild_along), when it ran.
  bool rebuilt = false;
  core::ReintegrationReport rebuild;
  // Live re-anchoring.
  uint64_t corrections = 0;          // changes of T_map_odom received
  uint64_t corrections_dropped = 0;  // their ring was full (the thread was seconds behind)
  uint64_t map_moves = 0;            // the map's keyframe lists received (note_map_keyframes)
  uint64_t reanchored = 0;           // keyframes taken out and fused again
  double reanchor_cpu_s = 0;         // the CPU that cost
  int reanchor_pending_max = 0;      // keyframes waiting for it, at most (sampled after each correction)
  int reanchor_left = 0;             // still waiting when the thread stopped (the budget ran out first)
  rt::LatencyHistogram reanchor_catch_up;  // correction received -> every keyframe it moved re-fused
  // The viewer stream (attach_view).
  uint64_t view_messages = 0, view_bytes = 0, view_no_slot = 0;
};

class DenseMapper {
 public:
  // Starts the thread when opt.enabled (nothing otherwise). `wait_when_full`:
  // the deterministic paces. T_BC: camera -> body, from the rig.
  DenseMapper(const DenseOptions& opt, const Rig& rig, bool wait_when_full);
  ~DenseMapper();
  DenseMapper(const DenseMapper&) = delete;
  DenseMapper& operator=(const DenseMapper&) = delete;

  bool enabled() const { return started_; }
  // Estimator thread, after a tracked frame; T_WB its pose. Allocation- and lock-free.
  void offer(int64_t t_ns, const ImageView& rgb, const ImageView& depth, const Eigen::Isometry3d& T_WB);
  // Estimator thread, every frame (before offer): the map's correction
  // T_map_odom = C_MW and its change counter (MapFrameState::alignment). Only
  // a change is passed on (a ring). Allocation- and lock-free. Used by live_reanchor.
  void note_correction(int64_t t_ns, uint32_t alignment, const Eigen::Isometry3d& C_MW);
  // The map's loop thread, after it moved its keyframes (a loop closed, a
  // global bundle adjustment applied), with their corrections sorted by time.
  // With live_reanchor every archived keyframe within their span then takes
  // its correction from the two map keyframes around it instead of
  // T_map_odom shared out over time: a bundle adjustment that moves keyframes
  // one by one is followed in flight. Copied under a mutex (neither thread is
  // real time; the estimator thread never calls it). Allocates.
  void note_map_keyframes(const std::vector<MapCorrection>& sorted);
  // Before the first offer: the viewer's stream, at most view.max_kbps [kbit/s]
  // (encoded on kst-dense; the sink must outlive stop()). Allocates the encoder.
  void attach_view(DenseViewSink* sink, const DenseViewOptions& view);
  // Waits until the thread fused everything handed over.
  void wait_idle();
  // Fuses what was handed over, then joins. Idempotent.
  void stop();
  // After stop(): the map, in W (the frame of the trajectory output).
  const core::TsdfMap& map() const { return *map_; }
  // After stop(): clears the map and fuses every archived keyframe again,
  // moved by the correction C_MW(t_ns) = T_MB(t) * T_WB(t)^-1 that C_MW_of gives
  // for its time (the map's final trajectory after loops and bundle
  // adjustments against the odometry it was fused along), so map() is then in
  // that frame M. The same memory: write what W needs first. False from
  // C_MW_of: the keyframe is left out, counted.
  void rebuild_along(const std::function<bool(int64_t t_ns, Eigen::Isometry3d& C_MW)>& C_MW_of);
  // The archive (after stop()): capacity, counters.
  const core::KeyframeArchive* archive() const { return archive_.get(); }
  // ---- A planner's queries in flight: any thread but a real-time one (they
  // wait while kst-dense fuses or moves one keyframe, a few ms). The frame is
  // the live map's: W, or the map frame M with live_reanchor (live_frame_is_map).
  // The map not running: unknown / false. docs/dense.md "Live queries".
  core::Occupancy occupancy(const Eigen::Vector3d& p) const;
  core::Occupancy segment(const Eigen::Vector3d& a, const Eigen::Vector3d& b) const;
  bool distance(const Eigen::Vector3d& p, float& sdf_m) const;
  // Anything else TsdfMap offers (extract_surface, ...), under the same lock.
  void read(const std::function<void(const core::TsdfMap&)>& fn) const;
  bool live_frame_is_map() const { return opt_.live_reanchor; }
  uint64_t queries() const { return queries_.load(std::memory_order_relaxed); }
  // Any thread, approximate: keyframes a correction moved that wait to be re-fused.
  int reanchor_backlog() const { return reanchor_backlog_.load(std::memory_order_acquire); }
  // Any thread: corrections the thread has taken in (their backlog is then known).
  uint64_t corrections_applied() const { return corrections_applied_.load(std::memory_order_acquire); }
  // Any thread: the map's keyframe lists the thread has taken in.
  uint64_t map_moves_applied() const { return map_moves_applied_.load(std::memory_order_acquire); }
  const DenseStats& stats() const { return stats_; }
  const DenseOptions& options() const { return opt_; }
  // The thread's row (name, priority, CPU) and what it was granted.
  static const rt::ThreadSpec& thread_spec();
  const rt::ThreadSetupReport& thread_report() const { return thread_report_; }

 private:
  struct Slot {
    int64_t t_ns = 0;
    int64_t handed_ns = 0;
    Eigen::Isometry3d T_WC = Eigen::Isometry3d::Identity();
    Eigen::Isometry3d C_MW = Eigen::Isometry3d::Identity();  // the correction when it was taken
    ImageView rgb, depth;
    std::vector<uint8_t> rgb_bytes, depth_bytes;
  };
  static constexpr std::size_t kRingCapacity = 64;
  struct Correction {
    int64_t t_ns = 0;
    int64_t received_ns = 0;
    Eigen::Isometry3d C_MW = Eigen::Isometry3d::Identity();
  };
  void run();
  void fuse_slot(Slot& s);
  void apply_correction(const Correction& c);
  void apply_map_keyframes();
  // The map's correction at t from its keyframe list, when t lies within it.
  bool map_correction_at(int64_t t_ns, Eigen::Isometry3d& C_MW) const;
  bool reanchor_one();  // false: nothing due, or no budget now
  int reanchor_pending(int* worst) const;
  void pump_view();
  bool is_keyframe(int64_t t_ns, const Eigen::Isometry3d& T_WB) const;

  DenseOptions opt_;
  Rig rig_;
  Eigen::Isometry3d T_BC_ = Eigen::Isometry3d::Identity();
  bool wait_when_full_ = false;
  bool started_ = false;
  std::unique_ptr<core::TsdfMap> map_;
  std::unique_ptr<core::KeyframeArchive> archive_;  // written on kst-dense only
  std::vector<Slot> slots_;
  rt::SpscRing<uint32_t, kRingCapacity> filled_;  // estimator -> dense
  rt::SpscRing<uint32_t, kRingCapacity> free_;    // dense -> estimator
  rt::Doorbell work_bell_, free_bell_;
  std::atomic<bool> stop_{false};
  std::atomic<uint64_t> handed_{0}, done_{0};
  std::thread thread_;
  rt::ThreadSetupReport thread_report_;
  bool have_last_ = false;
  int64_t last_t_ns_ = 0;
  Eigen::Isometry3d last_T_WB_ = Eigen::Isometry3d::Identity();
  DenseStats stats_;
  // Live re-anchoring. Estimator thread: the newest correction and its counter.
  bool have_alignment_ = false;
  uint32_t alignment_ = 0;
  Eigen::Isometry3d C_now_ = Eigen::Isometry3d::Identity();
  rt::SpscRing<Correction, 64> corrections_;  // estimator -> dense
  // kst-dense: per archived keyframe (indexed by its store number modulo the
  // archive's capacity) the correction it is fused with and the one it should have.
  std::vector<Eigen::Isometry3d> fused_C_, target_C_;
  Correction last_correction_;  // the interval start for the next one
  bool have_correction_ = false;
  int64_t interval_t_a_ = 0;  // where the newest correction's interval began, and the correction then
  Eigen::Isometry3d interval_C_a_ = Eigen::Isometry3d::Identity();
  // The map's keyframe corrections: handed in under map_moves_mutex_, used on kst-dense.
  std::mutex map_moves_mutex_;
  std::vector<MapCorrection> map_moves_in_;
  std::atomic<bool> map_moves_ready_{false};
  std::vector<MapCorrection> map_C_;  // kst-dense: the newest list
  std::atomic<int> reanchor_backlog_{0};
  std::atomic<uint64_t> corrections_applied_{0}, map_moves_applied_{0};
  double reanchor_tokens_cpu_s_ = 0;
  int64_t reanchor_refill_ns_ = -1;
  int64_t catch_up_since_ns_ = -1;  // a correction left keyframes to re-fuse since then
  // Held exclusively by kst-dense while it changes the map (fusion,
  // re-anchoring, the end's re-integration), shared by the queries above. The
  // estimator thread never takes it. kst-dense's own reads need no lock.
  mutable std::shared_mutex map_mutex_;
  mutable std::atomic<uint64_t> queries_{0};
  // The viewer stream (kst-dense).
  std::atomic<DenseViewSink*> view_sink_{nullptr};
  std::unique_ptr<DenseViewEncoder> view_encoder_;
  std::unique_ptr<ByteBudget> view_budget_;
  int64_t view_period_ns_ = 0;
  int64_t view_next_round_ns_ = 0;
};

}  // namespace kestrel::dense

// The map beside the odometry: the hand-off between the tracking thread and
// the mapping and loop-closing threads (paper 001's three threads), and the
// work those two threads do. docs/map.md.
//
//   tracking thread --KeyframePacket slots--> SpscRing --> mapping thread
//        ^                                                   | LocalMapper: insert, fuse,
//        |                                                   | local BA, cull
//        +--MapUpdate slots (refined points, T_map_odom)-----+
//                                                            v
//                                            loop thread (place recognition,
//                                            loop closing, relocalisation)
//
// The tracking side never allocates and never waits: keyframe packets and
// updates are fixed pools whose slot indices travel through SPSC rings; with
// every packet in flight a keyframe is not mapped (counted), and an update
// the tracking side has not taken is replaced by the next one. The mapping
// and loop threads share the Map and are serialised by their caller (the
// harness holds one mutex around mapping_step() and loop_step(): the two
// workers' group, EstimatorWorker): core has no threads and no locks.
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/core/depth_grid.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/core/global_bundle_adjustment.hpp"
#include "kestrel/core/local_mapper.hpp"
#include "kestrel/core/loop_closer.hpp"
#include "kestrel/core/map.hpp"
#include "kestrel/core/relocaliser.hpp"
#include "kestrel/rt/latency_histogram.hpp"
#include "kestrel/rt/mailbox.hpp"
#include "kestrel/rt/perf.hpp"
#include "kestrel/rt/spsc_ring.hpp"

namespace kestrel::core {

struct MapSystemOptions {
  bool mapping = true;  // the map and the local mapping thread (--mapping on|off)
  bool loop = true;     // loop closing and relocalisation (--loop on|off; nothing without mapping)
  MapOptions map;
  LoopOptions closing;        // loop detection, verification, correction (loop_closer.hpp)
  GlobalBaOptions global_ba;  // after each closed loop (global_bundle_adjustment.hpp)
  // Place recognition's vocabulary file ("": the one built into `kestrel`,
  // configs/vocabulary/). Core does no I/O: tools load it into `vocabulary`;
  // without one, loop closing and relocalisation are off.
  std::string vocabulary_path;
  std::shared_ptr<const Vocabulary> vocabulary;
  // A map to start from (`--map-in`): the bytes of a map file (map_file.hpp),
  // read by tools; map_in_path names it in errors. The flight then starts
  // not localised and maps nothing until a relocalisation finds it there.
  std::shared_ptr<const std::vector<uint8_t>> map_in;
  std::string map_in_path;

  [[nodiscard]] std::string validate() const;
};

// Mapping -> tracking: the refined points around the newest keyframe, in W.
struct MapUpdate {
  uint64_t keyframe_seq = 0;  // the packet it answers
  // T_map_odom changed since the last update (a loop closure, a
  // relocalisation): the tracker's local map is emptied before these points
  // go in, since its old points sit where the old alignment put them.
  bool realigned = false;
  MapFrameState frame;
  int n = 0;
  MapPointUpdate* points = nullptr;  // capacity MapOptions::update_max_points
};

struct MapSystemCounters {
  uint64_t keyframes_submitted = 0;
  uint64_t keyframes_overrun = 0;  // no free packet: the tracking side went on without the map
  uint64_t keyframes_mapped = 0;
  uint64_t updates_published = 0;
  uint64_t updates_applied = 0;
  uint64_t updates_skipped = 0;  // no free update slot on the mapping side
  uint64_t keyframes_lost = 0;   // not mapped: taken while the map was not localised
  uint64_t reloc_timeouts = 0;   // lost past reloc_timeout_s: mapping went on in the odometry's alignment
};

class MapSystem {
 public:
  MapSystem(const MapCamera& cam, int features_per_keyframe, const MapSystemOptions& opt);
  ~MapSystem();
  MapSystem(const MapSystem&) = delete;
  MapSystem& operator=(const MapSystem&) = delete;

  // Before the first keyframe (allocates), for a rig with a depth image: each
  // keyframe then carries its depth grid (map.depth_grid_cols; depth_grid.hpp)
  // for the loop's surface verification. rgb: the colour camera as
  // calibrated, the depth registered to it.
  void enable_depth_grid(const CameraIntrinsics& rgb, const DepthModel& depth);
  const DepthGridShape& depth_grid_shape() const { return grid_sampler_.shape(); }

  // ---- tracking thread: no allocation, no waiting ----
  // The keyframe's depth grid from its depth image (nothing without
  // enable_depth_grid or without depth).
  void fill_depth_grid(KeyframePacket* p, const ImageView& depth) const;
  // A free packet (features sized for the tracker), or nullptr (counted).
  KeyframePacket* begin_keyframe();
  void submit_keyframe(KeyframePacket* p);
  void cancel_keyframe(KeyframePacket* p);
  // The newest update not yet taken, or nullptr; give it back with release_update().
  const MapUpdate* take_update();
  void release_update(const MapUpdate* u);
  // A submitted keyframe is not fully processed yet.
  bool busy() const { return in_flight_.load(std::memory_order_acquire) > 0; }
  // Latest state of the map's frame (any thread).
  MapFrameState frame() const;

  // ---- mapping thread ----
  bool mapping_step();
  // ---- loop thread ----
  // Under the harness's map lock. After a closed loop it copies the map for
  // the global bundle adjustment, and the call after global_ba_step() writes
  // the solution back; in between it does nothing (returns false).
  bool loop_step();
  // The global bundle adjustment's solve, WITHOUT the map lock (it reads only
  // its copy), on the loop thread after loop_step(); false when there is
  // none waiting. The mapping thread goes on meanwhile.
  bool global_ba_step();

  // ---- after the threads stopped (or from the mapping/loop threads) ----
  // The map file's bytes (map_file.hpp).
  std::vector<uint8_t> save() const;
  // This flight's keyframes as the map holds them now, body poses by time;
  // T_CB: camera to body (the one overload: set_T_CB's). Allocates.
  std::vector<MapKeyframePose> keyframe_poses(const Eigen::Isometry3d& T_CB) const;
  std::vector<MapKeyframePose> keyframe_poses() const { return keyframe_poses(T_CB_); }
  // The backend's camera -> body, for keyframe_poses() (identity until set).
  void set_T_CB(const Eigen::Isometry3d& T_CB) { T_CB_ = T_CB; }

  // The pipeline's view of the two threads' work (EstimatorWorker): kMapping
  // steps mapping_step(), kLoop steps loop_step() and, outside the map's
  // exclusion, global_ba_step(). They share the map (one group).
  EstimatorWorker& mapping_worker() { return mapping_worker_; }
  EstimatorWorker& loop_worker() { return loop_worker_; }
  Map& map() { return *map_; }
  const Map& map() const { return *map_; }
  const LocalMapper& mapper() const { return *mapper_; }
  const LoopCloser& loop_closer() const { return *closer_; }
  // Before the flight: keep the loop closer's log (LoopCloser::set_logging).
  void set_loop_logging(bool on) { closer_->set_logging(on); }
  const Relocaliser* relocaliser() const { return reloc_.get(); }
  // nullptr when off (map.global_ba, or no loop closing).
  const GlobalBundleAdjustment* global_ba() const { return gba_.get(); }
  const rt::LatencyHistogram& global_ba_latency() const { return gba_latency_; }
  const MapSystemCounters& counters() const { return counters_; }
  const rt::LatencyHistogram& mapping_latency() const { return mapping_latency_; }
  const rt::LatencyHistogram& loop_latency() const { return loop_latency_; }
  const MapSystemOptions& options() const { return opt_; }
  std::string summary() const;

  // Before any thread starts (allocates): the map's figures as counters of
  // the run's registry, by path (map.*, map.local.*, map.reloc.*,
  // map.loop.*, map.global_ba.*; docs/threads.md "Counters"). Each is kept
  // up to date by the thread that owns the figure: the mapping thread after
  // each keyframe, the loop thread after each step. mirror_counters(): the
  // same for both, once the threads have stopped.
  void register_counters(rt::PerfRegistry& registry);
  void mirror_counters() noexcept;

 private:
  class MappingWorker final : public EstimatorWorker {
   public:
    explicit MappingWorker(MapSystem& m) : m_(m) {}
    Kind kind() const override { return Kind::kMapping; }
    bool step() override { return m_.mapping_step(); }
    const void* group() const override { return &m_; }
    bool busy() const override { return m_.busy(); }
    const rt::LatencyHistogram* latency() const override { return &m_.mapping_latency_; }

   private:
    MapSystem& m_;
  };
  class LoopWorker final : public EstimatorWorker {
   public:
    explicit LoopWorker(MapSystem& m) : m_(m) {}
    Kind kind() const override { return Kind::kLoop; }
    bool step() override { return m_.loop_step(); }
    const void* group() const override { return &m_; }
    bool step_ungrouped() override { return m_.global_ba_step(); }
    bool busy() const override { return m_.busy(); }
    const rt::LatencyHistogram* latency() const override { return &m_.loop_latency_; }

   private:
    MapSystem& m_;
  };

  static constexpr int kPackets = 6;
  static constexpr int kUpdates = 3;
  void publish_update(int kf, uint64_t seq);
  void publish_frame();
  // A keyframe of another chain than the map's (or any, on a loaded map not
  // found yet): try to find it; true when the map is localised afterwards.
  bool localise(const KeyframePacket& pk);

  MapSystemOptions opt_;
  std::unique_ptr<Map> map_;
  std::unique_ptr<LocalMapper> mapper_;
  std::unique_ptr<LoopCloser> closer_;
  std::unique_ptr<Relocaliser> reloc_;           // with a vocabulary and the loop on
  std::unique_ptr<GlobalBundleAdjustment> gba_;  // with the loop on and map.global_ba
  MapCamera cam_;
  // Packets: slot indices tracking -> mapping (todo), mapping -> tracking (free).
  std::unique_ptr<KeyframePacket[]> packets_;
  std::unique_ptr<KeyframeFeature[]> packet_features_;
  DepthGridSampler grid_sampler_;
  std::unique_ptr<uint16_t[]> packet_grids_;
  rt::SpscRing<uint8_t, 8> packet_todo_, packet_free_;
  int free_packets_[kPackets] = {};
  int n_free_packets_ = 0;
  uint64_t next_seq_ = 1;
  // Updates: mapping -> tracking (ready), tracking -> mapping (free).
  std::unique_ptr<MapUpdate[]> updates_;
  std::unique_ptr<MapPointUpdate[]> update_points_;
  rt::SpscRing<uint8_t, 8> update_ready_, update_free_;
  // Mapping -> loop: keyframe slots to look at.
  rt::SpscRing<int32_t, 64> loop_todo_;
  std::atomic<int> in_flight_{0};
  rt::Mailbox<MapFrameState> frame_;
  // Mapping/loop side.
  MapFrameState state_;
  bool realigned_ = false;
  int32_t last_kf_ = -1;
  uint32_t chain_ = 0;           // the odometry chain the map is localised in
  bool loaded_unfound_ = false;  // a loaded map this flight has not found yet
  int64_t lost_since_ns_ = -1;
  rt::LatencyHistogram mapping_latency_, loop_latency_, gba_latency_;
  MapSystemCounters counters_;
  std::atomic<uint64_t> overrun_{0}, applied_{0};
  // register_counters(): each registered counter and the figure it mirrors
  // (a plain field its thread writes, or one of the atomics above).
  struct Mirror {
    rt::PerfCounter* counter = nullptr;
    const uint64_t* figure = nullptr;
    const std::atomic<uint64_t>* shared = nullptr;
  };
  std::vector<Mirror> mapping_mirror_, loop_mirror_;
  rt::PerfCounter* mapping_elapsed_ = nullptr;  // map.mapping_step
  rt::PerfCounter* loop_elapsed_ = nullptr;     // map.loop_step
  rt::PerfCounter* gba_elapsed_ = nullptr;      // map.global_ba.solve
  static void mirror(const std::vector<Mirror>& mirrors) noexcept;
  Eigen::Isometry3d T_CB_ = Eigen::Isometry3d::Identity();
  MappingWorker mapping_worker_{*this};
  LoopWorker loop_worker_{*this};
};

}  // namespace kestrel::core

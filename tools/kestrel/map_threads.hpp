// The map's two threads, shared by `kestrel replay` and `kestrel run`:
// kst-mapping steps the estimator's kMapping worker (local mapping), kst-loop
// its kLoop worker (place recognition, loop closing, relocalisation, then the
// global bundle adjustment's solve outside the lock). They share the map (one
// worker group), so one mutex serialises them; no real-time thread
// touches that mutex (the tracking side reaches the map only through the
// lock-free hand-off of core/mapping). docs/map.md, docs/threads.md.
#pragma once

#include <atomic>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

#include "kestrel/core/estimator.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/rt/doorbell.hpp"

namespace kestrel::cli {

class MapThreads {
 public:
  // Starts a thread for each of the estimator's map workers (none without a map), scheduled by
  // the table's kst-mapping and kst-loop rows; what was granted is appended to `applied`.
  MapThreads(core::Estimator& est, const drivers::ThreadTable& table, std::vector<AppliedThread>& applied);
  ~MapThreads();
  MapThreads(const MapThreads&) = delete;
  MapThreads& operator=(const MapThreads&) = delete;

  // The tracking side calls this after handing a frame over: both threads
  // sleep on a doorbell until then. Lock-free and allocation-free.
  void wake() noexcept {
    bells_[0].ring();
    bells_[1].ring();
  }
  // Returns once the map has taken all that was handed over (the
  // deterministic paces call it per frame, from one thread).
  void wait_idle();
  // Lets the work handed over finish, then joins. Idempotent.
  void stop();
  bool running() const { return started_; }
  // Called on kst-loop, under the map's mutex, whenever a loop step moved the
  // map's keyframes (a loop closed, a global bundle adjustment applied), with
  // the keyframes as they are now. A relocalisation (on kst-mapping) moves the
  // whole map against the odometry: T_map_odom says all of that. Not real
  // time: it may allocate. Set or cleared at any time (under the same mutex).
  void set_on_map_moved(std::function<void(const std::vector<core::MapKeyframePose>&)> fn);
  // CPU seconds of each thread (after stop()).
  double mapping_cpu_s() const { return cpu_s_[0]; }
  double loop_cpu_s() const { return cpu_s_[1]; }

 private:
  bool busy() const;

  core::Estimator& est_;
  core::EstimatorWorker* workers_[2] = {nullptr, nullptr};  // kMapping, kLoop
  bool started_ = false;
  std::atomic<bool> stop_{false};
  std::mutex mutex_;
  std::function<void(const std::vector<core::MapKeyframePose>&)> on_map_moved_;  // under mutex_
  std::thread threads_[2];
  rt::Doorbell bells_[2];
  rt::Doorbell idle_bell_;
  double cpu_s_[2] = {0, 0};
};

}  // namespace kestrel::cli

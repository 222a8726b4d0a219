#include "kestrel/map_threads.hpp"

#include <time.h>

#include <utility>

#include "kestrel/core/map_system.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/thread_setup.hpp"

namespace kestrel::cli {

MapThreads::MapThreads(core::Estimator& est, const drivers::ThreadTable& table,
                       std::vector<AppliedThread>& applied)
    : est_(est) {
  const core::EstimatorWorkers workers = est.workers();
  workers_[0] = workers.find(core::EstimatorWorker::Kind::kMapping);
  workers_[1] = workers.find(core::EstimatorWorker::Kind::kLoop);
  if (workers_[0] == nullptr && workers_[1] == nullptr) return;
  started_ = true;
  const drivers::PipelineThread which[2] = {drivers::PipelineThread::kMapping,
                                            drivers::PipelineThread::kLoop};
  for (int t = 0; t < 2; ++t) {
    if (workers_[t] == nullptr) continue;
    rt::ThreadSetupReport sched;
    threads_[t] = rt::start_thread(
        table[which[t]],
        [this, t] {
          core::EstimatorWorker& w = *workers_[t];
          for (;;) {
            bool worked;
            {
              // One mutex for the workers' group (the map they share).
              std::unique_lock<std::mutex> lock(mutex_, std::defer_lock);
              if (w.group() != nullptr) lock.lock();
              const core::MapSystem* ms = est_.map_system();
              const uint32_t before = ms != nullptr ? ms->frame().alignment : 0;
              worked = w.step();
              if (t == 1 && on_map_moved_ && ms != nullptr && ms->frame().alignment != before)
                on_map_moved_(ms->keyframe_poses());
            }
            if (w.step_ungrouped()) worked = true;
            if (worked) {
              // A mapped keyframe is new work for the loop thread.
              if (t == 0) bells_[1].ring();
              idle_bell_.ring();
            } else {
              if (stop_.load(std::memory_order_acquire)) break;
              bells_[t].wait_for_ns(kIdleWaitNs);
            }
          }
          timespec ts{};
          clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
          cpu_s_[t] = static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
        },
        &sched);
    applied.push_back(applied_thread(table[which[t]], sched));
  }
}

MapThreads::~MapThreads() { stop(); }

void MapThreads::set_on_map_moved(std::function<void(const std::vector<core::MapKeyframePose>&)> fn) {
  const std::lock_guard<std::mutex> lock(mutex_);
  on_map_moved_ = std::move(fn);
}

bool MapThreads::busy() const {
  for (const core::EstimatorWorker* w : workers_)
    if (w != nullptr && w->busy()) return true;
  return false;
}

void MapThreads::wait_idle() {
  while (busy()) idle_bell_.wait_for_ns(kIdleWaitNs);
}

void MapThreads::stop() {
  if (!started_) return;
  wake();
  wait_idle();
  stop_.store(true, std::memory_order_release);
  wake();
  for (std::thread& t : threads_)
    if (t.joinable()) t.join();
  started_ = false;
}

}  // namespace kestrel::cli

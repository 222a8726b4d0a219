#include "kestrel/map_threads.hpp"

#include <time.h>

#include <utility>

#include "kestrel/core/map_system.hpp"
#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/thread_setup.hpp"

namespace kestrel::cli {
namespace {
// The bound on a sleep nobody rang for (stop, or work that appeared without a
// wake()): a few wake-ups a second, where the 200 us sleep loop took 5 000.
constexpr int64_t kIdleWaitNs = 50'000'000;
}  // namespace

MapThreads::MapThreads(core::Estimator& est, const drivers::ThreadTable& table,
                       std::vector<AppliedThread>& applied)
    : est_(est) {
  if (!est.has_map()) return;
  started_ = true;
  const drivers::PipelineThread which[2] = {drivers::PipelineThread::kMapping,
                                            drivers::PipelineThread::kLoop};
  for (int t = 0; t < 2; ++t) {
    rt::ThreadSetupReport sched;
    threads_[t] = rt::start_thread(
        table[which[t]],
        [this, t] {
          for (;;) {
            bool worked;
            {
              std::lock_guard<std::mutex> lock(mutex_);
              if (t == 0) {
                worked = est_.mapping_step();
              } else {
                const core::MapSystem* ms = est_.map_system();
                const uint32_t before = ms != nullptr ? ms->frame().alignment : 0;
                worked = est_.loop_step();
                if (on_map_moved_ && ms != nullptr && ms->frame().alignment != before)
                  on_map_moved_(est_.map_keyframe_poses());
              }
            }
            // The global bundle adjustment solves its copy of the map outside
            // the lock, so the mapping thread goes on meanwhile.
            if (t == 1 && est_.map_system() != nullptr && est_.map_system()->global_ba_step()) worked = true;
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

void MapThreads::wait_idle() {
  while (est_.map_busy()) idle_bell_.wait_for_ns(kIdleWaitNs);
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

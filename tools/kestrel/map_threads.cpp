#include "kestrel/map_threads.hpp"

#include <time.h>

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
              worked = t == 0 ? est_.mapping_step() : est_.loop_step();
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

#include "kestrel/map_threads.hpp"

#include <time.h>

#include "kestrel/rt/clock.hpp"
#include "kestrel/rt/thread_setup.hpp"

namespace kestrel::cli {

MapThreads::MapThreads(core::Estimator& est, const drivers::ThreadTable& table, std::vector<AppliedThread>& applied)
    : est_(est) {
  if (!est.has_map()) return;
  started_ = true;
  const drivers::PipelineThread which[2] = {drivers::PipelineThread::kMapping, drivers::PipelineThread::kLoop};
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
            if (!worked) {
              if (stop_.load(std::memory_order_acquire)) break;
              rt::sleep_for_ns(200'000);
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

void MapThreads::stop() {
  if (!started_) return;
  while (est_.map_busy()) rt::sleep_for_ns(1'000'000);
  stop_.store(true, std::memory_order_release);
  for (std::thread& t : threads_)
    if (t.joinable()) t.join();
  started_ = false;
}

}  // namespace kestrel::cli

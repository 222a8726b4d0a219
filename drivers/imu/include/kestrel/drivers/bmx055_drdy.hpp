// BMX055 data-ready / FIFO-watermark line through the Linux GPIO character
// device (gpiochip, uAPI v2). The kernel stamps each edge on CLOCK_MONOTONIC
// in its interrupt handler, which is the best time the host can get for "the
// FIFO reached its watermark" (docs/drivers/bmx055.md, "Timestamps").
#pragma once

#include <cstdint>
#include <string>

namespace kestrel::drivers::bmx055 {

class GpioDataReadyLine {
 public:
  GpioDataReadyLine() = default;
  ~GpioDataReadyLine();
  GpioDataReadyLine(const GpioDataReadyLine&) = delete;
  GpioDataReadyLine& operator=(const GpioDataReadyLine&) = delete;

  // "" on success, else a message naming the chip and line.
  std::string open(const std::string& chip_path, unsigned line_offset, bool rising_edge = true);
  void close();
  bool is_open() const { return fd_ >= 0; }

  // Waits until an edge or until `deadline_ns` (CLOCK_MONOTONIC). Returns 1
  // with the newest edge's kernel time in edge_t_ns (older queued edges are
  // consumed and counted as coalesced), 0 on timeout, -1 on error.
  int wait(int64_t deadline_ns, int64_t& edge_t_ns);
  uint64_t coalesced_edges() const { return coalesced_; }

 private:
  int fd_ = -1;
  uint64_t coalesced_ = 0;
};

bool gpio_cdev_built();

}  // namespace kestrel::drivers::bmx055

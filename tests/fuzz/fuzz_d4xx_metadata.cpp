// A RealSense D4xx metadata buffer as the uvcvideo metadata node hands it over
// (drivers/camera d4xx_metadata): records of host time, USB frame number and
// the UVC payload header with Intel's blocks. Any bytes: the parser never
// reads past them (libFuzzer's input is an exact-size allocation, ASan
// watches), and what it accepts re-encodes to a record that parses to the
// same times, counter and size.
// Seeds: records as the fake D4xx nodes of the driver tests build them, with
// and without each optional part, and two records in one buffer.
#include <cstring>
#include <vector>

#include "fuzz_target.hpp"
#include "kestrel/drivers/d4xx_metadata.hpp"

namespace d4 = kestrel::drivers::d4xx;

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  d4::FrameMetadata m;
  const d4::ParseStatus s = d4::parse_metadata_buffer(data, size, m);
  (void)d4::parse_status_name(s);
  if (s != d4::ParseStatus::kOk) return 0;
  if (m.records < 1 || m.blocks < 1 || m.header_length < 2) std::abort();
  d4::EncodeOptions o;
  o.pts = m.has_pts;
  o.scr = m.has_scr;
  o.capture_timing = m.timing.present;
  o.configuration = m.configuration.present;
  o.control = m.control.present;
  o.depth_control = !m.control.rgb;
  if (!o.capture_timing && !o.configuration && !o.control)
    return 0;  // only blocks the encoder does not write
  // The encoder writes RGB exposure in 100 us units: compare what survives that.
  if (m.control.present && m.control.rgb) m.control.exposure_us -= m.control.exposure_us % 100;
  std::vector<uint8_t> again(512);
  const size_t n = d4::encode_record(m, o, again.data(), again.size());
  if (n == 0) std::abort();
  again.resize(n);
  d4::FrameMetadata back;
  if (d4::parse_metadata_buffer(again.data(), again.size(), back) != d4::ParseStatus::kOk) std::abort();
  if (back.host_ns != m.host_ns || back.pts_us != m.pts_us || back.has_pts != m.has_pts ||
      back.timing.sensor_timestamp_us != m.timing.sensor_timestamp_us ||
      back.timing.frame_counter != m.timing.frame_counter ||
      back.configuration.width != m.configuration.width)
    std::abort();
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  d4::FrameMetadata m;
  m.host_ns = 1'234'567'890'123;
  m.usb_sof = 321;
  m.pts_us = 4'000'000'000u;
  m.scr_stc = 3'999'999'000u;
  m.timing.flags = d4::kTimingFrameCounterValid | d4::kTimingSensorTimestampValid | d4::kTimingExposureValid;
  m.timing.frame_counter = 42;
  m.timing.sensor_timestamp_us = 3'999'980'000u;
  m.timing.exposure_time_us = 8'000;
  m.configuration.width = 640;
  m.configuration.height = 480;
  m.configuration.fps = 30;
  m.control.flags = d4::kRgbControlManualExposureValid | d4::kDepthControlExposureValid;
  m.control.exposure_us = 8'000;
  size_t count = 0;
  std::vector<uint8_t> all;
  const d4::EncodeOptions variants[] = {{},
                                        {true, true, true, true, true, true},
                                        {true, false, true, false, false, false},
                                        {false, true, true, true, false, true}};
  for (const d4::EncodeOptions& o : variants) {
    std::vector<uint8_t> b(512);
    b.resize(d4::encode_record(m, o, b.data(), b.size()));
    write_file(dir + "/record" + std::to_string(count++) + ".bin", b.data(), b.size());
    all.insert(all.end(), b.begin(), b.end());
  }
  write_file(dir + "/records.bin", all.data(), all.size());
  return count + 1;
}

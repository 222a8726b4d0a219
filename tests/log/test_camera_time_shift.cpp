// The rig's camera-IMU offset applied by the readers: every camera stamp
// moves by time_offset_cam_imu_ns (t_imu = t_cam + offset, docs/frames.md) and
// the records still come out in time order, depth right behind its colour
// image; the same for the klog reader (re-sorted while streaming) and a
// folder reader (its tables shifted before the merge).
#include <gtest/gtest.h>

#include <fstream>
#include <vector>

#include "kestrel/drivers/camera_time_shift.hpp"
#include "kestrel/drivers/folder_logs.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/log_export.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "log_fixtures.hpp"
#include "test_data.hpp"

namespace kestrel::test {
namespace {

using drivers::LogRecord;
using drivers::RecordType;

// 1 s of a 400 Hz IMU, 30 Hz colour + depth (stamped on the camera's clock)
// and 100 Hz ground truth, written in time order as a recorder would.
std::string write_log(const std::string& dir, int64_t offset_ns) {
  const std::string path = dir + "/offset.klog";
  Rig rig = fixture_rig();
  rig.time_offset_cam_imu_ns = offset_ns;
  drivers::KlogWriter w;
  w.open(path, rig);
  uint32_t frame = 0;
  for (uint32_t i = 0; i < 400; ++i) {
    const ImuSample s = fixture_imu(i);
    w.write_imu(s);
    if (i % 4 == 0) {
      GroundTruthPose g = fixture_gt(i, false);
      g.t_ns = s.t_ns;
      w.write_ground_truth(g);
    }
    const int64_t next_frame_ns = 1'000'000'000 + int64_t{frame} * 33'333'333;
    if (s.t_ns >= next_frame_ns) {
      drivers::LogImage rgb = fixture_image(frame, PixelFormat::kRgb8);
      drivers::LogImage depth = fixture_image(frame, PixelFormat::kDepthU16);
      depth.t_ns = rgb.t_ns;
      w.write_image(RecordType::kRgb, rgb);
      w.write_image(RecordType::kDepth, depth);
      ++frame;
    }
  }
  w.close();
  return path;
}

void expect_shifted_and_ordered(const std::vector<LogRecord>& got, const std::vector<LogRecord>& stored,
                                int64_t offset_ns) {
  ASSERT_EQ(got.size(), stored.size());
  // Same records, camera stamps moved by the offset, nothing else touched.
  std::vector<int64_t> cam_stored, cam_got;
  size_t imu_stored = 0, imu_got = 0;
  for (const auto& r : stored) {
    if (r.type == RecordType::kRgb) cam_stored.push_back(r.image.t_ns);
    imu_stored += r.type == RecordType::kImu;
  }
  for (size_t i = 0; i < got.size(); ++i) {
    const LogRecord& r = got[i];
    if (r.type == RecordType::kRgb) {
      cam_got.push_back(r.image.t_ns);
      ASSERT_LT(i + 1, got.size());
      EXPECT_EQ(got[i + 1].type, RecordType::kDepth) << "depth follows its colour image";
      EXPECT_EQ(got[i + 1].image.t_ns, r.image.t_ns);
      EXPECT_EQ(got[i + 1].image.seq, r.image.seq);
    }
    imu_got += r.type == RecordType::kImu;
    if (i > 0) {
      EXPECT_LE(drivers::record_time_ns(got[i - 1]), drivers::record_time_ns(r))
          << "record " << i << " out of time order";
    }
  }
  EXPECT_EQ(imu_got, imu_stored);
  ASSERT_EQ(cam_got.size(), cam_stored.size());
  for (size_t k = 0; k < cam_got.size(); ++k) EXPECT_EQ(cam_got[k], cam_stored[k] + offset_ns);
}

TEST(CameraTimeShift, KlogReaderShiftsAndReordersBothSigns) {
  const std::string dir = temp_dir("camera_time_shift");
  // Zero: stored order and stamps, untouched; the reference for the others.
  const std::vector<LogRecord> stored = [&] {
    drivers::KlogReader r(write_log(dir, 0));
    return all_records(r);
  }();
  for (const int64_t offset_ns : {int64_t{30'000'000}, int64_t{-30'000'000}, int64_t{2'345'678}}) {
    SCOPED_TRACE("offset " + std::to_string(offset_ns) + " ns");
    drivers::KlogReader r(write_log(dir, offset_ns));
    EXPECT_EQ(r.rig().time_offset_cam_imu_ns, offset_ns);  // what was applied
    const std::vector<LogRecord> got = all_records(r);
    expect_shifted_and_ordered(got, stored, offset_ns);
    // Rewind replays the same sequence.
    r.rewind();
    const std::vector<LogRecord> again = all_records(r);
    ASSERT_EQ(again.size(), got.size());
    for (size_t i = 0; i < got.size(); ++i) {
      EXPECT_EQ(again[i].type, got[i].type);
      EXPECT_EQ(drivers::record_time_ns(again[i]), drivers::record_time_ns(got[i]));
    }
  }
}

TEST(CameraTimeShift, HoldsBackOnlyAboutTheOffset) {
  // A camera 10 ms ahead of the IMU (negative offset): an image may still
  // come that belongs 10 ms before the newest sample, so exactly the last
  // 10 ms of samples are held, no more.
  drivers::CameraTimeShift shift(-10'000'000);
  LogRecord r;
  for (int i = 0; i < 100; ++i) {
    LogRecord imu;
    imu.type = RecordType::kImu;
    imu.imu.t_ns = i * 1'000'000;
    shift.push(std::move(imu));
    while (shift.pop(r, false)) {
    }
    if (i >= 10) {
      EXPECT_EQ(shift.held(), 11u) << "at " << i << " ms";
    }
  }
  size_t rest = 0;
  while (shift.pop(r, true)) ++rest;
  EXPECT_EQ(rest, 11u);
  EXPECT_EQ(r.imu.t_ns, 99'000'000);
}

TEST(CameraTimeShift, FolderReaderShiftsItsTables) {
  const std::string dir = temp_dir("camera_time_shift_folder");
  // A log with no offset, exported to EuRoC; then the folder's rig claims one.
  drivers::KlogReader zero(write_log(dir, 0));
  drivers::export_euroc(zero, dir + "/euroc");
  const std::vector<LogRecord> stored = [&] {
    drivers::EurocReader r(dir + "/euroc");
    return all_records(r);
  }();
  Rig rig = drivers::load_rig_file(dir + "/euroc/mav0/kestrel_rig.yaml");
  EXPECT_EQ(rig.time_offset_cam_imu_ns, 0);
  rig.time_offset_cam_imu_ns = -25'000'000;
  std::ofstream(dir + "/euroc/mav0/kestrel_rig.yaml") << drivers::rig_to_yaml(rig);
  drivers::EurocReader shifted(dir + "/euroc");
  expect_shifted_and_ordered(all_records(shifted), stored, -25'000'000);
}

}  // namespace
}  // namespace kestrel::test

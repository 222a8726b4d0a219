// Any byte string as an MCAP file: the container reader (from memory) with
// every CDR decoder on every message, and Rosbag2Reader (topics by type, rig
// from CameraInfo / tf_static, colour-depth pairing, image conversion) on the
// same bytes as a file; bytes with SQLite's header go through the sqlite3
// storage (libsqlite3 on a damaged database, then our reading of its rows).
// Never a crash, a leak or an allocation beyond the reader's bounds. Seeds:
// rosbag2 exports of the log fixture (zstd, lz4, unchunked), a cut of one, and
// the same bag as a .db3 and a cut of that, so the fuzzer starts past magic
// and CRCs.
#include <unistd.h>

#include "db3_fixture.hpp"
#include "fuzz_target.hpp"
#include "kestrel/drivers/klog.hpp"
#include "kestrel/drivers/mcap.hpp"
#include "kestrel/drivers/ros2_msgs.hpp"
#include "kestrel/drivers/rosbag2.hpp"
#include "log_fixtures.hpp"

namespace {
namespace ros2 = kestrel::drivers::ros2;
namespace mcap = kestrel::drivers::mcap;

void decode_all(const uint8_t* p, size_t n) {
  try {
    ros2::Imu m;
    ros2::decode(p, n, m);
  } catch (const std::runtime_error&) {
  }
  try {
    ros2::Image m;
    ros2::decode(p, n, m);
  } catch (const std::runtime_error&) {
  }
  try {
    ros2::CompressedImage m;
    ros2::decode(p, n, m);
  } catch (const std::runtime_error&) {
  }
  try {
    ros2::CameraInfo m;
    ros2::decode(p, n, m);
  } catch (const std::runtime_error&) {
  }
  try {
    ros2::Odometry m;
    ros2::decode(p, n, m);
  } catch (const std::runtime_error&) {
  }
  try {
    ros2::PoseStamped m;
    ros2::decode(p, n, m);
  } catch (const std::runtime_error&) {
  }
  try {
    std::vector<ros2::TransformStamped> m;
    ros2::decode(p, n, m);
  } catch (const std::runtime_error&) {
  }
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  mcap::ReaderOptions o;
  o.max_chunk_bytes = 64u << 20;  // the fuzzer's memory limit, not the reader's default
  o.max_record_bytes = 64u << 20;
  decode_all(data, size);
  try {
    mcap::Reader r(data, size, o);
    std::vector<mcap::MessageRef> refs;
    r.scan([&](const mcap::MessageRef& m, const uint8_t* p, size_t n) {
      refs.push_back(m);
      decode_all(p, n);
    });
    std::vector<uint8_t> scratch;
    for (const auto& m : refs) {
      const uint8_t* p = nullptr;
      if (r.load(m, scratch, p)) decode_all(p, m.size);
    }
  } catch (const std::runtime_error&) {
  }
  static const std::string path = "/tmp/kestrel_fuzz_rosbag2_" + std::to_string(getpid()) + ".mcap";
  kestrel::fuzz::write_file(path, data, size);
  try {
    kestrel::drivers::Rosbag2ReadOptions ro;
    ro.mcap = o;
    kestrel::drivers::Rosbag2Reader rd(path, ro);
    kestrel::drivers::LogRecord rec;
    size_t n = 0;
    while (rd.next(rec)) {
      if ((rec.type == kestrel::drivers::RecordType::kRgb ||
           rec.type == kestrel::drivers::RecordType::kDepth) &&
          rec.image.pixels.size() != static_cast<size_t>(rec.image.width) * rec.image.height *
                                         kestrel::bytes_per_pixel(rec.image.format))
        std::abort();  // an image's size must agree with its pixels
      ++n;
    }
  } catch (const std::runtime_error&) {
  }
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  const std::string klog = dir + "/fixture.klog.tmp";
  kestrel::test::write_small_klog(klog, nullptr);
  size_t n = 0;
  for (const auto& [comp, chunk] :
       std::vector<std::pair<std::string, size_t>>{{"zstd", 2048}, {"lz4", 2048}, {"", 0}}) {
    kestrel::drivers::KlogReader src(klog);
    kestrel::drivers::Rosbag2WriteOptions w;
    w.mcap.compression = comp;
    w.mcap.chunk_size_bytes = chunk;
    const std::string bag = dir + "/bag_tmp";
    kestrel::drivers::export_rosbag2(src, bag, w);
    const auto bytes = kestrel::test::read_bytes(bag + "/bag_tmp_0.mcap");
    const std::string name = comp.empty() ? "unchunked" : comp;
    kestrel::test::write_bytes(dir + "/" + name + ".mcap", bytes.data(), bytes.size());
    if (comp.empty()) {
      kestrel::test::write_bytes(dir + "/cut.mcap", bytes.data(), bytes.size() / 2), ++n;
      kestrel::test::write_db3_from_mcap(bag + "/bag_tmp_0.mcap", bag, "seed.db3");
      const auto db = kestrel::test::read_bytes(bag + "/seed.db3");
      kestrel::test::write_bytes(dir + "/sqlite.db3", db.data(), db.size());
      kestrel::test::write_bytes(dir + "/cut.db3", db.data(), db.size() * 6 / 10);
      n += 2;
    }
    std::filesystem::remove_all(bag);
    ++n;
  }
  std::filesystem::remove(klog);
  return n;
}

// The flight-controller link beyond ODOMETRY: HEARTBEAT and TIMESYNC against
// the specification (CRC_EXTRA from the field lists) and node-mavlink, the
// decoder for what the autopilot sends (resynchronisation, mutations: the
// fuzz entry), the clock offset from TIMESYNC, the serial port (a pty pair),
// UDP with a fake autopilot answering TIMESYNC, and the command line's
// contract: --mavlink-udp and --mavlink-serial both send HEARTBEAT (id 0)
// and ODOMETRY (id 331).
#include <arpa/inet.h>
#include <fcntl.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <fstream>
#include <map>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "kestrel/drivers/mavlink/mavlink_decoder.hpp"
#include "kestrel/drivers/mavlink/mavlink_v2.hpp"
#include "kestrel/drivers/mavlink/serial_link.hpp"
#include "kestrel/drivers/mavlink/time_sync.hpp"
#include "kestrel/mavlink/odometry_stream.hpp"
#include "mavlink_fuzz_entry.hpp"
#include "run_command.hpp"
#include "test_data.hpp"

namespace km = kestrel::mavlink;

namespace {

struct Field {
  const char* type;
  const char* name;
  int size;
  int array;
};

// CRC_EXTRA as the generator computes it: message name, then each base field's
// type and name (wire order: sorted by type size, stable), array lengths.
uint8_t crc_extra_of(const char* message, std::vector<Field> base) {
  std::stable_sort(base.begin(), base.end(), [](const Field& a, const Field& b) { return a.size > b.size; });
  uint16_t crc = 0xFFFF;
  auto add = [&](const std::string& s) {
    crc = km::crc_x25(reinterpret_cast<const uint8_t*>(s.data()), s.size(), crc);
  };
  add(std::string(message) + " ");
  for (const Field& f : base) {
    add(std::string(f.type) + " ");
    add(std::string(f.name) + " ");
    if (f.array > 0) crc = km::crc_x25_accumulate(static_cast<uint8_t>(f.array), crc);
  }
  return static_cast<uint8_t>((crc & 0xFF) ^ (crc >> 8));
}

std::vector<km::MavlinkFrame> decode_all(const std::vector<uint8_t>& bytes, km::MavlinkDecoder& d) {
  std::vector<km::MavlinkFrame> out;
  d.feed(bytes.data(), bytes.size(), [&](const km::MavlinkFrame& f) { out.push_back(f); });
  return out;
}

void append(std::vector<uint8_t>& v, const uint8_t* p, size_t n) { v.insert(v.end(), p, p + n); }

// A pty pair: the test holds the master (the autopilot's side), the link opens the slave.
struct Pty {
  int master = -1;
  std::string slave;
  Pty() {
    master = posix_openpt(O_RDWR | O_NOCTTY);
    if (master >= 0 && grantpt(master) == 0 && unlockpt(master) == 0) slave = ptsname(master);
    // Raw on the master side too, so no byte is translated.
    termios t{};
    if (master >= 0 && tcgetattr(master, &t) == 0) {
      cfmakeraw(&t);
      tcsetattr(master, TCSANOW, &t);
    }
  }
  ~Pty() {
    if (master >= 0) close(master);
  }
  // Whatever arrives within timeout_ms.
  std::vector<uint8_t> read_for(int timeout_ms) const {
    std::vector<uint8_t> v;
    const auto until = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    while (std::chrono::steady_clock::now() < until) {
      pollfd p{master, POLLIN, 0};
      if (poll(&p, 1, 20) <= 0) continue;
      uint8_t buf[4096];
      const ssize_t n = read(master, buf, sizeof buf);
      if (n > 0) v.insert(v.end(), buf, buf + n);
    }
    return v;
  }
};

int udp_socket_on_loopback(uint16_t* port) {
  const int fd = socket(AF_INET, SOCK_DGRAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (fd < 0 || bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) return -1;
  socklen_t len = sizeof a;
  getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len);
  *port = ntohs(a.sin_port);
  return fd;
}

}  // namespace

TEST(MavlinkCrc, HeartbeatAndTimesyncCrcExtraFromTheXml) {
  EXPECT_EQ(crc_extra_of("HEARTBEAT", {{"uint8_t", "type", 1, 0},
                                       {"uint8_t", "autopilot", 1, 0},
                                       {"uint8_t", "base_mode", 1, 0},
                                       {"uint32_t", "custom_mode", 4, 0},
                                       {"uint8_t", "system_status", 1, 0},
                                       {"uint8_t", "mavlink_version", 1, 0}}),
            km::kHeartbeatCrcExtra);
  // TIMESYNC's target_system / target_component are extensions: not in CRC_EXTRA.
  EXPECT_EQ(crc_extra_of("TIMESYNC", {{"int64_t", "tc1", 8, 0}, {"int64_t", "ts1", 8, 0}}),
            km::kTimesyncCrcExtra);
  EXPECT_EQ(km::kHeartbeatCrcExtra, 50);
  EXPECT_EQ(km::kTimesyncCrcExtra, 34);
}

TEST(MavlinkEncode, HeartbeatLayoutIsAnOnboardControllerWithTheVioComponent) {
  km::HeartbeatMsg h;
  h.system_status = km::kMavStateActive;
  uint8_t f[km::kMaxFrameBytes];
  const size_t n = km::encode_heartbeat(h, 9, 1, km::kMavCompIdVisualInertialOdometry, f);
  ASSERT_EQ(n, km::kHeaderV2Bytes + 9 + 2);
  EXPECT_EQ(f[1], 9);  // custom_mode 0 first, mavlink_version 3 last: nothing to trim
  EXPECT_EQ(f[6], 197);
  EXPECT_EQ(f[7] | f[8] << 8 | f[9] << 16, 0);
  EXPECT_EQ(f[10 + 4], 18);  // MAV_TYPE_ONBOARD_CONTROLLER
  EXPECT_EQ(f[10 + 5], 8);   // MAV_AUTOPILOT_INVALID
  EXPECT_EQ(f[10 + 7], 4);   // MAV_STATE_ACTIVE
  EXPECT_EQ(f[10 + 8], 3);   // mavlink_version
}

TEST(MavlinkDecoder, FindsEveryFrameThroughNoiseDamageAndSplits) {
  std::vector<uint8_t> s;
  uint8_t f[km::kMaxFrameBytes];
  const uint8_t junk[] = {0x00, 0xFD, 0x03, 0x42};  // a stray start byte, too
  append(s, junk, sizeof junk);
  km::TimesyncMsg t;
  t.tc1 = 0;
  t.ts1 = 123456789012345;
  append(s, f, km::encode_timesync(t, 1, 1, 1, f));
  // A damaged frame (one payload bit): dropped, the next one found.
  km::HeartbeatMsg h;
  size_t n = km::encode_heartbeat(h, 2, 1, 1, f);
  f[12] ^= 0x10;
  append(s, f, n);
  append(s, f, km::encode_heartbeat(h, 3, 1, 1, f));
  // A message we have no CRC_EXTRA for (SYS_STATUS, #1): scanned past.
  const uint8_t payload[31] = {1, 2, 3};
  append(s, f, km::frame_v2(1, 124, payload, sizeof payload, 4, 1, 1, f));
  km::OdometryMsg o;
  o.x = 1.5f;
  append(s, f, km::encode_odometry(o, 5, 1, 1, f));
  // The answer, tc1 != 0: trimmed to 14 bytes (zero targets and ts1's two
  // high bytes), zero-extended again.
  t.tc1 = 987654321;
  append(s, f, km::encode_timesync(t, 6, 1, 1, f));

  for (size_t step : {s.size(), size_t{1}, size_t{7}}) {
    SCOPED_TRACE("fed " + std::to_string(step) + " bytes at a time");
    km::MavlinkDecoder d;
    std::vector<km::MavlinkFrame> got;
    for (size_t i = 0; i < s.size(); i += step)
      d.feed(s.data() + i, std::min(step, s.size() - i),
             [&](const km::MavlinkFrame& fr) { got.push_back(fr); });
    ASSERT_EQ(got.size(), 4u);
    EXPECT_EQ(got[0].msgid, km::kMsgIdTimesync);
    EXPECT_EQ(km::unpack_timesync(got[0].payload).ts1, 123456789012345);
    EXPECT_EQ(got[1].msgid, km::kMsgIdHeartbeat);
    EXPECT_EQ(got[1].seq, 3);
    EXPECT_EQ(km::unpack_heartbeat(got[1].payload).type, km::kMavTypeOnboardController);
    EXPECT_EQ(got[2].msgid, km::kMsgIdOdometry);
    EXPECT_EQ(got[3].payload_len, 14);
    EXPECT_EQ(km::unpack_timesync(got[3].payload).tc1, 987654321);
    EXPECT_EQ(km::unpack_timesync(got[3].payload).target_system, 0);
    EXPECT_EQ(d.stats().frames, 4u);
    EXPECT_EQ(d.stats().bad_crc, 1u);     // the damaged frame
    EXPECT_EQ(d.stats().bad_header, 1u);  // the stray start byte's false header (flags 0x42)
    EXPECT_EQ(d.stats().unknown_msgid, 1u);
  }
}

TEST(MavlinkDecoder, MutatedStreamsNeverCrashOrInventFrames) {
  // The fuzz target's entry on random mutations of a valid stream (the
  // libFuzzer target runs the same with coverage, -DKESTREL_BUILD_FUZZ=ON).
  std::vector<uint8_t> s;
  uint8_t f[km::kMaxFrameBytes];
  for (int i = 0; i < 20; ++i) {
    km::TimesyncMsg t;
    t.tc1 = i;
    t.ts1 = 1000 * i;
    append(s, f, km::encode_timesync(t, static_cast<uint8_t>(i), 1, 1, f));
    km::HeartbeatMsg h;
    append(s, f, km::encode_heartbeat(h, static_cast<uint8_t>(i), 1, 1, f));
  }
  EXPECT_EQ(kestrel::test::mavlink_fuzz_one(s.data(), s.size()), 40u);
  std::mt19937 rng(11);
  uint64_t total = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    std::vector<uint8_t> m = s;
    const int edits = 1 + static_cast<int>(rng() % 8);
    for (int e = 0; e < edits; ++e) {
      const size_t at = rng() % m.size();
      switch (rng() % 4) {
        case 0:
          m[at] ^= static_cast<uint8_t>(1u << (rng() % 8));
          break;
        case 1:
          m[at] = static_cast<uint8_t>(rng());
          break;
        case 2:
          m.erase(m.begin() + static_cast<long>(at));
          break;
        default:
          m.insert(m.begin() + static_cast<long>(at), static_cast<uint8_t>(rng()));
          break;
      }
    }
    total += kestrel::test::mavlink_fuzz_one(m.data(), m.size());
  }
  // Most frames survive a few edits: the decoder resynchronises.
  EXPECT_GT(total, 3000u * 30u);
  std::vector<uint8_t> noise(100000);
  for (auto& b : noise) b = static_cast<uint8_t>(rng());
  kestrel::test::mavlink_fuzz_one(noise.data(), noise.size());
}

TEST(MavlinkTimeSync, LearnsTheAutopilotClockAndAnswersInIt) {
  km::TimeSync ts;
  const int64_t offset = 123'456'789'000;  // autopilot minus ours
  int64_t now = 5'000'000'000;
  km::TimesyncMsg reply;
  // Before it knows: an autopilot's request is answered with our clock.
  km::TimesyncMsg req;
  req.ts1 = now + offset;
  ASSERT_TRUE(ts.on_message(req, 1, 1, 1, 197, now, &reply));
  EXPECT_EQ(reply.tc1, now);
  EXPECT_EQ(reply.ts1, req.ts1);
  EXPECT_EQ(reply.target_system, 1);
  EXPECT_EQ(reply.target_component, 1);
  // Exchanges with 1..3 ms one-way delays, symmetric on average.
  std::mt19937 rng(3);
  for (int i = 0; i < 20; ++i) {
    const km::TimesyncMsg q = ts.request(now);
    const int64_t d1 = 1'000'000 + static_cast<int64_t>(rng() % 1000);
    const int64_t d2 = 1'000'000 + static_cast<int64_t>(rng() % 1000);
    km::TimesyncMsg ans;
    ans.tc1 = now + d1 + offset;
    ans.ts1 = q.ts1;
    ans.target_system = 1;
    ans.target_component = 197;
    now += d1 + d2;
    EXPECT_FALSE(ts.on_message(ans, 1, 1, 1, 197, now, &reply));
    now += 100'000'000;
    if (i == 3) {
      EXPECT_FALSE(ts.converged());
    }
  }
  ASSERT_TRUE(ts.converged());
  EXPECT_NEAR(static_cast<double>(ts.offset_ns()), static_cast<double>(offset), 1'000.0);  // < 1 us
  EXPECT_EQ(ts.to_link_time_ns(now), now + ts.offset_ns());
  ASSERT_TRUE(ts.on_message(req, 1, 1, 1, 197, now, &reply));
  EXPECT_EQ(reply.tc1, now + ts.offset_ns()) << "answers in the autopilot's time base once converged";
  // Not an answer to ours, a round trip too long, or for another component: ignored.
  km::TimesyncMsg stray;
  stray.tc1 = 1;
  stray.ts1 = 42;
  EXPECT_FALSE(ts.on_message(stray, 1, 1, 1, 197, now, &reply));
  const km::TimesyncMsg slow = ts.request(now);
  stray.ts1 = slow.ts1;
  EXPECT_FALSE(ts.on_message(stray, 1, 1, 1, 197, now + 50'000'000, &reply));
  EXPECT_EQ(ts.stats().responses_rejected, 2u);
  req.target_component = 55;
  EXPECT_FALSE(ts.on_message(req, 1, 1, 1, 197, now, &reply));
  // The autopilot rebooted: its clock jumped; three answers in a row say so.
  for (int i = 0; i < 8; ++i) {
    const km::TimesyncMsg q = ts.request(now);
    km::TimesyncMsg ans;
    ans.tc1 = now + 1'000'000 + 7'000'000'000;
    ans.ts1 = q.ts1;
    now += 2'000'000;
    ts.on_message(ans, 1, 1, 1, 197, now, &reply);
  }
  EXPECT_EQ(ts.stats().resets, 1u);
  EXPECT_NEAR(static_cast<double>(ts.offset_ns()), 7e9, 1e3);
}

TEST(MavlinkSerial, PtyCarriesFramesBothWays) {
  Pty pty;
  ASSERT_FALSE(pty.slave.empty()) << "no pty available";
  km::OdometryStreamOptions so;
  so.serial_device = pty.slave;
  so.serial_baud = 921600;
  so.timesync_rate_hz = 0;  // only answer, no requests of ours in this test
  km::OdometryStream stream(so);
  EXPECT_EQ(stream.endpoint(), pty.slave + ":921600");
  stream.service(1'000'000'000);  // heartbeat due
  kestrel::core::PoseSample in;
  in.t_ns = 2'000'000'000;
  in.quality = kestrel::core::TrackingQuality::kTracking;
  in.set_p_WB(Eigen::Vector3d(1, 2, 3));
  ASSERT_TRUE(stream.publish(in));
  km::MavlinkDecoder d;
  std::vector<km::MavlinkFrame> got = decode_all(pty.read_for(300), d);
  ASSERT_EQ(got.size(), 2u);
  EXPECT_EQ(got[0].msgid, km::kMsgIdHeartbeat);
  EXPECT_EQ(got[1].msgid, km::kMsgIdOdometry);
  EXPECT_EQ(got[1].compid, 197);
  // The autopilot asks for our clock; the link answers on the next service().
  km::TimesyncMsg q;
  q.ts1 = 777'000'000'000;
  uint8_t f[km::kMaxFrameBytes];
  const size_t n = km::encode_timesync(q, 0, 1, 1, f);
  ASSERT_EQ(write(pty.master, f, n), static_cast<ssize_t>(n));
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  stream.service(1'100'000'000);
  got = decode_all(pty.read_for(300), d);
  ASSERT_EQ(got.size(), 1u);
  ASSERT_EQ(got[0].msgid, km::kMsgIdTimesync);
  const km::TimesyncMsg a = km::unpack_timesync(got[0].payload);
  EXPECT_EQ(a.tc1, 1'100'000'000);
  EXPECT_EQ(a.ts1, q.ts1);
  EXPECT_EQ(a.target_system, 1);
  EXPECT_EQ(a.target_component, 1);
  EXPECT_EQ(stream.time_sync().stats().requests_answered, 1u);
  // A baud termios has no code for is a clear error naming the choices.
  try {
    km::SerialLink bad(pty.slave, 123456);
    ADD_FAILURE() << "baud 123456 accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("921600"), std::string::npos) << e.what();
  }
  EXPECT_THROW(km::SerialLink("/nonexistent/ttyX", 921600), std::invalid_argument);
  std::string dev;
  int baud = 0;
  EXPECT_TRUE(km::parse_serial_spec("/dev/ttyS1:57600", 921600, dev, baud));
  EXPECT_EQ(dev, "/dev/ttyS1");
  EXPECT_EQ(baud, 57600);
  EXPECT_TRUE(km::parse_serial_spec("/dev/ttyS1", 921600, dev, baud));
  EXPECT_EQ(baud, 921600);
  EXPECT_FALSE(km::parse_serial_spec("/dev/ttyS1:fast", 921600, dev, baud));
}

TEST(MavlinkUdp, StampsOdometryInTheAutopilotClockOnceItAnswers) {
  // A fake autopilot on loopback whose clock is 42 s ahead of ours: it answers
  // our TIMESYNC requests; after a few, ODOMETRY carries its time.
  uint16_t port = 0;
  const int ap = udp_socket_on_loopback(&port);
  ASSERT_GE(ap, 0);
  km::OdometryStreamOptions so;
  so.endpoint = "127.0.0.1:" + std::to_string(port);
  so.odometry_rate_hz = 10;  // at most every 90 ms
  km::OdometryStream stream(so);
  const int64_t ap_ahead_ns = 42'000'000'000;
  km::MavlinkDecoder d;
  std::map<uint32_t, int> seen;
  int64_t now = 10'000'000'000;
  for (int step = 0; step < 40 && !stream.time_sync().converged(); ++step) {
    stream.service(now);
    // The autopilot reads what came and answers requests at once.
    uint8_t buf[2048];
    sockaddr_in from{};
    socklen_t fl = sizeof from;
    pollfd p{ap, POLLIN, 0};
    while (poll(&p, 1, 50) > 0) {
      const ssize_t n = recvfrom(ap, buf, sizeof buf, 0, reinterpret_cast<sockaddr*>(&from), &fl);
      if (n <= 0) break;
      d.feed(buf, static_cast<size_t>(n), [&](const km::MavlinkFrame& f) {
        ++seen[f.msgid];
        if (f.msgid != km::kMsgIdTimesync) return;
        const km::TimesyncMsg q = km::unpack_timesync(f.payload);
        if (q.tc1 != 0) return;
        km::TimesyncMsg a;
        a.tc1 = q.ts1 + 1'000'000 + ap_ahead_ns;  // 1 ms each way
        a.ts1 = q.ts1;
        a.target_system = f.sysid;
        a.target_component = f.compid;
        uint8_t out[km::kMaxFrameBytes];
        const size_t m = km::encode_timesync(a, 0, 1, 1, out);
        sendto(ap, out, m, 0, reinterpret_cast<sockaddr*>(&from), fl);
      });
    }
    now += 2'000'000;  // the answer arrives 2 ms after the request, in our clock
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
    stream.service(now);
    now += 100'000'000;
  }
  ASSERT_TRUE(stream.time_sync().converged());
  EXPECT_NEAR(static_cast<double>(stream.time_sync().offset_ns()), static_cast<double>(ap_ahead_ns), 1e3);
  // 3 s more of our clock: a heartbeat a second.
  for (int step = 0; step < 30; ++step) {
    stream.service(now);
    now += 100'000'000;
  }
  {
    uint8_t buf[2048];
    pollfd p{ap, POLLIN, 0};
    while (poll(&p, 1, 100) > 0) {
      const ssize_t n = recv(ap, buf, sizeof buf, 0);
      if (n <= 0) break;
      d.feed(buf, static_cast<size_t>(n), [&](const km::MavlinkFrame& f) { ++seen[f.msgid]; });
    }
  }
  EXPECT_GE(seen[km::kMsgIdHeartbeat], 3) << "1 Hz over > 3 s of our clock";
  EXPECT_LE(seen[km::kMsgIdHeartbeat], 5);
  kestrel::core::PoseSample in;
  in.quality = kestrel::core::TrackingQuality::kTracking;
  in.t_ns = now;
  ASSERT_TRUE(stream.publish(in));
  in.t_ns = now + 50'000'000;
  EXPECT_FALSE(stream.publish(in)) << "sooner than the configured 10 Hz";
  EXPECT_EQ(stream.stream_stats().rate_skipped, 1u);
  uint8_t buf[2048];
  pollfd p{ap, POLLIN, 0};
  bool found = false;
  while (!found && poll(&p, 1, 500) > 0) {
    const ssize_t n = recv(ap, buf, sizeof buf, 0);
    d.feed(buf, static_cast<size_t>(n), [&](const km::MavlinkFrame& f) {
      if (f.msgid != km::kMsgIdOdometry) return;
      uint64_t t = 0;
      for (int i = 0; i < 8; ++i) t |= static_cast<uint64_t>(f.payload[i]) << (8 * i);
      EXPECT_NEAR(static_cast<double>(t), (now + ap_ahead_ns) / 1e3, 2.0);
      found = true;
    });
  }
  EXPECT_TRUE(found);
  close(ap);
}

TEST(MavlinkEncode, HeartbeatAndTimesyncDecodedByNodeMavlink) {
  const std::string cache = std::string(KESTREL_BUILD_DIR) + "/npm-cache";
  const kestrel::test::CmdResult install = kestrel::test::run_command(
      "sh " + std::string(KESTREL_SOURCE_DIR) + "/tests/mavlink/install_node_mavlink.sh " + cache);
  if (install.code != 0)
    GTEST_SKIP() << "node-mavlink unavailable, independent decode NOT checked: " << install.out;
  const std::string bin = kestrel::test::temp_dir("mavlink_node_link") + "/frames.bin";
  {
    std::ofstream f(bin, std::ios::binary);
    uint8_t b[km::kMaxFrameBytes];
    km::HeartbeatMsg h;
    h.system_status = km::kMavStateActive;
    f.write(reinterpret_cast<const char*>(b),
            static_cast<std::streamsize>(km::encode_heartbeat(h, 7, 1, 197, b)));
    km::TimesyncMsg t;
    t.tc1 = -5;  // signed on the wire
    t.ts1 = 1'234'567'890'123'456'789;
    t.target_system = 3;
    t.target_component = 1;
    f.write(reinterpret_cast<const char*>(b),
            static_cast<std::streamsize>(km::encode_timesync(t, 8, 1, 197, b)));
  }
  const kestrel::test::CmdResult r = kestrel::test::run_command("NODE_PATH=" + cache + "/node_modules node " +
                                                                std::string(KESTREL_SOURCE_DIR) +
                                                                "/tests/mavlink/decode_odometry.js " + bin);
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("stats valid 2 invalid 0 unknown 0"), std::string::npos) << r.out;
  // pkt I seq sysid compid msgid len crc_in crc_node: node's CRC (its CRC_EXTRA) equals ours.
  std::istringstream ss(r.out);
  std::string line;
  std::map<std::string, std::string> fields;
  int pkts = 0;
  while (std::getline(ss, line)) {
    std::istringstream ls(line);
    std::string tag;
    ls >> tag;
    if (tag == "pkt") {
      long long i, seq, sys, comp, id, len, c1, c2;
      ls >> i >> seq >> sys >> comp >> id >> len >> c1 >> c2;
      EXPECT_EQ(c1, c2) << line;
      EXPECT_EQ(comp, 197);
      EXPECT_EQ(id, i == 0 ? 0 : 111);
      ++pkts;
    } else if (tag == "field") {
      std::string i, name, v;
      ls >> i >> name >> v;
      fields[i + "." + name] = v;
    }
  }
  EXPECT_EQ(pkts, 2);
  EXPECT_EQ(fields["0.type"], "18");
  EXPECT_EQ(fields["0.autopilot"], "8");
  EXPECT_EQ(fields["0.system_status"], "4");
  EXPECT_EQ(fields["0.mavlink_version"], "3");
  EXPECT_EQ(fields["1.tc1"], "-5");
  EXPECT_EQ(fields["1.ts1"], "1234567890123456789");
  EXPECT_EQ(fields["1.target_system"], "3");
  EXPECT_EQ(fields["1.target_component"], "1");
}

namespace {

// A 3 s simulated log, written once per test process.
std::string small_log() {
  static const std::string path = [] {
    const std::string p = kestrel::test::temp_dir("mavlink_cli") + "/hover.klog";
    const kestrel::test::CmdResult r = kestrel::test::run_kestrel(
        "sim --scenario hover --duration 3 --seed 3 --width 160 --height 120 --out " + p);
    if (r.code != 0) std::fprintf(stderr, "sim failed: %s\n", r.out.c_str());
    return p;
  }();
  return path;
}

void expect_heartbeat_and_odometry(const std::vector<uint8_t>& bytes, const std::string& what) {
  km::MavlinkDecoder d;
  std::map<uint32_t, int> n;
  d.feed(bytes.data(), bytes.size(), [&](const km::MavlinkFrame& f) {
    ++n[f.msgid];
    EXPECT_EQ(f.compid, 197);
  });
  EXPECT_GE(n[km::kMsgIdHeartbeat], 1) << what << ": no HEARTBEAT (id 0)";
  EXPECT_GE(n[km::kMsgIdOdometry], 10) << what << ": no ODOMETRY (id 331)";
  EXPECT_EQ(d.stats().bad_crc, 0u) << what;
}

}  // namespace

TEST(MavlinkCli, UdpAndSerialBothSendHeartbeatAndOdometry) {
  const std::string log = small_log();
  // UDP.
  uint16_t port = 0;
  const int rx = udp_socket_on_loopback(&port);
  ASSERT_GE(rx, 0);
  std::vector<uint8_t> udp_bytes;
  std::thread reader([&] {
    uint8_t buf[2048];
    pollfd p{rx, POLLIN, 0};
    while (poll(&p, 1, 3000) > 0) {
      const ssize_t n = recv(rx, buf, sizeof buf, 0);
      if (n <= 0) break;
      udp_bytes.insert(udp_bytes.end(), buf, buf + n);
    }
  });
  const kestrel::test::CmdResult r = kestrel::test::run_kestrel(
      "replay " + log + " --estimator vo --mavlink-udp 127.0.0.1:" + std::to_string(port));
  reader.join();
  close(rx);
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("HEARTBEAT"), std::string::npos) << r.out;
  expect_heartbeat_and_odometry(udp_bytes, "--mavlink-udp");
  // Serial, through a pty.
  Pty pty;
  ASSERT_FALSE(pty.slave.empty());
  std::vector<uint8_t> serial_bytes;
  std::atomic<bool> done{false};
  std::thread sreader([&] {
    while (!done.load()) {
      const std::vector<uint8_t> v = pty.read_for(100);
      serial_bytes.insert(serial_bytes.end(), v.begin(), v.end());
    }
    const std::vector<uint8_t> v = pty.read_for(200);
    serial_bytes.insert(serial_bytes.end(), v.begin(), v.end());
  });
  const kestrel::test::CmdResult s = kestrel::test::run_kestrel(
      "replay " + log + " --estimator vo --mavlink-serial " + pty.slave + ":921600");
  done.store(true);
  sreader.join();
  ASSERT_EQ(s.code, 0) << s.out;
  expect_heartbeat_and_odometry(serial_bytes, "--mavlink-serial");
  // Both at once, or a malformed one, is a usage error.
  EXPECT_EQ(
      kestrel::test::run_kestrel("replay " + log + " --mavlink-udp 127.0.0.1:1 --mavlink-serial " + pty.slave)
          .code,
      2);
  EXPECT_EQ(kestrel::test::run_kestrel("replay " + log + " --mavlink-serial " + pty.slave + ":fast").code, 2);
}

TEST(MavlinkSigning, OdometryStreamSignsEverythingAndAnswersOnlySignedRequests) {
  // The ODOMETRY link with a key: every frame it sends verifies with the key (a
  // fresh verifier, as the autopilot is), an unsigned TIMESYNC request from the
  // autopilot is refused and counted, a signed one is answered.
  uint16_t port = 0;
  const int ap = udp_socket_on_loopback(&port);
  ASSERT_GE(ap, 0);
  km::SigningKey key;
  for (size_t i = 0; i < key.bytes.size(); ++i) key.bytes[i] = static_cast<uint8_t>(200 - i);
  km::OdometryStreamOptions so;
  so.endpoint = "127.0.0.1:" + std::to_string(port);
  so.signing = true;
  so.signing_key = key;
  so.signing_link_id = 4;
  km::OdometryStream stream(so);
  km::MavlinkSigning ap_verify(key, 0), ap_sign(key, 9);
  km::MavlinkDecoder verified;
  verified.set_signing(&ap_verify);
  std::map<uint32_t, int> seen;
  sockaddr_in from{};
  socklen_t fl = sizeof from;
  auto drain = [&] {
    uint8_t buf[2048];
    pollfd p{ap, POLLIN, 0};
    while (poll(&p, 1, 50) > 0) {
      const ssize_t n = recvfrom(ap, buf, sizeof buf, 0, reinterpret_cast<sockaddr*>(&from), &fl);
      if (n <= 0) break;
      verified.feed(buf, static_cast<size_t>(n), [&](const km::MavlinkFrame& f) { ++seen[f.msgid]; });
    }
  };
  int64_t now = 1'000'000'000;
  stream.service(now);
  kestrel::core::PoseSample in;
  in.quality = kestrel::core::TrackingQuality::kTracking;
  in.t_ns = now;
  ASSERT_TRUE(stream.publish(in));
  drain();
  EXPECT_EQ(seen[km::kMsgIdHeartbeat], 1);
  EXPECT_EQ(seen[km::kMsgIdTimesync], 1);
  EXPECT_EQ(seen[km::kMsgIdOdometry], 1);
  EXPECT_EQ(verified.stats().unauthenticated, 0u);
  ASSERT_NE(stream.signing_stats(), nullptr);
  EXPECT_EQ(stream.signing_stats()->signed_sent, 3u);

  // The autopilot asks for our clock, unsigned then signed.
  km::TimesyncMsg q;
  q.ts1 = 777;
  uint8_t out[km::kMaxFrameBytes];
  size_t m = km::encode_timesync(q, 0, 1, 1, out);
  sendto(ap, out, m, 0, reinterpret_cast<sockaddr*>(&from), fl);
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  stream.service(now + 1000);
  EXPECT_EQ(stream.time_sync().stats().requests_answered, 0u);
  EXPECT_EQ(stream.decoder_stats().unauthenticated, 1u);
  EXPECT_EQ(stream.signing_stats()->unsigned_rejected, 1u);
  m = km::encode_timesync(q, 1, 1, 1, out, &ap_sign);
  sendto(ap, out, m, 0, reinterpret_cast<sockaddr*>(&from), fl);
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  stream.service(now + 2000);
  EXPECT_EQ(stream.time_sync().stats().requests_answered, 1u);
  drain();
  EXPECT_EQ(seen[km::kMsgIdTimesync], 2) << "the answer, signed";
  EXPECT_EQ(verified.stats().unauthenticated, 0u);
  close(ap);
}

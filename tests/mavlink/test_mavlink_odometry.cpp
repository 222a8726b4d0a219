// The ODOMETRY encoder checked against the specification and against an
// independent implementation (node-mavlink from npm): frames we encode are
// decoded by node and compared field by field, CRC included, and node's own
// encoding of the decoded message must equal ours byte for byte.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "kestrel/drivers/mavlink/mavlink_v2.hpp"
#include "kestrel/drivers/mavlink/udp_sender.hpp"
#include "kestrel/mavlink/odometry_adapter.hpp"
#include "kestrel/mavlink/odometry_stream.hpp"
#include "run_command.hpp"
#include "test_data.hpp"

namespace km = kestrel::mavlink;

namespace {

std::string run_capture(const std::string& cmd, int* code) {
  const kestrel::test::CmdResult r = kestrel::test::run_command(cmd);
  *code = r.code;
  return r.out;
}

std::string hex(const uint8_t* d, size_t n) {
  static const char* k = "0123456789abcdef";
  std::string s;
  for (size_t i = 0; i < n; ++i) {
    s += k[d[i] >> 4];
    s += k[d[i] & 15];
  }
  return s;
}

// An estimator pose covariance [dp_W; dtheta_B] with every cross term set
// (symmetric positive definite), as the window / EKF backends export it.
Eigen::Matrix<double, 6, 6> full_covariance() {
  Eigen::Matrix<double, 6, 6> A;
  for (int r = 0; r < 6; ++r)
    for (int c = 0; c < 6; ++c) A(r, c) = 0.01 * std::sin(1.0 + 7.0 * r + 3.0 * c);
  Eigen::Matrix<double, 6, 6> P = A * A.transpose();
  P.diagonal() += Eigen::Matrix<double, 6, 1>(4e-4, 9e-4, 1e-4, 2e-4, 3e-4, 5e-4);
  return P;
}

kestrel::core::PoseSample covariance_input() {
  kestrel::core::PoseSample in;
  in.t_ns = 7'000'000'000;
  in.quality = kestrel::core::TrackingQuality::kTracking;
  in.set_p_WB(Eigen::Vector3d(0.5, -1.5, 2.0));
  in.set_q_WB(Eigen::Quaterniond(Eigen::AngleAxisd(0.7, Eigen::Vector3d(0.2, -0.3, 1.0).normalized())));
  in.set_v_WB(Eigen::Vector3d(0.3, 0.1, -0.2));
  in.pose_cov_valid = true;
  Eigen::Map<Eigen::Matrix<double, 6, 6>>(in.pose_cov) = full_covariance();
  return in;
}

// Messages that exercise every field, the extension tail, trimming and NaN.
std::vector<km::OdometryMsg> sample_messages() {
  std::vector<km::OdometryMsg> v;
  km::OdometryMsg a;
  a.time_usec = 1234567890123ull;
  a.x = 1.25f;
  a.y = -2.5f;
  a.z = -0.75f;
  a.q[0] = 0.9238795f;
  a.q[1] = 0.0f;
  a.q[2] = 0.0f;
  a.q[3] = -0.3826834f;
  a.vx = 0.1f;
  a.vy = -0.2f;
  a.vz = 0.3f;
  a.rollspeed = 0.01f;
  a.pitchspeed = -0.02f;
  a.yawspeed = 0.5f;
  for (int i = 0; i < 21; ++i) {
    a.pose_covariance[i] = 0.001f * static_cast<float>(i + 1);
    a.velocity_covariance[i] = -0.01f * static_cast<float>(i + 1);
  }
  a.reset_counter = 7;
  a.estimator_type = km::kMavEstimatorVio;
  a.quality = 100;
  v.push_back(a);

  km::OdometryMsg b = a;  // zero extensions: the v2 tail trim removes them
  b.reset_counter = 0;
  b.estimator_type = 0;
  b.quality = 0;
  v.push_back(b);

  km::OdometryMsg c = a;  // lost: NaN covariance, quality -1, counter at its top
  c.pose_covariance[0] = std::numeric_limits<float>::quiet_NaN();
  c.velocity_covariance[0] = std::numeric_limits<float>::quiet_NaN();
  c.reset_counter = 255;
  c.quality = -1;
  v.push_back(c);

  km::OdometryMsg d{};  // everything zero: the payload shrinks to one byte
  d.q[0] = 0.0f;
  d.frame_id = 0;
  d.child_frame_id = 0;
  d.estimator_type = 0;
  v.push_back(d);

  km::OdometryMsg e = a;  // a nonzero last base byte, zero extensions but the last one
  e.reset_counter = 0;
  e.estimator_type = 0;
  e.quality = 42;
  e.time_usec = 0xFFFFFFFFFFFFFFFFull;
  v.push_back(e);

  // A backend's full pose covariance through the adapter (FRD frames): the
  // 21 floats must survive node-mavlink's decode exactly.
  km::OdometryMsg f;
  if (km::to_odometry(covariance_input(), km::OdometryAdapterOptions{}, f)) v.push_back(f);
  return v;
}

std::vector<double> parse_values(const std::string& s) {
  std::vector<double> out;
  std::stringstream ss(s);
  std::string tok;
  while (std::getline(ss, tok, ',')) out.push_back(std::strtod(tok.c_str(), nullptr));
  return out;
}

void expect_same(double node, float ours, const std::string& what) {
  if (std::isnan(ours)) {
    EXPECT_TRUE(std::isnan(node)) << what << ": node " << node;
  } else {
    EXPECT_EQ(node, static_cast<double>(ours)) << what;  // float32 round trip is exact
  }
}

}  // namespace

TEST(MavlinkCrc, X25CheckValue) {
  // CRC-16/MCRF4XX check value of "123456789" (the X.25 variant MAVLink uses).
  const char* s = "123456789";
  EXPECT_EQ(km::crc_x25(reinterpret_cast<const uint8_t*>(s), 9), 0x6F91);
}

TEST(MavlinkCrc, OdometryCrcExtraFromCommonXml) {
  // The base fields of ODOMETRY as common.xml lists them (extensions are not
  // part of CRC_EXTRA). The wire order sorts them by type size, stable.
  struct F {
    const char* type;
    const char* name;
    int size;
    int array;
  };
  std::vector<F> xml = {{"uint64_t", "time_usec", 8, 0},
                        {"uint8_t", "frame_id", 1, 0},
                        {"uint8_t", "child_frame_id", 1, 0},
                        {"float", "x", 4, 0},
                        {"float", "y", 4, 0},
                        {"float", "z", 4, 0},
                        {"float", "q", 4, 4},
                        {"float", "vx", 4, 0},
                        {"float", "vy", 4, 0},
                        {"float", "vz", 4, 0},
                        {"float", "rollspeed", 4, 0},
                        {"float", "pitchspeed", 4, 0},
                        {"float", "yawspeed", 4, 0},
                        {"float", "pose_covariance", 4, 21},
                        {"float", "velocity_covariance", 4, 21}};
  std::stable_sort(xml.begin(), xml.end(), [](const F& a, const F& b) { return a.size > b.size; });
  uint16_t crc = 0xFFFF;
  auto add = [&](const std::string& s) {
    crc = km::crc_x25(reinterpret_cast<const uint8_t*>(s.data()), s.size(), crc);
  };
  add("ODOMETRY ");
  for (const F& f : xml) {
    add(std::string(f.type) + " ");
    add(std::string(f.name) + " ");
    if (f.array > 0) crc = km::crc_x25_accumulate(static_cast<uint8_t>(f.array), crc);
  }
  const uint8_t extra = static_cast<uint8_t>((crc & 0xFF) ^ (crc >> 8));
  EXPECT_EQ(extra, km::kOdometryCrcExtra);
  EXPECT_EQ(extra, 91);
}

TEST(MavlinkEncode, LayoutAndTrim) {
  const auto msgs = sample_messages();
  uint8_t frame[km::kMaxFrameBytes];
  // Full message: 233-byte payload, the last byte is quality.
  size_t n = km::encode_odometry(msgs[0], 5, 1, 197, frame);
  ASSERT_EQ(n, km::kHeaderV2Bytes + 233 + 2);
  EXPECT_EQ(frame[0], 0xFD);
  EXPECT_EQ(frame[1], 233);
  EXPECT_EQ(frame[4], 5);
  EXPECT_EQ(frame[5], 1);
  EXPECT_EQ(frame[6], 197);
  EXPECT_EQ(frame[7] | (frame[8] << 8) | (frame[9] << 16), 331);
  EXPECT_EQ(frame[10 + 232], 100);  // quality
  EXPECT_EQ(frame[10 + 230], 7);    // reset_counter
  EXPECT_EQ(frame[10 + 228], km::kMavFrameLocalFrd);
  // Zero extensions are trimmed: 230 bytes remain (child_frame_id last).
  n = km::encode_odometry(msgs[1], 0, 1, 197, frame);
  EXPECT_EQ(frame[1], 230);
  EXPECT_EQ(n, km::kHeaderV2Bytes + 230 + 2);
  // All zero: one byte stays.
  n = km::encode_odometry(msgs[3], 0, 1, 197, frame);
  EXPECT_EQ(frame[1], 1);
  EXPECT_EQ(n, km::kHeaderV2Bytes + 1 + 2);
}

TEST(MavlinkEncode, DecodedByNodeMavlinkFieldByField) {
  const std::string cache = std::string(KESTREL_BUILD_DIR) + "/npm-cache";
  int code = 0;
  const std::string install = run_capture(
      "sh " + std::string(KESTREL_SOURCE_DIR) + "/tests/mavlink/install_node_mavlink.sh " + cache, &code);
  if (code != 0) GTEST_SKIP() << "node-mavlink unavailable, independent decode NOT checked: " << install;

  const auto msgs = sample_messages();
  // The last one carries a backend's full covariance, rotated into FRD: every
  // one of its 21 floats (cross terms included) must come back from node.
  ASSERT_EQ(msgs.size(), 6u);
  int nonzero = 0;
  for (float c : msgs[5].pose_covariance) nonzero += c != 0.0f ? 1 : 0;
  ASSERT_EQ(nonzero, 21);
  const std::string dir = kestrel::test::temp_dir("mavlink_node");
  const std::string bin = dir + "/frames.bin";
  std::vector<std::string> ours_hex;
  std::vector<uint16_t> ours_crc;
  {
    std::ofstream f(bin, std::ios::binary);
    // Noise before and between frames: the decoder must resynchronise on STX.
    const uint8_t junk[3] = {0x00, 0x55, 0x12};
    f.write(reinterpret_cast<const char*>(junk), 3);
    for (size_t i = 0; i < msgs.size(); ++i) {
      uint8_t frame[km::kMaxFrameBytes];
      const size_t n = km::encode_odometry(msgs[i], static_cast<uint8_t>(250 + i), 42, 197, frame);
      f.write(reinterpret_cast<const char*>(frame), static_cast<std::streamsize>(n));
      ours_hex.push_back(hex(frame, n));
      ours_crc.push_back(static_cast<uint16_t>(frame[n - 2] | (frame[n - 1] << 8)));
    }
  }
  const std::string out =
      run_capture("NODE_PATH=" + cache + "/node_modules node " + std::string(KESTREL_SOURCE_DIR) +
                      "/tests/mavlink/decode_odometry.js " + bin,
                  &code);
  ASSERT_EQ(code, 0) << out;

  std::map<size_t, std::map<std::string, std::string>> fields;
  std::map<size_t, std::vector<long long>> pkt;
  std::map<size_t, std::string> reser;
  long long valid = -1, invalid = -1, unknown = -1;
  std::stringstream ss(out);
  std::string line;
  while (std::getline(ss, line)) {
    std::stringstream ls(line);
    std::string tag;
    ls >> tag;
    if (tag == "pkt") {
      size_t i;
      ls >> i;
      long long v;
      while (ls >> v) pkt[i].push_back(v);
    } else if (tag == "field") {
      size_t i;
      std::string name, val;
      ls >> i >> name >> val;
      fields[i][name] = val;
    } else if (tag == "reserialized") {
      size_t i;
      ls >> i >> reser[i];
    } else if (tag == "stats") {
      std::string k;
      ls >> k >> valid >> k >> invalid >> k >> unknown;
    }
  }
  EXPECT_EQ(valid, static_cast<long long>(msgs.size())) << out;
  EXPECT_EQ(invalid, 0) << out;
  EXPECT_EQ(unknown, 0) << out;
  ASSERT_EQ(pkt.size(), msgs.size()) << out;
  for (size_t i = 0; i < msgs.size(); ++i) {
    SCOPED_TRACE("message " + std::to_string(i));
    const auto& m = msgs[i];
    const auto& h = pkt[i];
    ASSERT_EQ(h.size(), 7u) << out;
    EXPECT_EQ(h[0], static_cast<long long>(250 + i));  // seq
    EXPECT_EQ(h[1], 42);                               // sysid
    EXPECT_EQ(h[2], 197);                              // compid
    EXPECT_EQ(h[3], 331);                              // msgid
    EXPECT_EQ(h[5], ours_crc[i]);                      // the CRC node read is ours ...
    EXPECT_EQ(h[6], ours_crc[i]);                      // ... and the one node computes with its CRC_EXTRA
    auto& f = fields[i];
    EXPECT_EQ(f["time_usec"], std::to_string(m.time_usec));
    EXPECT_EQ(std::atoi(f["frame_id"].c_str()), m.frame_id);
    EXPECT_EQ(std::atoi(f["child_frame_id"].c_str()), m.child_frame_id);
    EXPECT_EQ(std::atoi(f["reset_counter"].c_str()), m.reset_counter);
    EXPECT_EQ(std::atoi(f["estimator_type"].c_str()), m.estimator_type);
    EXPECT_EQ(std::atoi(f["quality"].c_str()), m.quality);
    const std::pair<const char*, float> scalars[] = {{"x", m.x},
                                                     {"y", m.y},
                                                     {"z", m.z},
                                                     {"vx", m.vx},
                                                     {"vy", m.vy},
                                                     {"vz", m.vz},
                                                     {"rollspeed", m.rollspeed},
                                                     {"pitchspeed", m.pitchspeed},
                                                     {"yawspeed", m.yawspeed}};
    for (const auto& [name, v] : scalars) {
      const auto vals = parse_values(f[name]);
      ASSERT_EQ(vals.size(), 1u) << name;
      expect_same(vals[0], v, name);
    }
    const auto q = parse_values(f["q"]);
    ASSERT_EQ(q.size(), 4u);
    for (int k = 0; k < 4; ++k) expect_same(q[k], m.q[k], "q" + std::to_string(k));
    const auto pc = parse_values(f["pose_covariance"]);
    const auto vc = parse_values(f["velocity_covariance"]);
    ASSERT_EQ(pc.size(), 21u);
    ASSERT_EQ(vc.size(), 21u);
    for (int k = 0; k < 21; ++k) {
      expect_same(pc[k], m.pose_covariance[k], "pose_covariance" + std::to_string(k));
      expect_same(vc[k], m.velocity_covariance[k], "velocity_covariance" + std::to_string(k));
    }
    if (i == 3) {
      // All-zero payload: the MAVLink serialization guide keeps the first
      // payload byte ("never truncated"), node-mavlink 2.3.0 trims to zero
      // bytes. Node still decodes ours (checked above); its own frame must
      // differ from ours exactly by that byte.
      EXPECT_EQ(ours_hex[i].substr(2, 2), "01");
      EXPECT_EQ(reser[i].substr(2, 2), "00")
          << "node-mavlink changed its trimming: compare whole frames again";
    } else {
      EXPECT_EQ(reser[i], ours_hex[i]) << "node-mavlink encodes the same message differently";
    }
  }
}

TEST(MavlinkAdapter, FramesToLocalFrdAndBodyFrd) {
  km::OdometryAdapterOptions opt;
  kestrel::core::PoseSample in;
  in.t_ns = 5'000'000'123;
  in.quality = kestrel::core::TrackingQuality::kUninitialized;
  km::OdometryMsg m;
  EXPECT_FALSE(km::to_odometry(in, opt, m)) << "nothing is sent before initialisation";

  // 1 m up, 2 m along W x, 3 m along W y (left): FRD z = -1, x = 2, y = -3.
  in.quality = kestrel::core::TrackingQuality::kTracking;
  in.set_p_WB(Eigen::Vector3d(2, 3, 1));
  // Yawed 30 deg to the left (counter-clockwise seen from above): NED/FRD yaw is -30 deg.
  const double yaw = 30.0 * M_PI / 180.0;
  in.set_q_WB(Eigen::Quaterniond(Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ())));
  // Flying forward along the body x at 1 m/s, climbing at 0.5 m/s, turning left at 0.2 rad/s.
  in.set_v_WB(in.q_WB() * Eigen::Vector3d(1, 0, 0) + Eigen::Vector3d(0, 0, 0.5));
  in.set_omega_B(Eigen::Vector3d(0, 0, 0.2));
  in.reset_counter = 258;
  ASSERT_TRUE(km::to_odometry(in, opt, m));
  EXPECT_EQ(m.time_usec, 5'000'000u);
  EXPECT_EQ(m.frame_id, km::kMavFrameLocalFrd);
  EXPECT_EQ(m.child_frame_id, km::kMavFrameBodyFrd);
  EXPECT_FLOAT_EQ(m.x, 2);
  EXPECT_FLOAT_EQ(m.y, -3);
  EXPECT_FLOAT_EQ(m.z, -1);
  // Quaternion of a pure yaw of -30 deg about FRD z (down).
  EXPECT_NEAR(m.q[0], std::cos(-yaw / 2), 1e-6);
  EXPECT_NEAR(m.q[1], 0, 1e-6);
  EXPECT_NEAR(m.q[2], 0, 1e-6);
  EXPECT_NEAR(m.q[3], std::sin(-yaw / 2), 1e-6);
  // Body FRD velocity: forward 1, right 0, down -0.5.
  EXPECT_NEAR(m.vx, 1, 1e-6);
  EXPECT_NEAR(m.vy, 0, 1e-6);
  EXPECT_NEAR(m.vz, -0.5, 1e-6);
  EXPECT_NEAR(m.yawspeed, -0.2, 1e-6);  // turning left = negative yaw rate about down
  EXPECT_EQ(m.reset_counter, 2) << "the counter wraps at 256 on the wire";
  EXPECT_EQ(m.quality, 100);
  EXPECT_EQ(m.estimator_type, km::kMavEstimatorVio);
  // Fixed covariance while tracking: diagonal, variances of the documented sigmas.
  EXPECT_FLOAT_EQ(m.pose_covariance[0],
                  static_cast<float>(opt.tracking_pos_sigma_m * opt.tracking_pos_sigma_m));
  EXPECT_FLOAT_EQ(m.pose_covariance[1], 0.0f);
  EXPECT_FLOAT_EQ(m.pose_covariance[15],
                  static_cast<float>(opt.tracking_att_sigma_rad * opt.tracking_att_sigma_rad));
  EXPECT_FLOAT_EQ(m.pose_covariance[20],
                  static_cast<float>(opt.tracking_att_sigma_rad * opt.tracking_att_sigma_rad));

  in.quality = kestrel::core::TrackingQuality::kImuOnly;
  ASSERT_TRUE(km::to_odometry(in, opt, m));
  EXPECT_EQ(m.quality, opt.quality_coasting);
  EXPECT_GT(m.pose_covariance[0], static_cast<float>(opt.tracking_pos_sigma_m * opt.tracking_pos_sigma_m));

  in.quality = kestrel::core::TrackingQuality::kLost;
  ASSERT_TRUE(km::to_odometry(in, opt, m));
  EXPECT_EQ(m.quality, -1);
  EXPECT_TRUE(std::isnan(m.pose_covariance[0]));
  EXPECT_TRUE(std::isnan(m.velocity_covariance[0]));

  // A covariance from the estimator is rotated, not replaced: position y/z flip sign in their cross terms.
  in.quality = kestrel::core::TrackingQuality::kTracking;
  in.pose_cov_valid = true;
  Eigen::Map<Eigen::Matrix<double, 6, 6>> cov(in.pose_cov);
  cov.setIdentity();
  cov(0, 1) = cov(1, 0) = 0.25;
  ASSERT_TRUE(km::to_odometry(in, opt, m));
  EXPECT_FLOAT_EQ(m.pose_covariance[0], 1.0f);
  EXPECT_FLOAT_EQ(m.pose_covariance[1], -0.25f);
}

TEST(MavlinkAdapter, EstimatorCovarianceIsRotatedIntoFrdAndCheckedByPerturbation) {
  // Independent of the adapter's Jacobian: perturb the estimate in the
  // covariance's own convention (p + dp_W, R Exp(dtheta_B)), convert both
  // poses with the adapter, read the error back in FRD (dp_L, Log(R_LF' R'_LF)),
  // and propagate the covariance through that measured linear map.
  const km::OdometryAdapterOptions opt;
  const kestrel::core::PoseSample in = covariance_input();
  km::OdometryMsg m0;
  ASSERT_TRUE(km::to_odometry(in, opt, m0));
  auto rot = [](const km::OdometryMsg& m) {
    return Eigen::Quaterniond(m.q[0], m.q[1], m.q[2], m.q[3]).normalized().toRotationMatrix().cast<double>();
  };
  const double h = 1e-4;
  Eigen::Matrix<double, 6, 6> M;
  for (int k = 0; k < 6; ++k) {
    kestrel::core::PoseSample d = in;
    Eigen::Matrix<double, 6, 1> e = Eigen::Matrix<double, 6, 1>::Zero();
    e[k] = h;
    d.set_p_WB(in.p_WB() + e.head<3>());
    d.set_q_WB(in.q_WB() *
               Eigen::Quaterniond(Eigen::AngleAxisd(e.tail<3>().norm(), e.tail<3>().normalized())));
    if (k < 3) d.set_q_WB(in.q_WB());
    km::OdometryMsg m1;
    ASSERT_TRUE(km::to_odometry(d, opt, m1));
    Eigen::Matrix<double, 6, 1> f;
    f.head<3>() = Eigen::Vector3d(m1.x - m0.x, m1.y - m0.y, m1.z - m0.z);
    const Eigen::AngleAxisd aa(rot(m0).transpose() * rot(m1));
    f.tail<3>() = aa.angle() * aa.axis();
    M.col(k) = f / h;
  }
  const Eigen::Matrix<double, 6, 6> expect = M * in.covariance().cov * M.transpose();
  int idx = 0;
  for (int r = 0; r < 6; ++r)
    for (int c = r; c < 6; ++c, ++idx)
      // float32 positions and quaternion limit the finite difference to ~1e-3 relative.
      EXPECT_NEAR(m0.pose_covariance[idx], expect(r, c), 2e-3 * expect.diagonal().maxCoeff() + 1e-7)
          << "pose_covariance[" << idx << "] (" << r << "," << c << ")";
  // The backends export no twist covariance: the documented fixed value.
  EXPECT_FLOAT_EQ(m0.velocity_covariance[0],
                  static_cast<float>(opt.tracking_vel_sigma_mps * opt.tracking_vel_sigma_mps));
  // Coasting: the last camera update's covariance would be over-confident; the fixed coasting value goes out.
  kestrel::core::PoseSample coast = in;
  coast.quality = kestrel::core::TrackingQuality::kImuOnly;
  km::OdometryMsg mc;
  ASSERT_TRUE(km::to_odometry(coast, opt, mc));
  EXPECT_FLOAT_EQ(mc.pose_covariance[0],
                  static_cast<float>(opt.coasting_pos_sigma_m * opt.coasting_pos_sigma_m));
  EXPECT_FLOAT_EQ(mc.pose_covariance[1], 0.0f);
}

TEST(MavlinkUdp, StreamSendsOneDatagramPerPose) {
  const int rx = socket(AF_INET, SOCK_DGRAM, 0);
  ASSERT_GE(rx, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  a.sin_port = 0;
  ASSERT_EQ(bind(rx, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
  socklen_t len = sizeof a;
  ASSERT_EQ(getsockname(rx, reinterpret_cast<sockaddr*>(&a), &len), 0);
  timeval tv{2, 0};
  setsockopt(rx, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);

  km::OdometryStreamOptions so;
  so.endpoint = "127.0.0.1:" + std::to_string(ntohs(a.sin_port));
  km::OdometryStream stream(so);
  kestrel::core::PoseSample in;
  in.t_ns = 1'000'000'000;
  EXPECT_FALSE(stream.publish(in));  // uninitialised: not sent, counted
  EXPECT_EQ(stream.not_initialised(), 1u);
  in.quality = kestrel::core::TrackingQuality::kTracking;
  in.set_p_WB(Eigen::Vector3d(1, 2, 3));
  for (int i = 0; i < 3; ++i) EXPECT_TRUE(stream.publish(in));
  EXPECT_EQ(stream.stats().sent, 3u);
  EXPECT_EQ(stream.stats().failed, 0u);

  km::OdometryMsg m;
  ASSERT_TRUE(km::to_odometry(in, so.adapter, m));
  for (int i = 0; i < 3; ++i) {
    uint8_t buf[512];
    const ssize_t n = recv(rx, buf, sizeof buf, 0);
    ASSERT_GT(n, 0);
    uint8_t expect[km::kMaxFrameBytes];
    const size_t en = km::encode_odometry(m, static_cast<uint8_t>(i), so.sysid, so.compid, expect);
    EXPECT_EQ(hex(buf, static_cast<size_t>(n)), hex(expect, en)) << "datagram " << i;
  }
  close(rx);
}

TEST(MavlinkUdp, BadEndpointsAreClearErrors) {
  for (const char* e :
       {"nohost", "127.0.0.1:", ":14540", "127.0.0.1:0", "127.0.0.1:70000", "127.0.0.1:12x"}) {
    try {
      km::UdpSender s(e);
      ADD_FAILURE() << e << " accepted";
    } catch (const std::invalid_argument& ex) {
      EXPECT_NE(std::string(ex.what()).find(e), std::string::npos) << ex.what();
    }
  }
}

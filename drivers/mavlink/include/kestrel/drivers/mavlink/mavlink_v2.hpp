// MAVLink v2 framing and the messages Kestrel sends (ODOMETRY #331, HEARTBEAT,
// TIMESYNC, COMMAND_LONG) and reads (TIMESYNC, HIGHRES_IMU, SCALED_IMU,
// RAW_IMU, COMMAND_ACK), written from the protocol specification rather than
// generated: the framing is a few dozen lines and owning it keeps the pipeline
// free of a code generator. The byte layout is documented in docs/px4.md;
// signing in mavlink_signing.hpp.
#pragma once

#include <cstddef>
#include <cstdint>

namespace kestrel::mavlink {

constexpr uint8_t kStxV2 = 0xFD;
constexpr std::size_t kHeaderV2Bytes = 10;  // STX, len, incompat, compat, seq, sysid, compid, msgid[3]
constexpr std::size_t kChecksumBytes = 2;
constexpr std::size_t kMaxPayloadBytes = 255;
constexpr std::size_t kSignatureBlockBytes = 13;  // link id, timestamp, signature (mavlink_signing.hpp)
// A frame as it may go out: signed ones included.
constexpr std::size_t kMaxFrameBytes =
    kHeaderV2Bytes + kMaxPayloadBytes + kChecksumBytes + kSignatureBlockBytes;

class MavlinkSigning;

constexpr uint32_t kMsgIdOdometry = 331;
// CRC_EXTRA is the X.25 hash of the message's base fields (common.xml), so a
// sender and a receiver that disagree on the layout reject each other's frames.
// tests/mavlink recomputes it from the field list.
constexpr uint8_t kOdometryCrcExtra = 91;
constexpr std::size_t kOdometryPayloadBytes = 233;  // untrimmed, extensions included

// HEARTBEAT (#0, minimal.xml): who we are, once a second.
constexpr uint32_t kMsgIdHeartbeat = 0;
constexpr uint8_t kHeartbeatCrcExtra = 50;
constexpr std::size_t kHeartbeatPayloadBytes = 9;
// TIMESYNC (#111): tc1 = 0 asks the peer for its clock; its answer echoes ts1.
constexpr uint32_t kMsgIdTimesync = 111;
constexpr uint8_t kTimesyncCrcExtra = 34;
constexpr std::size_t kTimesyncPayloadBytes = 18;  // extensions target_system, target_component included

// HIGHRES_IMU (#105): SI units (m/s^2, rad/s, gauss, hPa, degC), time_usec on the autopilot's clock.
constexpr uint32_t kMsgIdHighresImu = 105;
constexpr uint8_t kHighresImuCrcExtra = 93;
constexpr std::size_t kHighresImuPayloadBytes = 63;  // extension `id` included
// SCALED_IMU (#26): mG, mrad/s, mgauss, time_boot_ms.
constexpr uint32_t kMsgIdScaledImu = 26;
constexpr uint8_t kScaledImuCrcExtra = 170;
constexpr std::size_t kScaledImuPayloadBytes = 24;  // extension `temperature` included
// RAW_IMU (#27): the sensor's counts (the scale is the board's: from the config).
constexpr uint32_t kMsgIdRawImu = 27;
constexpr uint8_t kRawImuCrcExtra = 144;
constexpr std::size_t kRawImuPayloadBytes = 29;  // extensions `id`, `temperature` included
// COMMAND_LONG (#76) and its COMMAND_ACK (#77).
constexpr uint32_t kMsgIdCommandLong = 76;
constexpr uint8_t kCommandLongCrcExtra = 152;
constexpr std::size_t kCommandLongPayloadBytes = 33;
constexpr uint32_t kMsgIdCommandAck = 77;
constexpr uint8_t kCommandAckCrcExtra = 143;
constexpr std::size_t kCommandAckPayloadBytes = 10;  // extensions included
constexpr uint16_t kMavCmdSetMessageInterval = 511;  // param1 message id, param2 interval us
constexpr uint8_t kMavResultAccepted = 0;

constexpr uint8_t kMavCompIdAutopilot1 = 1;
constexpr uint8_t kMavCompIdVisualInertialOdometry = 197;  // MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
constexpr uint8_t kMavTypeOnboardController = 18;          // MAV_TYPE_ONBOARD_CONTROLLER
constexpr uint8_t kMavAutopilotInvalid = 8;                // MAV_AUTOPILOT_INVALID: not a flight controller
// MAV_STATE values (minimal.xml).
enum MavState : uint8_t {
  kMavStateUninit = 0,
  kMavStateBoot = 1,
  kMavStateStandby = 3,
  kMavStateActive = 4,
  kMavStateCritical = 5,
};

struct HeartbeatMsg {
  uint32_t custom_mode = 0;
  uint8_t type = kMavTypeOnboardController;
  uint8_t autopilot = kMavAutopilotInvalid;
  uint8_t base_mode = 0;
  uint8_t system_status = kMavStateStandby;
  uint8_t mavlink_version = 3;
};

struct TimesyncMsg {
  int64_t tc1 = 0;  // ns; 0 in a request
  int64_t ts1 = 0;  // ns: the requester's clock, echoed in the answer
  uint8_t target_system = 0;
  uint8_t target_component = 0;
};

struct HighresImuMsg {
  uint64_t time_usec = 0;
  float xacc = 0, yacc = 0, zacc = 0;     // m/s^2
  float xgyro = 0, ygyro = 0, zgyro = 0;  // rad/s
  float xmag = 0, ymag = 0, zmag = 0;     // gauss
  float abs_pressure = 0, diff_pressure = 0, pressure_alt = 0, temperature = 0;
  uint16_t fields_updated = 0;  // HIGHRES_IMU_UPDATED_* bits
  uint8_t id = 0;               // which of the autopilot's IMUs (extension)
};

struct ScaledImuMsg {
  uint32_t time_boot_ms = 0;
  int16_t xacc = 0, yacc = 0, zacc = 0;     // mG
  int16_t xgyro = 0, ygyro = 0, zgyro = 0;  // mrad/s
  int16_t xmag = 0, ymag = 0, zmag = 0;     // mgauss
  int16_t temperature = 0;                  // cdegC (extension; 0 = not sent)
};

struct RawImuMsg {
  uint64_t time_usec = 0;
  int16_t xacc = 0, yacc = 0, zacc = 0;  // counts
  int16_t xgyro = 0, ygyro = 0, zgyro = 0;
  int16_t xmag = 0, ymag = 0, zmag = 0;
  uint8_t id = 0;           // extension
  int16_t temperature = 0;  // cdegC (extension)
};

struct CommandLongMsg {
  float param[7] = {};
  uint16_t command = 0;
  uint8_t target_system = 0;
  uint8_t target_component = 0;
  uint8_t confirmation = 0;
};

struct CommandAckMsg {
  uint16_t command = 0;
  uint8_t result = 0;
  uint8_t progress = 0;
  int32_t result_param2 = 0;
  uint8_t target_system = 0;
  uint8_t target_component = 0;
};

// MAV_FRAME values used here (common.xml).
enum MavFrame : uint8_t {
  kMavFrameLocalNed = 1,
  kMavFrameBodyFrd = 12,
  kMavFrameLocalFrd = 20,  // earth-fixed, z down, x = the vehicle's heading at the origin
};

// MAV_ESTIMATOR_TYPE values (common.xml).
enum MavEstimatorType : uint8_t {
  kMavEstimatorUnknown = 0,
  kMavEstimatorNaive = 1,
  kMavEstimatorVision = 2,
  kMavEstimatorVio = 3,
};

// ODOMETRY fields in MAVLink units and frames (conversion from Kestrel's W/B
// happens in odometry_adapter.hpp, nowhere else).
struct OdometryMsg {
  uint64_t time_usec = 0;
  uint8_t frame_id = kMavFrameLocalFrd;
  uint8_t child_frame_id = kMavFrameBodyFrd;
  float x = 0, y = 0, z = 0;  // m
  float q[4] = {1, 0, 0, 0};  // w x y z
  float vx = 0, vy = 0, vz = 0;
  float rollspeed = 0, pitchspeed = 0, yawspeed = 0;
  float pose_covariance[21] = {};      // row-major upper triangle of 6x6 (x y z roll pitch yaw)
  float velocity_covariance[21] = {};  // (vx vy vz rollspeed pitchspeed yawspeed)
  // Extensions.
  uint8_t reset_counter = 0;
  uint8_t estimator_type = kMavEstimatorVio;
  int8_t quality = 0;  // % : -1 failed, 0 unknown, 1 worst .. 100 best
};

// X.25 / CRC-16-MCRF4XX as MAVLink uses it (init 0xFFFF, no final xor).
uint16_t crc_x25_accumulate(uint8_t byte, uint16_t crc);
uint16_t crc_x25(const uint8_t* data, std::size_t n, uint16_t crc = 0xFFFF);

// The untrimmed wire payload: base fields sorted by type size (8, 4, 1 bytes),
// then the extensions in definition order. Returns kOdometryPayloadBytes.
std::size_t pack_odometry_payload(const OdometryMsg& m, uint8_t* payload);

// Wraps a payload in a v2 frame: trailing zero bytes are trimmed (at least one
// byte stays), header and checksum (with crc_extra) added, and, with `sign`,
// the signed flag and the signature block. `out` needs kMaxFrameBytes.
// Returns the frame length.
std::size_t frame_v2(uint32_t msgid, uint8_t crc_extra, const uint8_t* payload, std::size_t payload_len,
                     uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                     MavlinkSigning* sign = nullptr);

// pack + frame in one call; no allocation.
std::size_t encode_odometry(const OdometryMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                            MavlinkSigning* sign = nullptr);
std::size_t encode_heartbeat(const HeartbeatMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                             MavlinkSigning* sign = nullptr);
std::size_t encode_timesync(const TimesyncMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                            MavlinkSigning* sign = nullptr);
std::size_t encode_command_long(const CommandLongMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid,
                                uint8_t* out, MavlinkSigning* sign = nullptr);
// What an autopilot sends (the simulated autopilot of tests/mavlink, and the fuzz seeds).
std::size_t encode_highres_imu(const HighresImuMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid,
                               uint8_t* out, MavlinkSigning* sign = nullptr);
std::size_t encode_scaled_imu(const ScaledImuMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                              MavlinkSigning* sign = nullptr);
std::size_t encode_raw_imu(const RawImuMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid, uint8_t* out,
                           MavlinkSigning* sign = nullptr);
std::size_t encode_command_ack(const CommandAckMsg& m, uint8_t seq, uint8_t sysid, uint8_t compid,
                               uint8_t* out, MavlinkSigning* sign = nullptr);

// From a payload zero-extended to the message's full length (what
// MavlinkDecoder hands out).
HeartbeatMsg unpack_heartbeat(const uint8_t* payload);
TimesyncMsg unpack_timesync(const uint8_t* payload);
HighresImuMsg unpack_highres_imu(const uint8_t* payload);
ScaledImuMsg unpack_scaled_imu(const uint8_t* payload);
RawImuMsg unpack_raw_imu(const uint8_t* payload);
CommandLongMsg unpack_command_long(const uint8_t* payload);
CommandAckMsg unpack_command_ack(const uint8_t* payload);

// CRC_EXTRA and untrimmed payload length of the messages this build knows
// (HEARTBEAT, TIMESYNC, ODOMETRY, the IMU messages, COMMAND_LONG/ACK); false
// for any other id.
bool message_spec(uint32_t msgid, uint8_t* crc_extra, std::size_t* payload_len);

}  // namespace kestrel::mavlink

// The Foxglove WebSocket protocol (subprotocol foxglove.websocket.v1), the
// part a live ROS 2 data source needs: serverInfo, advertise, subscribe /
// unsubscribe, binary message data. Written from the protocol's published
// specification (github.com/foxglove/ws-protocol, docs/spec.md) and checked in
// ctest against the npm client @foxglove/ws-protocol (docs/ros2.md).
//
// The client's messages come from the network: parse_client_message() is a
// pure function over untrusted bytes with every size bounded (fuzzed by
// tests/fuzz/fuzz_foxglove_client.cpp).
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

namespace kestrel::foxglove {

inline constexpr const char* kSubprotocol = "foxglove.websocket.v1";
// A client message is a small JSON object: a few subscriptions. Bigger is refused.
inline constexpr size_t kMaxClientMessageBytes = 16 * 1024;
inline constexpr size_t kMaxIdsPerMessage = 256;

struct Channel {
  uint32_t id = 0;
  std::string topic;
  std::string encoding = "cdr";
  std::string schema_name;  // "nav_msgs/msg/Odometry"
  std::string schema;       // the ros2msg text
  std::string schema_encoding = "ros2msg";
};

struct ClientMessage {
  enum class Op { kSubscribe, kUnsubscribe };
  Op op = Op::kSubscribe;
  std::vector<std::pair<uint32_t, uint32_t>> subscribe;  // (subscription id, channel id)
  std::vector<uint32_t> unsubscribe;                     // subscription ids
};

// A text frame from a client. Returns "" and fills `out`, or the error, naming
// the field ("subscriptions[2].channelId: expected an unsigned 32-bit integer").
// Ops the server does not offer (advertise, publish, parameters, services)
// are errors too: the server announced no such capability.
std::string parse_client_message(const char* text, size_t n, ClientMessage& out);

// The server's text frames.
std::string server_info_json(const std::string& name, const std::string& session_id);
std::string advertise_json(const std::vector<Channel>& channels);
std::string status_json(int level, const std::string& message);  // level 0 info, 1 warning, 2 error

// A binary Message Data frame: opcode 0x01, subscription id (u32 LE),
// receive timestamp [ns] (u64 LE), the payload.
void message_data_frame(uint32_t subscription_id, uint64_t t_ns, const uint8_t* payload, size_t n,
                        std::string& out);

}  // namespace kestrel::foxglove

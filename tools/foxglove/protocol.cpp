#include "kestrel/foxglove/protocol.hpp"

#include <cstring>
#include <nlohmann/json.hpp>

namespace kestrel::foxglove {
namespace {

using json = nlohmann::json;

bool u32_of(const json& v, uint32_t& out) {
  if (!v.is_number_unsigned() && !v.is_number_integer()) return false;
  if (v.is_number_integer() && v.get<int64_t>() < 0) return false;
  const uint64_t u = v.get<uint64_t>();
  if (u > 0xFFFFFFFFull) return false;
  out = static_cast<uint32_t>(u);
  return true;
}

void put_le(std::string& out, uint64_t v, int bytes) {
  for (int k = 0; k < bytes; ++k) out.push_back(static_cast<char>(v >> (8 * k)));
}

}  // namespace

std::string parse_client_message(const char* text, size_t n, ClientMessage& out) {
  out = ClientMessage{};
  if (n > kMaxClientMessageBytes) {
    return "message of " + std::to_string(n) + " bytes (at most " + std::to_string(kMaxClientMessageBytes) +
           ")";
  }
  const json j = json::parse(text, text + n, nullptr, false);
  if (j.is_discarded()) return "not JSON";
  if (!j.is_object()) return "expected a JSON object";
  const auto op = j.find("op");
  if (op == j.end() || !op->is_string()) return "op: missing or not a string";
  const std::string o = op->get<std::string>();
  if (o == "subscribe") {
    out.op = ClientMessage::Op::kSubscribe;
    const auto s = j.find("subscriptions");
    if (s == j.end() || !s->is_array()) return "subscriptions: missing or not an array";
    if (s->size() > kMaxIdsPerMessage) {
      return "subscriptions: " + std::to_string(s->size()) + " entries (at most " +
             std::to_string(kMaxIdsPerMessage) + ")";
    }
    for (size_t i = 0; i < s->size(); ++i) {
      const json& e = (*s)[i];
      const std::string where = "subscriptions[" + std::to_string(i) + "]";
      if (!e.is_object()) return where + ": expected an object";
      uint32_t id = 0, channel = 0;
      const auto a = e.find("id"), c = e.find("channelId");
      if (a == e.end() || !u32_of(*a, id)) return where + ".id: expected an unsigned 32-bit integer";
      if (c == e.end() || !u32_of(*c, channel))
        return where + ".channelId: expected an unsigned 32-bit integer";
      out.subscribe.emplace_back(id, channel);
    }
    return "";
  }
  if (o == "unsubscribe") {
    out.op = ClientMessage::Op::kUnsubscribe;
    const auto s = j.find("subscriptionIds");
    if (s == j.end() || !s->is_array()) return "subscriptionIds: missing or not an array";
    if (s->size() > kMaxIdsPerMessage) {
      return "subscriptionIds: " + std::to_string(s->size()) + " entries (at most " +
             std::to_string(kMaxIdsPerMessage) + ")";
    }
    for (size_t i = 0; i < s->size(); ++i) {
      uint32_t id = 0;
      if (!u32_of((*s)[i], id))
        return "subscriptionIds[" + std::to_string(i) + "]: expected an unsigned 32-bit integer";
      out.unsubscribe.push_back(id);
    }
    return "";
  }
  // Cut what is echoed: the op came from the network.
  return "op: '" + o.substr(0, 40) + "' not offered by this server";
}

std::string server_info_json(const std::string& name, const std::string& session_id) {
  return json{{"op", "serverInfo"},
              {"name", name},
              {"capabilities", json::array()},
              {"supportedEncodings", json::array()},
              {"metadata", json::object()},
              {"sessionId", session_id}}
      .dump();
}

std::string advertise_json(const std::vector<Channel>& channels) {
  json a = json::array();
  for (const Channel& c : channels) {
    a.push_back({{"id", c.id},
                 {"topic", c.topic},
                 {"encoding", c.encoding},
                 {"schemaName", c.schema_name},
                 {"schema", c.schema},
                 {"schemaEncoding", c.schema_encoding}});
  }
  return json{{"op", "advertise"}, {"channels", a}}.dump();
}

std::string status_json(int level, const std::string& message) {
  return json{{"op", "status"}, {"level", level}, {"message", message}}.dump();
}

void message_data_frame(uint32_t subscription_id, uint64_t t_ns, const uint8_t* payload, size_t n,
                        std::string& out) {
  out.clear();
  out.reserve(13 + n);
  out.push_back(0x01);
  put_le(out, subscription_id, 4);
  put_le(out, t_ns, 8);
  out.append(reinterpret_cast<const char*>(payload), n);
}

}  // namespace kestrel::foxglove

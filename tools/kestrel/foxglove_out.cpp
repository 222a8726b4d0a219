#include "kestrel/foxglove_out.hpp"

#include <cstdio>
#include <stdexcept>

#include "kestrel/commands.hpp"
#include "kestrel/drivers/ros2_msgs.hpp"

namespace kestrel::cli {
namespace {

std::vector<foxglove::Channel> channels() {
  std::vector<foxglove::Channel> c;
  for (int i = 0; i < kRos2Topics; ++i) {
    const Ros2TopicInfo& t = ros2_topic_info(static_cast<Ros2Topic>(i));
    foxglove::Channel ch;
    ch.topic = t.topic;
    ch.schema_name = t.type;
    ch.schema = drivers::ros2::schema_text(t.type);
    c.push_back(ch);
  }
  return c;  // ids are the index: Ros2Topic's value
}

}  // namespace

FoxgloveSink::FoxgloveSink(const foxglove::ServerOptions& opt) : server_(opt, channels()), out_(*this) {}

void FoxgloveSink::publish(Ros2Topic topic, int64_t t_ns, const std::vector<uint8_t>& cdr) {
  server_.publish(static_cast<uint32_t>(topic), static_cast<uint64_t>(t_ns), cdr.data(), cdr.size());
}

std::shared_ptr<FoxgloveSink> add_foxglove(ReplayOptions& opt, const std::string& endpoint,
                                           double map_points_rate_hz, double wait_s) {
  if (endpoint.empty()) return nullptr;
  foxglove::ServerOptions so;
  try {
    foxglove::parse_endpoint(endpoint, so);
  } catch (const std::invalid_argument& e) {
    throw UsageError(e.what());
  }
  auto f = std::make_shared<FoxgloveSink>(so);
  f->server().start();
  std::printf("foxglove: ws://%s:%u (foxglove.websocket.v1): open it in Foxglove with \"Open connection\"\n",
              so.address.c_str(), static_cast<unsigned>(f->server().port()));
  std::fflush(stdout);
  connect_ros2_output(opt, std::shared_ptr<Ros2Output>(f, &f->output()), map_points_rate_hz);
  if (wait_s > 0 && !f->server().wait_for_client(static_cast<int64_t>(wait_s * 1e9)))
    std::printf("foxglove: no client after %.1f s, starting anyway\n", wait_s);
  return f;
}

}  // namespace kestrel::cli

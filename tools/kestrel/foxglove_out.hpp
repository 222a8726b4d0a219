// `kestrel replay|run --foxglove [ADDR:]PORT`: the topics of ros2_topics.hpp
// served live over the Foxglove WebSocket protocol (tools/foxglove,
// docs/ros2.md). Fed from ReplayOptions' callbacks on the output thread;
// the server's own thread does the sending, so nothing waits for a client.
#pragma once

#include <memory>
#include <string>

#include "kestrel/foxglove/server.hpp"
#include "kestrel/ros2_topics.hpp"

namespace kestrel::cli {

class FoxgloveSink final : public Ros2Sink {
 public:
  explicit FoxgloveSink(const foxglove::ServerOptions& opt);
  void publish(Ros2Topic topic, int64_t t_ns, const std::vector<uint8_t>& cdr) override;
  foxglove::Server& server() { return server_; }
  Ros2Output& output() { return out_; }

 private:
  foxglove::Server server_;
  Ros2Output out_;
};

// Starts the server at `endpoint` ("" : none) and chains it onto opt's
// callbacks; waits up to wait_s for a client first. Prints where it listens.
// Throws UsageError for a bad endpoint, std::runtime_error when it cannot listen.
std::shared_ptr<FoxgloveSink> add_foxglove(ReplayOptions& opt, const std::string& endpoint,
                                           double map_points_rate_hz, double wait_s);

}  // namespace kestrel::cli

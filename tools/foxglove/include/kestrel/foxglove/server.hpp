// `--foxglove [ADDR:]PORT`: a Foxglove WebSocket server (protocol.hpp) on a
// thread of its own (kst-foxglove, SCHED_OTHER), built on websocketpp's asio
// transport as the viewer is. publish() is called from the output thread
// (never a real-time thread): it copies the message into a queue bounded in
// bytes and wakes the server thread; a full queue drops and counts. A client
// whose socket has more than max_client_backlog_bytes queued gets no
// messages until it drains (dropped and counted), so a slow client never
// holds anyone back.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/foxglove/protocol.hpp"

namespace kestrel::foxglove {

struct ServerOptions {
  std::string address = "0.0.0.0";
  uint16_t port = 0;  // 0: any free port (port() tells which)
  int max_clients = 4;
  size_t max_queue_bytes = 16u << 20;          // publish() -> server thread
  size_t max_client_backlog_bytes = 4u << 20;  // per client socket
  std::string name = "kestrel";
};

// "[ADDR:]PORT" into opt.address / opt.port; throws std::invalid_argument quoting the text.
void parse_endpoint(const std::string& text, ServerOptions& opt);

struct ServerStats {
  uint64_t clients = 0, clients_refused = 0;
  uint64_t bad_handshakes = 0;     // no foxglove.websocket.v1 subprotocol offered
  uint64_t handshakes_failed = 0;  // not HTTP, timed out, closed early
  uint64_t protocol_errors = 0;    // malformed WebSocket frames (or over the size; closed)
  uint64_t bad_messages = 0;       // client messages refused by parse_client_message, or binary
  uint64_t subscriptions = 0, unsubscriptions = 0;
  uint64_t published = 0;            // messages handed to publish()
  uint64_t dropped_queue = 0;        // publish() found the queue full
  uint64_t dropped_slow_client = 0;  // a subscribed client's socket was not draining
  uint64_t messages_sent = 0, bytes_sent = 0;
  std::string last_error;  // the last bad message's error, for the summary
};

class Server {
 public:
  Server(const ServerOptions& opt, std::vector<Channel> channels);
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;
  // Binds and starts the thread; throws std::runtime_error naming the address.
  void start();
  void stop();  // idempotent
  uint16_t port() const;
  // Blocks until a client is connected or timeout_ns passed; true if one is.
  bool wait_for_client(int64_t timeout_ns);
  // Output thread: one message of channel `channel_id`, log time t_ns.
  void publish(uint32_t channel_id, uint64_t t_ns, const uint8_t* data, size_t n);
  ServerStats stats() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

std::string stats_summary(const ServerStats& s);

}  // namespace kestrel::foxglove

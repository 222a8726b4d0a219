#include "kestrel/foxglove/server.hpp"

#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <chrono>
#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <utility>
#include <websocketpp/config/asio_no_tls.hpp>
#include <websocketpp/server.hpp>

namespace kestrel::foxglove {
namespace {
using WsServer = websocketpp::server<websocketpp::config::asio>;
using Hdl = websocketpp::connection_hdl;

struct Pending {
  uint32_t channel;
  uint64_t t_ns;
  std::string data;
};
}  // namespace

void parse_endpoint(const std::string& text, ServerOptions& opt) {
  const size_t colon = text.rfind(':');
  const std::string port = colon == std::string::npos ? text : text.substr(colon + 1);
  char* end = nullptr;
  const long p = std::strtol(port.c_str(), &end, 10);
  if (port.empty() || *end != '\0' || p < 0 || p > 65535)
    throw std::invalid_argument("--foxglove '" + text + "': expected [ADDR:]PORT with PORT in 0..65535");
  if (colon != std::string::npos) {
    opt.address = text.substr(0, colon);
    if (opt.address.empty()) throw std::invalid_argument("--foxglove '" + text + "': empty address");
  }
  opt.port = static_cast<uint16_t>(p);
}

struct Server::Impl {
  ServerOptions opt;
  std::vector<Channel> channels;
  WsServer ws;
  std::thread thread;
  bool started = false;
  uint16_t port = 0;

  // Shared with the output thread.
  mutable std::mutex mutex;
  std::condition_variable client_cv;
  std::deque<Pending> queue;
  size_t queue_bytes = 0;
  bool flush_posted = false;
  bool stopping = false;
  ServerStats stats;

  // Under the mutex too: publish() and wait_for_client() look at the clients.
  struct Client {
    std::map<uint32_t, uint32_t> sub_by_id;  // subscription id -> channel id
  };
  std::map<Hdl, Client, std::owner_less<Hdl>> clients;
  std::string frame;

  void on_open(const Hdl& h) {
    std::lock_guard<std::mutex> l(mutex);
    if (static_cast<int>(clients.size()) >= opt.max_clients) {
      ++stats.clients_refused;
      websocketpp::lib::error_code ec;
      ws.close(h, websocketpp::close::status::try_again_later, "too many clients", ec);
      return;
    }
    clients[h];
    ++stats.clients;
    websocketpp::lib::error_code ec;
    ws.send(h, server_info_json(opt.name, std::to_string(::getpid())), websocketpp::frame::opcode::text, ec);
    ws.send(h, advertise_json(channels), websocketpp::frame::opcode::text, ec);
    client_cv.notify_all();
  }
  void on_close(const Hdl& h) {
    std::lock_guard<std::mutex> l(mutex);
    // websocketpp closes a connection whose frames break RFC 6455 or exceed
    // the message size; the close code says which.
    websocketpp::lib::error_code ec;
    const auto con = ws.get_con_from_hdl(h, ec);
    if (!ec) {
      const auto code = con->get_local_close_code();
      if (code == websocketpp::close::status::protocol_error ||
          code == websocketpp::close::status::message_too_big ||
          code == websocketpp::close::status::invalid_payload)
        ++stats.protocol_errors;
    }
    clients.erase(h);
  }
  void on_fail(Hdl h) {
    std::lock_guard<std::mutex> l(mutex);
    websocketpp::lib::error_code ec;
    const auto con = ws.get_con_from_hdl(std::move(h), ec);
    // A refused subprotocol is counted where it is refused (on_validate).
    if (!ec && con->get_ec() == websocketpp::error::make_error_code(websocketpp::error::rejected)) return;
    // Stopping cancels the accept websocketpp keeps pending: not a client's failure.
    if (stopping) return;
    ++stats.handshakes_failed;
    if (!ec) stats.last_error = "handshake failed: " + con->get_ec().message();
  }
  bool on_validate(Hdl h) {
    const auto con = ws.get_con_from_hdl(std::move(h));
    for (const std::string& p : con->get_requested_subprotocols()) {
      if (p == kSubprotocol) {
        con->select_subprotocol(kSubprotocol);
        return true;
      }
    }
    std::lock_guard<std::mutex> l(mutex);
    ++stats.bad_handshakes;
    return false;
  }
  void bad(const Hdl& h, const std::string& why) {
    // Called with the mutex held.
    ++stats.bad_messages;
    stats.last_error = why;
    websocketpp::lib::error_code ec;
    // A client flooding bad messages without reading its answers gets no more of them.
    const auto con = ws.get_con_from_hdl(h, ec);
    if (ec || con->get_buffered_amount() > opt.max_client_backlog_bytes) return;
    ws.send(h, status_json(2, why), websocketpp::frame::opcode::text, ec);
  }
  void on_message(const Hdl& h, const WsServer::message_ptr& msg) {
    std::lock_guard<std::mutex> l(mutex);
    const auto it = clients.find(h);
    if (it == clients.end()) return;
    if (msg->get_opcode() != websocketpp::frame::opcode::text) {
      bad(h, "binary client messages (client publish) are not offered by this server");
      return;
    }
    const std::string& p = msg->get_payload();
    ClientMessage m;
    const std::string err = parse_client_message(p.data(), p.size(), m);
    if (!err.empty()) {
      bad(h, err);
      return;
    }
    if (m.op == ClientMessage::Op::kSubscribe) {
      for (const auto& [id, channel] : m.subscribe) {
        if (channel >= channels.size()) {
          bad(h, "subscribe: channel " + std::to_string(channel) + " was not advertised");
          continue;
        }
        if (it->second.sub_by_id.size() >= kMaxIdsPerMessage && !it->second.sub_by_id.count(id)) {
          bad(h, "subscribe: more than " + std::to_string(kMaxIdsPerMessage) + " subscriptions");
          continue;
        }
        it->second.sub_by_id[id] = channel;
        ++stats.subscriptions;
      }
    } else {
      for (uint32_t id : m.unsubscribe) stats.unsubscriptions += it->second.sub_by_id.erase(id);
    }
  }
  // Server thread: everything queued, to every subscriber with room.
  void flush() {
    std::deque<Pending> q;
    {
      std::lock_guard<std::mutex> l(mutex);
      q.swap(queue);
      queue_bytes = 0;
      flush_posted = false;
    }
    for (const Pending& m : q) {
      std::lock_guard<std::mutex> l(mutex);
      for (auto& [h, c] : clients) {
        for (const auto& [sub, channel] : c.sub_by_id) {
          if (channel != m.channel) continue;
          websocketpp::lib::error_code ec;
          const auto con = ws.get_con_from_hdl(h, ec);
          if (ec) continue;
          if (con->get_buffered_amount() > opt.max_client_backlog_bytes) {
            ++stats.dropped_slow_client;
            continue;
          }
          message_data_frame(sub, m.t_ns, reinterpret_cast<const uint8_t*>(m.data.data()), m.data.size(),
                             frame);
          ws.send(h, frame, websocketpp::frame::opcode::binary, ec);
          if (!ec) {
            ++stats.messages_sent;
            stats.bytes_sent += frame.size();
          }
        }
      }
    }
  }
};

Server::Server(const ServerOptions& opt, std::vector<Channel> channels) : impl_(std::make_unique<Impl>()) {
  impl_->opt = opt;
  impl_->channels = std::move(channels);
  for (size_t i = 0; i < impl_->channels.size(); ++i) impl_->channels[i].id = static_cast<uint32_t>(i);
}

Server::~Server() { stop(); }

void Server::start() {
  Impl& m = *impl_;
  m.ws.clear_access_channels(websocketpp::log::alevel::all);
  m.ws.clear_error_channels(websocketpp::log::elevel::all);
  m.ws.init_asio();
  m.ws.set_reuse_addr(true);
  m.ws.set_max_message_size(kMaxClientMessageBytes);
  m.ws.set_validate_handler([&m](const Hdl& h) { return m.on_validate(h); });
  m.ws.set_open_handler([&m](const Hdl& h) { m.on_open(h); });
  m.ws.set_close_handler([&m](const Hdl& h) { m.on_close(h); });
  m.ws.set_fail_handler([&m](const Hdl& h) { m.on_fail(h); });
  m.ws.set_message_handler([&m](const Hdl& h, const WsServer::message_ptr& msg) { m.on_message(h, msg); });
  websocketpp::lib::error_code ec;
  m.ws.listen(m.opt.address, std::to_string(m.opt.port), ec);
  if (ec) {
    throw std::runtime_error("--foxglove: cannot listen on " + m.opt.address + ":" +
                             std::to_string(m.opt.port) + ": " + ec.message());
  }
  m.ws.start_accept(ec);
  if (ec) throw std::runtime_error("--foxglove: cannot accept on " + m.opt.address + ": " + ec.message());
  boost::system::error_code aec;
  m.port = m.ws.get_local_endpoint(aec).port();
  m.thread = std::thread([&m] {
    pthread_setname_np(pthread_self(), "kst-foxglove");
    // Below the pipeline: a busy client must not take CPU from tracking.
    setpriority(PRIO_PROCESS, static_cast<id_t>(::syscall(SYS_gettid)), 10);
    m.ws.run();
  });
  m.started = true;
}

void Server::stop() {
  Impl& m = *impl_;
  if (!m.started) return;
  m.started = false;
  boost::asio::post(m.ws.get_io_service(), [&m] {
    m.flush();
    {
      std::lock_guard<std::mutex> l(m.mutex);
      m.stopping = true;
    }
    websocketpp::lib::error_code ec;
    m.ws.stop_listening(ec);
    std::vector<Hdl> hs;
    {
      std::lock_guard<std::mutex> l(m.mutex);
      for (auto& [h, c] : m.clients) hs.push_back(h);
    }
    for (const Hdl& h : hs) m.ws.close(h, websocketpp::close::status::going_away, "replay finished", ec);
  });
  // The closing handshakes finish or time out, then run() returns.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(2);
  while (std::chrono::steady_clock::now() < deadline) {
    {
      std::lock_guard<std::mutex> l(m.mutex);
      if (m.clients.empty()) break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  m.ws.stop();
  if (m.thread.joinable()) m.thread.join();
}

uint16_t Server::port() const { return impl_->port; }

bool Server::wait_for_client(int64_t timeout_ns) {
  std::unique_lock<std::mutex> l(impl_->mutex);
  return impl_->client_cv.wait_for(l, std::chrono::nanoseconds(timeout_ns),
                                   [this] { return !impl_->clients.empty(); });
}

void Server::publish(uint32_t channel_id, uint64_t t_ns, const uint8_t* data, size_t n) {
  Impl& m = *impl_;
  bool post = false;
  {
    std::lock_guard<std::mutex> l(m.mutex);
    ++m.stats.published;
    if (m.clients.empty()) return;  // nobody to send to: nothing kept
    if (m.queue_bytes + n > m.opt.max_queue_bytes) {
      ++m.stats.dropped_queue;
      return;
    }
    m.queue.push_back({channel_id, t_ns, std::string(reinterpret_cast<const char*>(data), n)});
    m.queue_bytes += n;
    post = !m.flush_posted;
    m.flush_posted = true;
  }
  if (post) boost::asio::post(m.ws.get_io_service(), [&m] { m.flush(); });
}

ServerStats Server::stats() const {
  std::lock_guard<std::mutex> l(impl_->mutex);
  return impl_->stats;
}

std::string stats_summary(const ServerStats& s) {
  std::string out = "foxglove: " + std::to_string(s.clients) + " client(s), " +
                    std::to_string(s.messages_sent) + " messages sent (" +
                    std::to_string(s.bytes_sent / 1000) + " kB), dropped " + std::to_string(s.dropped_queue) +
                    " (queue full) + " + std::to_string(s.dropped_slow_client) + " (slow client)";
  if (s.clients_refused + s.bad_handshakes + s.handshakes_failed + s.protocol_errors + s.bad_messages > 0) {
    out += "; refused " + std::to_string(s.clients_refused) + " client(s), " +
           std::to_string(s.bad_handshakes) + " handshake(s) without the subprotocol, " +
           std::to_string(s.handshakes_failed) + " failed handshake(s), " +
           std::to_string(s.protocol_errors) + " protocol error(s), " + std::to_string(s.bad_messages) +
           " bad message(s)" + (s.last_error.empty() ? "" : " (last: " + s.last_error + ")");
  }
  return out + "\n";
}

}  // namespace kestrel::foxglove

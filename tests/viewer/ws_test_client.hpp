// A deliberately small HTTP / WebSocket client over POSIX sockets, so the
// viewer's tests can send what no well-behaved client would: unmasked or
// reserved frames, oversized lengths, nothing at all.
#pragma once

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstdint>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "kestrel/rt/clock.hpp"

namespace kestrel::viewer_test {

// -1 when the connection was refused. rcvbuf > 0 shrinks the receive buffer
// before connecting (a client that reads nothing then stalls its sender sooner).
inline int connect_local(uint16_t port, int rcvbuf = 0) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return -1;
  if (rcvbuf > 0) ::setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(port);
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) {
    ::close(fd);
    return -1;
  }
  return fd;
}

inline bool send_all(int fd, const std::string& data) {
  size_t off = 0;
  while (off < data.size()) {
    const ssize_t n = ::send(fd, data.data() + off, data.size() - off, MSG_NOSIGNAL);
    if (n <= 0) return false;
    off += static_cast<size_t>(n);
  }
  return true;
}

// Reads what arrives within timeout_ms (until the peer closes, or `until`
// is found when given). closed: the peer closed (or reset) the connection.
inline std::string recv_for(int fd, int timeout_ms, bool* closed = nullptr, const std::string& until = "") {
  std::string out;
  if (closed != nullptr) *closed = false;
  const int64_t deadline = rt::now_ns() + static_cast<int64_t>(timeout_ms) * 1'000'000;
  char buf[65536];
  while (rt::now_ns() < deadline) {
    pollfd p{fd, POLLIN, 0};
    const int left_ms = static_cast<int>((deadline - rt::now_ns()) / 1'000'000);
    if (::poll(&p, 1, left_ms > 0 ? left_ms : 0) <= 0) continue;
    const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
    if (n <= 0) {
      if (closed != nullptr) *closed = true;
      break;
    }
    out.append(buf, static_cast<size_t>(n));
    if (!until.empty() && out.find(until) != std::string::npos) break;
  }
  return out;
}

// "HTTP/1.1 404 Not Found" -> 404; 0 when nothing parsable came back.
inline int http_status(const std::string& response) {
  if (response.compare(0, 5, "HTTP/") != 0) return 0;
  const size_t sp = response.find(' ');
  return sp == std::string::npos ? 0 : std::atoi(response.c_str() + sp + 1);
}

inline std::string http_get(uint16_t port, const std::string& path, const std::string& method = "GET") {
  const int fd = connect_local(port);
  if (fd < 0) return {};
  send_all(fd, method + " " + path + " HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n");
  const std::string r = recv_for(fd, 3000);
  ::close(fd);
  return r;
}

// A masked client frame (RFC 6455 5.2): fin, opcode, payload.
inline std::string client_frame(uint8_t first_byte, const std::string& payload, bool masked = true) {
  std::string f(1, static_cast<char>(first_byte));
  const size_t n = payload.size();
  const uint8_t mask_bit = masked ? 0x80 : 0;
  if (n < 126) {
    f += static_cast<char>(mask_bit | n);
  } else if (n < 65536) {
    f += static_cast<char>(mask_bit | 126);
    f += static_cast<char>(n >> 8);
    f += static_cast<char>(n & 0xff);
  } else {
    f += static_cast<char>(mask_bit | 127);
    for (int i = 7; i >= 0; --i) f += static_cast<char>((static_cast<uint64_t>(n) >> (8 * i)) & 0xff);
  }
  const char key[4] = {0x12, 0x34, 0x56, 0x78};
  if (masked) f.append(key, 4);
  for (size_t i = 0; i < n; ++i) f += static_cast<char>(payload[i] ^ (masked ? key[i % 4] : 0));
  return f;
}

struct WsClient {
  int fd = -1;
  int status = 0;       // HTTP status of the handshake (101 when upgraded)
  std::string pending;  // bytes after the handshake response

  bool open(uint16_t port, const std::string& path = "/ws", int rcvbuf = 0) {
    fd = connect_local(port, rcvbuf);
    if (fd < 0) return false;
    send_all(fd, "GET " + path +
                     " HTTP/1.1\r\nHost: test\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                     "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n");
    std::string r = recv_for(fd, 3000, nullptr, "\r\n\r\n");
    const size_t end = r.find("\r\n\r\n");
    status = http_status(r);
    if (end != std::string::npos) pending = r.substr(end + 4);
    return status == 101;
  }
  // Next server message (server frames are unmasked); false on close/timeout.
  bool next(int timeout_ms, uint8_t* opcode, std::string* payload) {
    const int64_t deadline = rt::now_ns() + static_cast<int64_t>(timeout_ms) * 1'000'000;
    for (;;) {
      if (pending.size() >= 2) {
        const uint8_t b1 = static_cast<uint8_t>(pending[1]);
        size_t len = b1 & 0x7f, off = 2;
        if (len == 126 && pending.size() >= 4) {
          len = (static_cast<uint8_t>(pending[2]) << 8) | static_cast<uint8_t>(pending[3]);
          off = 4;
        } else if (len == 127 && pending.size() >= 10) {
          len = 0;
          for (int i = 0; i < 8; ++i) len = (len << 8) | static_cast<uint8_t>(pending[2 + i]);
          off = 10;
        } else if (len >= 126) {
          off = 0;  // header incomplete
        }
        if (off > 0 && pending.size() >= off + len) {
          *opcode = static_cast<uint8_t>(pending[0]) & 0x0f;
          *payload = pending.substr(off, len);
          pending.erase(0, off + len);
          return true;
        }
      }
      const int left = static_cast<int>((deadline - rt::now_ns()) / 1'000'000);
      if (left <= 0) return false;
      bool closed = false;
      const std::string more = recv_for(fd, std::min(left, 200), &closed);
      pending += more;
      if (closed && more.empty()) return false;
    }
  }
  // True when the server closed the connection (a close frame or EOF) within timeout_ms.
  bool closed_within(int timeout_ms) {
    const int64_t deadline = rt::now_ns() + static_cast<int64_t>(timeout_ms) * 1'000'000;
    while (rt::now_ns() < deadline) {
      uint8_t op = 0;
      std::string p;
      if (next(100, &op, &p)) {
        if (op == 0x8) return true;
        continue;
      }
      bool closed = false;
      pending += recv_for(fd, 50, &closed);
      if (closed) return true;
    }
    return false;
  }
  void close() {
    if (fd >= 0) ::close(fd);
    fd = -1;
  }
  ~WsClient() { close(); }
};

}  // namespace kestrel::viewer_test

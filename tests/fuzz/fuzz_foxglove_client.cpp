// The Foxglove server's client-message parser (tools/foxglove): a text frame
// from the network. Invariants: an accepted message never holds more ids than
// the bound, and parsing is the same the second time (no hidden state); a
// refused one names why.
// Seeds: what @foxglove/ws-protocol's client sends (subscribe, unsubscribe),
// and the ops this server does not offer.
#include <cstdlib>
#include <cstring>

#include "fuzz_target.hpp"
#include "kestrel/foxglove/protocol.hpp"

namespace fg = kestrel::foxglove;

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  fg::ClientMessage m, again;
  const char* text = reinterpret_cast<const char*>(data);
  const std::string err = fg::parse_client_message(text, size, m);
  if (err.empty()) {
    if (m.subscribe.size() > fg::kMaxIdsPerMessage || m.unsubscribe.size() > fg::kMaxIdsPerMessage)
      std::abort();
    if (size > fg::kMaxClientMessageBytes) std::abort();
  }
  if (fg::parse_client_message(text, size, again) != err) std::abort();
  if (again.subscribe != m.subscribe || again.unsubscribe != m.unsubscribe) std::abort();
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  write_file(dir + "/subscribe.json",
             R"({"op":"subscribe","subscriptions":[{"id":0,"channelId":0},{"id":1,"channelId":3}]})");
  write_file(dir + "/unsubscribe.json", R"({"op":"unsubscribe","subscriptionIds":[0,1]})");
  write_file(
      dir + "/advertise.json",
      R"({"op":"advertise","channels":[{"id":1,"topic":"/x","encoding":"cdr","schemaName":"a/msg/B"}]})");
  write_file(dir + "/bad_id.json",
             R"({"op":"subscribe","subscriptions":[{"id":-1,"channelId":4294967296}]})");
  return 4;
}

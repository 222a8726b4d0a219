// What Rosbag2Reader needs of a rosbag2 storage file, MCAP or SQLite3: the
// channels with their message types, every message once in file order, and a
// message's payload again by reference (images are decoded only when
// replayed). Private to drivers/rosbag2.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "kestrel/drivers/log_source.hpp"
#include "kestrel/drivers/mcap.hpp"

namespace kestrel::drivers::rosbag2_store {

class MessageStore {
 public:
  using OnMessage = std::function<void(const mcap::MessageRef&, const uint8_t* data, size_t size)>;
  virtual ~MessageStore() = default;
  // Every message in storage order; damage ends the scan with a problem (read up to it).
  virtual size_t scan(const OnMessage& on_message) = 0;
  virtual bool load(const mcap::MessageRef& m, std::vector<uint8_t>& scratch, const uint8_t*& data) = 0;
  virtual const std::map<uint16_t, mcap::SchemaRec>& schemas() const = 0;
  virtual const std::map<uint16_t, mcap::ChannelRec>& channels() const = 0;
  virtual const std::map<std::string, std::map<std::string, std::string>>& metadata() const = 0;
  virtual std::vector<LogProblem>& problems() = 0;
};

std::unique_ptr<MessageStore> open_mcap(const std::string& path, const mcap::ReaderOptions& options);
// rosbag2's sqlite3 storage plugin: tables topics(id, name, type,
// serialization_format, ...) and messages(id, topic_id, timestamp, data),
// opened read-only. Throws std::runtime_error naming the file when it is not
// such a database.
std::unique_ptr<MessageStore> open_sqlite3(const std::string& path);
// The file starts with SQLite's 16-byte header string.
bool is_sqlite3_file(const std::string& path);

}  // namespace kestrel::drivers::rosbag2_store

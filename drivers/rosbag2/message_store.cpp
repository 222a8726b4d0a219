// MCAP and SQLite3 behind one interface for Rosbag2Reader (message_store.hpp).
#include "message_store.hpp"

#include <sqlite3.h>

#include <cstring>
#include <fstream>
#include <set>
#include <stdexcept>

namespace kestrel::drivers::rosbag2_store {
namespace {

class McapStore : public MessageStore {
 public:
  McapStore(const std::string& path, const mcap::ReaderOptions& o) : r_(path, o) {}
  size_t scan(const OnMessage& f) override { return r_.scan(f); }
  bool load(const mcap::MessageRef& m, std::vector<uint8_t>& scratch, const uint8_t*& data) override {
    return r_.load(m, scratch, data);
  }
  const std::map<uint16_t, mcap::SchemaRec>& schemas() const override { return r_.schemas(); }
  const std::map<uint16_t, mcap::ChannelRec>& channels() const override { return r_.channels(); }
  const std::map<std::string, std::map<std::string, std::string>>& metadata() const override {
    return r_.metadata();
  }
  std::vector<LogProblem>& problems() override { return r_.problems(); }

 private:
  mcap::Reader r_;
};

// One prepared statement, finalised however the scope ends.
struct Stmt {
  sqlite3_stmt* s = nullptr;
  ~Stmt() { sqlite3_finalize(s); }
};

class SqliteStore : public MessageStore {
 public:
  explicit SqliteStore(const std::string& path) : path_(path) {
    if (sqlite3_open_v2(path.c_str(), &db_, SQLITE_OPEN_READONLY, nullptr) != SQLITE_OK) {
      const std::string why = db_ ? sqlite3_errmsg(db_) : "out of memory";
      sqlite3_close(db_);
      throw std::runtime_error(path + ": cannot open as SQLite3: " + why);
    }
    // A file cut short (a recorder killed mid-write, a full disk) still says
    // in its header how many pages it had, and SQLite refuses such a file at
    // the first statement. With the schema marked writable it takes the file's
    // real size instead and reads every page that is there, failing only at a
    // missing one: read up to the damage. The connection is read-only, so
    // nothing can be written through it either way.
    sqlite3_db_config(db_, SQLITE_DBCONFIG_WRITABLE_SCHEMA, 1, nullptr);
    try {
      read_topics();
      prepare(load_, "SELECT data FROM messages WHERE id = ?1");
    } catch (...) {
      sqlite3_finalize(load_.s);
      load_.s = nullptr;
      sqlite3_close(db_);
      throw;
    }
  }
  ~SqliteStore() override {
    sqlite3_finalize(load_.s);
    load_.s = nullptr;
    sqlite3_close(db_);
  }

  size_t scan(const OnMessage& f) override {
    // Row order is the order rosbag2 inserted them (receive order); the reader
    // sorts by stamp. A corrupt page ends the scan there: what came before stays.
    Stmt st;
    prepare(st, "SELECT id, topic_id, timestamp, data FROM messages ORDER BY id");
    std::map<uint16_t, uint32_t> seq;
    size_t n = 0;
    int64_t last_id = 0;
    int rc;
    while ((rc = sqlite3_step(st.s)) == SQLITE_ROW) {
      const int64_t id = sqlite3_column_int64(st.s, 0);
      last_id = id;
      const int64_t topic = sqlite3_column_int64(st.s, 1);
      const int64_t t = sqlite3_column_int64(st.s, 2);
      const auto* data = static_cast<const uint8_t*>(sqlite3_column_blob(st.s, 3));
      const int size = sqlite3_column_bytes(st.s, 3);
      const std::string where = path_ + ": messages row " + std::to_string(id);
      const auto ch = topic_ids_.find(topic);
      if (ch == topic_ids_.end()) {
        if (unknown_topics_.insert(topic).second) {
          problem(where, "bad-row",
                  "topic_id " + std::to_string(topic) + " is not in the topics table; skipped");
        }
        continue;
      }
      if (t < 0) {
        problem(where, "bad-row", "negative timestamp " + std::to_string(t) + "; skipped");
        continue;
      }
      mcap::MessageRef m;
      m.channel_id = ch->second;
      m.sequence = seq[ch->second]++;
      m.log_time_ns = m.publish_time_ns = static_cast<uint64_t>(t);
      m.offset = static_cast<uint64_t>(id);
      m.size = static_cast<uint32_t>(size);
      static const uint8_t kEmpty = 0;
      f(m, data ? data : &kEmpty, static_cast<size_t>(size));
      ++n;
    }
    if (rc != SQLITE_DONE) {
      problem(path_ + ": messages after row " + std::to_string(last_id),
              rc == SQLITE_CORRUPT ? "truncated" : "bad-file",
              std::string("SQLite: ") + sqlite3_errmsg(db_) + "; read up to here");
    }
    return n;
  }

  bool load(const mcap::MessageRef& m, std::vector<uint8_t>& scratch, const uint8_t*& data) override {
    sqlite3_reset(load_.s);
    sqlite3_bind_int64(load_.s, 1, static_cast<sqlite3_int64>(m.offset));
    if (sqlite3_step(load_.s) != SQLITE_ROW) {
      problem(path_ + ": messages row " + std::to_string(m.offset), "bad-file",
              std::string("cannot read the message again: ") + sqlite3_errmsg(db_));
      return false;
    }
    const auto* p = static_cast<const uint8_t*>(sqlite3_column_blob(load_.s, 0));
    const size_t n = static_cast<size_t>(sqlite3_column_bytes(load_.s, 0));
    scratch.assign(p, p + (p ? n : 0));
    sqlite3_reset(load_.s);
    if (scratch.size() != m.size) {
      problem(path_ + ": messages row " + std::to_string(m.offset), "bad-file", "the message changed size");
      return false;
    }
    data = scratch.data();
    return true;
  }

  const std::map<uint16_t, mcap::SchemaRec>& schemas() const override { return schemas_; }
  const std::map<uint16_t, mcap::ChannelRec>& channels() const override { return channels_; }
  const std::map<std::string, std::map<std::string, std::string>>& metadata() const override {
    return metadata_;
  }
  std::vector<LogProblem>& problems() override { return problems_; }

 private:
  void prepare(Stmt& st, const char* sql) {
    if (sqlite3_prepare_v2(db_, sql, -1, &st.s, nullptr) != SQLITE_OK)
      throw std::runtime_error(path_ + ": not a rosbag2 SQLite3 database (" + sqlite3_errmsg(db_) + ")");
  }
  void problem(std::string where, std::string kind, std::string detail) {
    problems_.push_back(LogProblem{std::move(where), std::move(kind), std::move(detail)});
  }
  // Every topic becomes a channel with a schema of its own (named by its
  // type, encoding ros2msg: the sqlite3 storage keeps no definitions).
  void read_topics() {
    Stmt st;
    prepare(st, "SELECT id, name, type, serialization_format FROM topics ORDER BY id");
    int rc;
    uint16_t next = 1;
    while ((rc = sqlite3_step(st.s)) == SQLITE_ROW) {
      auto text = [&st](int c) {
        const auto* p = sqlite3_column_text(st.s, c);
        return p ? std::string(reinterpret_cast<const char*>(p)) : std::string();
      };
      if (next == UINT16_MAX) {
        problem(path_ + ": topics", "unsupported", "more than 65534 topics; the rest ignored");
        break;
      }
      const uint16_t id = next++;
      topic_ids_[sqlite3_column_int64(st.s, 0)] = id;
      mcap::SchemaRec sc;
      sc.id = id;
      sc.name = text(2);
      sc.encoding = "ros2msg";
      schemas_[id] = sc;
      mcap::ChannelRec ch;
      ch.id = id;
      ch.schema_id = id;
      ch.topic = text(1);
      ch.message_encoding = text(3);
      channels_[id] = ch;
    }
    if (rc != SQLITE_DONE)
      throw std::runtime_error(path_ + ": topics table unreadable (" + sqlite3_errmsg(db_) + ")");
  }

  std::string path_;
  sqlite3* db_ = nullptr;
  Stmt load_;
  std::map<int64_t, uint16_t> topic_ids_;
  std::set<int64_t> unknown_topics_;
  std::map<uint16_t, mcap::SchemaRec> schemas_;
  std::map<uint16_t, mcap::ChannelRec> channels_;
  std::map<std::string, std::map<std::string, std::string>> metadata_;
  std::vector<LogProblem> problems_;
};

}  // namespace

std::unique_ptr<MessageStore> open_mcap(const std::string& path, const mcap::ReaderOptions& options) {
  return std::make_unique<McapStore>(path, options);
}

std::unique_ptr<MessageStore> open_sqlite3(const std::string& path) {
  return std::make_unique<SqliteStore>(path);
}

bool is_sqlite3_file(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  char m[16] = {};
  return f.read(m, 16) && std::memcmp(m, "SQLite format 3", 16) == 0;
}

}  // namespace kestrel::drivers::rosbag2_store

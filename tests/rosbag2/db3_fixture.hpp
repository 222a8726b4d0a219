// A rosbag2 sqlite3-storage bag made with libsqlite3 from an MCAP file's
// messages, in the layout of rosbag2's sqlite3 storage plugin (schema version 3:
// topics(id, name, type, serialization_format, offered_qos_profiles),
// messages(id, topic_id, timestamp, data)), with a metadata.yaml naming it.
// Topic ids start at 7 so a reader cannot rely on them matching MCAP channel
// ids. Used by tests/rosbag2 and the rosbag2 fuzz target's seeds.
#pragma once

#include <sqlite3.h>

#include <filesystem>
#include <fstream>
#include <stdexcept>
#include <string>

#include "kestrel/drivers/mcap.hpp"

namespace kestrel::test {

inline void write_db3_from_mcap(const std::string& mcap_path, const std::string& dir,
                                const std::string& name) {
  namespace mcap = drivers::mcap;
  std::filesystem::create_directories(dir);
  const std::string db_path = dir + "/" + name;
  std::filesystem::remove(db_path);
  sqlite3* db = nullptr;
  auto check = [&](int rc, int want, const char* what) {
    if (rc != want) throw std::runtime_error(db_path + ": " + what + ": " + (db ? sqlite3_errmsg(db) : "?"));
  };
  check(sqlite3_open(db_path.c_str(), &db), SQLITE_OK, "open");
  struct Closer {
    sqlite3* db;
    sqlite3_stmt* topic = nullptr;
    sqlite3_stmt* msg = nullptr;
    ~Closer() {
      sqlite3_finalize(topic);
      sqlite3_finalize(msg);
      sqlite3_close(db);
    }
  } c{db};
  check(sqlite3_exec(db,
                     "CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT NOT NULL);"
                     "INSERT INTO schema VALUES(3, 'humble');"
                     "CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL, "
                     "serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL);"
                     "CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, "
                     "timestamp INTEGER NOT NULL, data BLOB NOT NULL);"
                     "CREATE INDEX timestamp_idx ON messages (timestamp ASC);"
                     "BEGIN;",
                     nullptr, nullptr, nullptr),
        SQLITE_OK, "create tables");
  check(sqlite3_prepare_v2(db, "INSERT INTO topics VALUES(?1, ?2, ?3, 'cdr', '')", -1, &c.topic, nullptr),
        SQLITE_OK, "prepare topics");
  check(sqlite3_prepare_v2(db, "INSERT INTO messages(topic_id, timestamp, data) VALUES(?1, ?2, ?3)", -1,
                           &c.msg, nullptr),
        SQLITE_OK, "prepare messages");
  mcap::Reader r(mcap_path);
  bool topics_done = false;
  r.scan([&](const mcap::MessageRef& m, const uint8_t* data, size_t n) {
    if (!topics_done) {
      for (const auto& [id, ch] : r.channels()) {
        sqlite3_reset(c.topic);
        sqlite3_bind_int(c.topic, 1, id + 7);
        sqlite3_bind_text(c.topic, 2, ch.topic.c_str(), -1, SQLITE_TRANSIENT);
        sqlite3_bind_text(c.topic, 3, r.schemas().at(ch.schema_id).name.c_str(), -1, SQLITE_TRANSIENT);
        check(sqlite3_step(c.topic), SQLITE_DONE, "insert topic");
      }
      topics_done = true;
    }
    sqlite3_reset(c.msg);
    sqlite3_bind_int(c.msg, 1, m.channel_id + 7);
    sqlite3_bind_int64(c.msg, 2, static_cast<sqlite3_int64>(m.log_time_ns));
    sqlite3_bind_blob(c.msg, 3, data, static_cast<int>(n), SQLITE_TRANSIENT);
    check(sqlite3_step(c.msg), SQLITE_DONE, "insert message");
  });
  check(sqlite3_exec(db, "COMMIT;", nullptr, nullptr, nullptr), SQLITE_OK, "commit");
  std::ofstream meta(dir + "/metadata.yaml");
  meta << "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: sqlite3\n"
          "  relative_file_paths:\n    - "
       << name << "\n";
  if (!meta.flush()) throw std::runtime_error(dir + "/metadata.yaml: cannot write");
}

}  // namespace kestrel::test

// MCAP container (https://mcap.dev/spec), written from the specification:
// a writer that chunks (zstd, lz4 frame or none) with message indexes, chunk
// indexes, statistics, summary offsets and CRCs, and a reader that scans the
// data section record by record (so a file without a summary, or cut short,
// is read up to the damage) and fetches any message again later by location.
// Neither runs on a real-time thread: both allocate and do file I/O.
#pragma once

#include <cstdint>
#include <cstdio>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include "kestrel/drivers/log_source.hpp"

namespace kestrel::drivers::mcap {

inline constexpr uint8_t kMagic[8] = {0x89, 'M', 'C', 'A', 'P', 0x30, '\r', '\n'};

enum Op : uint8_t {
  kHeader = 0x01,
  kFooter = 0x02,
  kSchema = 0x03,
  kChannel = 0x04,
  kMessage = 0x05,
  kChunk = 0x06,
  kMessageIndex = 0x07,
  kChunkIndex = 0x08,
  kAttachment = 0x09,
  kAttachmentIndex = 0x0A,
  kStatistics = 0x0B,
  kMetadata = 0x0C,
  kMetadataIndex = 0x0D,
  kSummaryOffset = 0x0E,
  kDataEnd = 0x0F,
};

struct WriterOptions {
  std::string profile = "ros2";
  std::string library = "kestrel";
  std::string compression = "zstd";    // "zstd", "lz4" or "" (none)
  size_t chunk_size_bytes = 4u << 20;  // uncompressed records per chunk; 0 = unchunked
  int zstd_level = 1;
};

struct WriterStats {
  uint64_t messages = 0;
  uint64_t chunks = 0;
  uint64_t bytes = 0;  // file size after close()
};

// Throws std::runtime_error naming the file on any write failure.
class Writer {
 public:
  Writer() = default;
  ~Writer();
  Writer(const Writer&) = delete;
  Writer& operator=(const Writer&) = delete;

  void open(const std::string& path, const WriterOptions& options = {});
  uint16_t add_schema(const std::string& name, const std::string& encoding, const std::string& data);
  uint16_t add_channel(uint16_t schema_id, const std::string& topic, const std::string& message_encoding,
                       const std::map<std::string, std::string>& metadata = {});
  void write(uint16_t channel_id, uint64_t log_time_ns, uint64_t publish_time_ns, const uint8_t* data,
             size_t size);
  void add_metadata(const std::string& name, const std::map<std::string, std::string>& metadata);
  // Flushes the last chunk, writes DataEnd, the summary and the footer.
  void close();
  bool is_open() const { return f_ != nullptr; }
  const WriterStats& stats() const { return stats_; }

 private:
  struct Schema {
    uint16_t id;
    std::string name, encoding, data;
  };
  struct Channel {
    uint16_t id, schema_id;
    std::string topic, encoding;
    std::map<std::string, std::string> metadata;
  };
  void put(const std::vector<uint8_t>& bytes, bool data_section);
  void flush_chunk();

  std::FILE* f_ = nullptr;
  std::string path_;
  WriterOptions opt_;
  uint64_t pos_ = 0;
  uint32_t data_crc_ = 0;
  std::vector<Schema> schemas_;
  std::vector<Channel> channels_;
  std::vector<uint8_t> chunk_, rec_, packed_;
  uint64_t chunk_start_ = 0, chunk_end_ = 0;
  std::map<uint16_t, std::vector<std::pair<uint64_t, uint64_t>>>
      chunk_index_;  // channel -> (log_time, offset)
  std::vector<std::vector<uint8_t>> chunk_indexes_, metadata_indexes_;
  std::map<uint16_t, uint64_t> channel_counts_;
  uint64_t t_min_ = UINT64_MAX, t_max_ = 0;
  uint32_t metadata_count_ = 0;
  WriterStats stats_;
};

struct ReaderOptions {
  // Untrusted lengths: a chunk claiming more than this uncompressed is refused
  // (reported), so a corrupt header cannot make the reader allocate gigabytes.
  uint64_t max_chunk_bytes = 512ull << 20;
  uint64_t max_record_bytes = 512ull << 20;
};

struct SchemaRec {
  uint16_t id = 0;
  std::string name, encoding, data;
};
struct ChannelRec {
  uint16_t id = 0, schema_id = 0;
  std::string topic, message_encoding;
  std::map<std::string, std::string> metadata;
};
// Where a message is: in chunk `chunk` (index into the reader's chunks, -1 =
// top level) at `offset` bytes into the chunk's records (or the file).
struct MessageRef {
  uint16_t channel_id = 0;
  uint32_t sequence = 0;
  uint64_t log_time_ns = 0, publish_time_ns = 0;
  int32_t chunk = -1;
  uint64_t offset = 0;
  uint32_t size = 0;
};

class Reader {
 public:
  // A file, or (for the fuzzer) bytes in memory.
  explicit Reader(const std::string& path, const ReaderOptions& options = {});
  Reader(const uint8_t* data, size_t size, const ReaderOptions& options = {});
  ~Reader();
  Reader(const Reader&) = delete;
  Reader& operator=(const Reader&) = delete;

  // Reads the data section in file order, calling `on_message` for each
  // message (data valid during the call). Damage is recorded in problems()
  // and ends or skips what it must; returns the number of messages seen.
  size_t scan(const std::function<void(const MessageRef&, const uint8_t* data, size_t size)>& on_message);
  // The payload of a message met by scan(); false (and a problem) if it cannot be read again.
  bool load(const MessageRef& m, std::vector<uint8_t>& scratch, const uint8_t*& data);

  const std::map<uint16_t, SchemaRec>& schemas() const { return schemas_; }
  const std::map<uint16_t, ChannelRec>& channels() const { return channels_; }
  const std::map<std::string, std::map<std::string, std::string>>& metadata() const { return metadata_; }
  const std::string& profile() const { return profile_; }
  std::vector<LogProblem>& problems() { return problems_; }
  uint64_t chunk_count() const { return chunks_.size(); }

 private:
  struct Chunk {
    uint64_t data_offset{};  // file offset of the compressed records
    uint64_t compressed_size{}, uncompressed_size{};
    uint32_t crc{};
    std::string compression;
  };
  void problem(uint64_t at, const std::string& kind, const std::string& detail);
  bool read_at(uint64_t off, size_t n, uint8_t* out);
  bool decompress(const Chunk& c, uint64_t at, std::vector<uint8_t>& out);
  // Parses one record of `body` (opcode op); messages go to on_message.
  void record(uint8_t op, const uint8_t* body, uint64_t len, uint64_t at, int32_t chunk, uint64_t offset,
              const std::function<void(const MessageRef&, const uint8_t*, size_t)>* on_message, size_t& n);

  std::string name_;
  std::FILE* f_ = nullptr;
  uint64_t size_ = 0;
  ReaderOptions opt_;
  std::string profile_;
  std::map<uint16_t, SchemaRec> schemas_;
  std::map<uint16_t, ChannelRec> channels_;
  std::map<std::string, std::map<std::string, std::string>> metadata_;
  std::vector<Chunk> chunks_;
  std::vector<LogProblem> problems_;
  int32_t cached_chunk_ = -1;
  std::vector<uint8_t> cache_, compressed_;
};

}  // namespace kestrel::drivers::mcap

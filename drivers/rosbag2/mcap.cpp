// MCAP writer and reader (https://mcap.dev/spec). All integers little-endian;
// strings and byte arrays carry a uint32 length, chunk records a uint64 one.
#include "kestrel/drivers/mcap.hpp"

#include <lz4frame.h>
#include <zlib.h>
#include <zstd.h>

#include <cstring>
#include <stdexcept>

namespace kestrel::drivers::mcap {
namespace {

void u8(std::vector<uint8_t>& b, uint8_t v) { b.push_back(v); }
template <typename T>
void le(std::vector<uint8_t>& b, T v) {
  for (size_t i = 0; i < sizeof(T); ++i)
    b.push_back(static_cast<uint8_t>(static_cast<uint64_t>(v) >> (8 * i)));
}
void str(std::vector<uint8_t>& b, const std::string& s) {
  le<uint32_t>(b, static_cast<uint32_t>(s.size()));
  b.insert(b.end(), s.begin(), s.end());
}
void str_map(std::vector<uint8_t>& b, const std::map<std::string, std::string>& m) {
  std::vector<uint8_t> body;
  for (const auto& [k, v] : m) str(body, k), str(body, v);
  le<uint32_t>(b, static_cast<uint32_t>(body.size()));
  b.insert(b.end(), body.begin(), body.end());
}
// opcode + uint64 length + body
void record(std::vector<uint8_t>& out, uint8_t op, const std::vector<uint8_t>& body) {
  u8(out, op);
  le<uint64_t>(out, body.size());
  out.insert(out.end(), body.begin(), body.end());
}
uint32_t crc(uint32_t c, const uint8_t* p, size_t n) {
  while (n > 0) {
    const uInt k = static_cast<uInt>(std::min<size_t>(n, 1u << 30));
    c = static_cast<uint32_t>(crc32(c, p, k));
    p += k, n -= k;
  }
  return c;
}

// Bounds-checked cursor over one record body; any overrun throws, and the
// caller turns that into a problem naming the record.
struct Cur {
  const uint8_t* p{};
  uint64_t n{}, i = 0;
  void need(uint64_t k) {
    if (k > n - i) throw std::runtime_error("field runs past the end of the record");
  }
  template <typename T>
  T le() {
    need(sizeof(T));
    uint64_t v = 0;
    for (size_t k = 0; k < sizeof(T); ++k) v |= static_cast<uint64_t>(p[i + k]) << (8 * k);
    i += sizeof(T);
    return static_cast<T>(v);
  }
  std::string str() {
    const uint32_t k = le<uint32_t>();
    need(k);
    std::string s(reinterpret_cast<const char*>(p + i), k);
    i += k;
    return s;
  }
  std::map<std::string, std::string> str_map() {
    const uint32_t k = le<uint32_t>();
    need(k);
    Cur c{p + i, k};
    std::map<std::string, std::string> m;
    while (c.i < c.n) {
      std::string key = c.str();
      m[key] = c.str();
    }
    i += k;
    return m;
  }
};

}  // namespace

// ---- Writer -----------------------------------------------------------------

Writer::~Writer() {
  if (f_) std::fclose(f_);
}

void Writer::put(const std::vector<uint8_t>& b, bool data_section) {
  if (b.empty()) return;
  if (std::fwrite(b.data(), 1, b.size(), f_) != b.size()) throw std::runtime_error(path_ + ": write failed");
  if (data_section) data_crc_ = crc(data_crc_, b.data(), b.size());
  pos_ += b.size();
}

void Writer::open(const std::string& path, const WriterOptions& options) {
  if (options.compression != "" && options.compression != "zstd" && options.compression != "lz4")
    throw std::runtime_error("MCAP compression \"" + options.compression + "\" (expected zstd, lz4 or none)");
  path_ = path;
  opt_ = options;
  f_ = std::fopen(path.c_str(), "wb");
  if (!f_) throw std::runtime_error(path + ": cannot create");
  std::vector<uint8_t> b(kMagic, kMagic + 8), body;
  str(body, opt_.profile);
  str(body, opt_.library);
  record(b, kHeader, body);
  put(b, true);
}

uint16_t Writer::add_schema(const std::string& name, const std::string& encoding, const std::string& data) {
  const uint16_t id = static_cast<uint16_t>(schemas_.size() + 1);  // 0 means "no schema"
  schemas_.push_back({id, name, encoding, data});
  std::vector<uint8_t> b, body;
  le<uint16_t>(body, id);
  str(body, name);
  str(body, encoding);
  str(body, data);
  record(b, kSchema, body);
  put(b, true);
  return id;
}

uint16_t Writer::add_channel(uint16_t schema_id, const std::string& topic,
                             const std::string& message_encoding,
                             const std::map<std::string, std::string>& metadata) {
  const uint16_t id = static_cast<uint16_t>(channels_.size());
  channels_.push_back({id, schema_id, topic, message_encoding, metadata});
  std::vector<uint8_t> b, body;
  le<uint16_t>(body, id);
  le<uint16_t>(body, schema_id);
  str(body, topic);
  str(body, message_encoding);
  str_map(body, metadata);
  record(b, kChannel, body);
  put(b, true);
  channel_counts_[id] = 0;
  return id;
}

void Writer::write(uint16_t channel_id, uint64_t log_time_ns, uint64_t publish_time_ns, const uint8_t* data,
                   size_t size) {
  if (!f_) throw std::runtime_error("MCAP writer not open");
  rec_.clear();
  u8(rec_, kMessage);
  le<uint64_t>(rec_, 2 + 4 + 8 + 8 + size);
  le<uint16_t>(rec_, channel_id);
  le<uint32_t>(rec_, static_cast<uint32_t>(channel_counts_[channel_id]));
  le<uint64_t>(rec_, log_time_ns);
  le<uint64_t>(rec_, publish_time_ns);
  rec_.insert(rec_.end(), data, data + size);
  ++channel_counts_[channel_id];
  ++stats_.messages;
  t_min_ = std::min(t_min_, log_time_ns);
  t_max_ = std::max(t_max_, log_time_ns);
  if (opt_.chunk_size_bytes == 0) {
    put(rec_, true);
    return;
  }
  if (chunk_.empty()) chunk_start_ = log_time_ns, chunk_end_ = log_time_ns;
  chunk_start_ = std::min(chunk_start_, log_time_ns);
  chunk_end_ = std::max(chunk_end_, log_time_ns);
  chunk_index_[channel_id].emplace_back(log_time_ns, chunk_.size());
  chunk_.insert(chunk_.end(), rec_.begin(), rec_.end());
  if (chunk_.size() >= opt_.chunk_size_bytes) flush_chunk();
}

void Writer::flush_chunk() {
  if (chunk_.empty()) return;
  const uint32_t ucrc = crc(0, chunk_.data(), chunk_.size());
  const uint8_t* payload = chunk_.data();
  size_t payload_size = chunk_.size();
  if (opt_.compression == "zstd") {
    packed_.resize(ZSTD_compressBound(chunk_.size()));
    const size_t n =
        ZSTD_compress(packed_.data(), packed_.size(), chunk_.data(), chunk_.size(), opt_.zstd_level);
    if (ZSTD_isError(n)) throw std::runtime_error(path_ + ": zstd: " + ZSTD_getErrorName(n));
    payload = packed_.data(), payload_size = n;
  } else if (opt_.compression == "lz4") {
    LZ4F_preferences_t prefs{};
    prefs.frameInfo.contentSize = chunk_.size();
    packed_.resize(LZ4F_compressFrameBound(chunk_.size(), &prefs));
    const size_t n = LZ4F_compressFrame(packed_.data(), packed_.size(), chunk_.data(), chunk_.size(), &prefs);
    if (LZ4F_isError(n)) throw std::runtime_error(path_ + ": lz4: " + LZ4F_getErrorName(n));
    payload = packed_.data(), payload_size = n;
  }
  const uint64_t chunk_offset = pos_;
  std::vector<uint8_t> head;
  u8(head, kChunk);
  const size_t body_len = 8 + 8 + 8 + 4 + 4 + opt_.compression.size() + 8 + payload_size;
  le<uint64_t>(head, body_len);
  le<uint64_t>(head, chunk_start_);
  le<uint64_t>(head, chunk_end_);
  le<uint64_t>(head, chunk_.size());
  le<uint32_t>(head, ucrc);
  str(head, opt_.compression);
  le<uint64_t>(head, payload_size);
  put(head, true);
  if (std::fwrite(payload, 1, payload_size, f_) != payload_size)
    throw std::runtime_error(path_ + ": write failed");
  data_crc_ = crc(data_crc_, payload, payload_size);
  pos_ += payload_size;
  const uint64_t chunk_length = pos_ - chunk_offset;

  // One MessageIndex per channel in the chunk, right after it.
  std::map<uint16_t, uint64_t> index_offsets;
  const uint64_t index_start = pos_;
  for (const auto& [ch, entries] : chunk_index_) {
    std::vector<uint8_t> b, body;
    le<uint16_t>(body, ch);
    le<uint32_t>(body, static_cast<uint32_t>(entries.size() * 16));
    for (const auto& [t, off] : entries) le<uint64_t>(body, t), le<uint64_t>(body, off);
    index_offsets[ch] = pos_;
    record(b, kMessageIndex, body);
    put(b, true);
  }
  std::vector<uint8_t> ci;
  le<uint64_t>(ci, chunk_start_);
  le<uint64_t>(ci, chunk_end_);
  le<uint64_t>(ci, chunk_offset);
  le<uint64_t>(ci, chunk_length);
  le<uint32_t>(ci, static_cast<uint32_t>(index_offsets.size() * 10));
  for (const auto& [ch, off] : index_offsets) le<uint16_t>(ci, ch), le<uint64_t>(ci, off);
  le<uint64_t>(ci, pos_ - index_start);
  str(ci, opt_.compression);
  le<uint64_t>(ci, payload_size);
  le<uint64_t>(ci, chunk_.size());
  chunk_indexes_.push_back(std::move(ci));
  chunk_.clear();
  chunk_index_.clear();
  ++stats_.chunks;
}

void Writer::add_metadata(const std::string& name, const std::map<std::string, std::string>& metadata) {
  flush_chunk();  // Metadata is a top-level record
  std::vector<uint8_t> b, body;
  str(body, name);
  str_map(body, metadata);
  const uint64_t at = pos_;
  record(b, kMetadata, body);
  put(b, true);
  std::vector<uint8_t> idx;
  le<uint64_t>(idx, at);
  le<uint64_t>(idx, b.size());
  str(idx, name);
  metadata_indexes_.push_back(std::move(idx));
  ++metadata_count_;
}

void Writer::close() {
  if (!f_) return;
  flush_chunk();
  std::vector<uint8_t> b, body;
  le<uint32_t>(body, data_crc_);
  record(b, kDataEnd, body);
  put(b, false);

  // Summary: every group is contiguous, and a SummaryOffset points at each.
  const uint64_t summary_start = pos_;
  uint32_t summary_crc = 0;
  std::vector<uint8_t> offsets;
  auto group = [&](uint8_t op, const std::vector<std::vector<uint8_t>>& bodies) {
    if (bodies.empty()) return;
    const uint64_t start = pos_;
    std::vector<uint8_t> g;
    for (const auto& bd : bodies) record(g, op, bd);
    put(g, false);
    summary_crc = crc(summary_crc, g.data(), g.size());
    std::vector<uint8_t> so;
    u8(so, op);
    le<uint64_t>(so, start);
    le<uint64_t>(so, g.size());
    record(offsets, kSummaryOffset, so);
  };
  std::vector<std::vector<uint8_t>> sch, chn;
  for (const auto& s : schemas_) {
    std::vector<uint8_t> x;
    le<uint16_t>(x, s.id), str(x, s.name), str(x, s.encoding), str(x, s.data);
    sch.push_back(std::move(x));
  }
  for (const auto& c : channels_) {
    std::vector<uint8_t> x;
    le<uint16_t>(x, c.id), le<uint16_t>(x, c.schema_id), str(x, c.topic), str(x, c.encoding);
    str_map(x, c.metadata);
    chn.push_back(std::move(x));
  }
  std::vector<uint8_t> st;
  le<uint64_t>(st, stats_.messages);
  le<uint16_t>(st, static_cast<uint16_t>(schemas_.size()));
  le<uint32_t>(st, static_cast<uint32_t>(channels_.size()));
  le<uint32_t>(st, 0);  // attachments
  le<uint32_t>(st, metadata_count_);
  le<uint32_t>(st, static_cast<uint32_t>(stats_.chunks));
  le<uint64_t>(st, stats_.messages ? t_min_ : 0);
  le<uint64_t>(st, stats_.messages ? t_max_ : 0);
  le<uint32_t>(st, static_cast<uint32_t>(channel_counts_.size() * 10));
  for (const auto& [ch, n] : channel_counts_) le<uint16_t>(st, ch), le<uint64_t>(st, n);
  group(kSchema, sch);
  group(kChannel, chn);
  group(kStatistics, {st});
  group(kChunkIndex, chunk_indexes_);
  group(kMetadataIndex, metadata_indexes_);
  const uint64_t summary_offset_start = pos_;
  put(offsets, false);
  summary_crc = crc(summary_crc, offsets.data(), offsets.size());

  std::vector<uint8_t> foot;
  u8(foot, kFooter);
  le<uint64_t>(foot, 20);
  le<uint64_t>(foot, summary_start);
  le<uint64_t>(foot, summary_offset_start);
  summary_crc = crc(summary_crc, foot.data(), foot.size());
  le<uint32_t>(foot, summary_crc);
  foot.insert(foot.end(), kMagic, kMagic + 8);
  put(foot, false);
  stats_.bytes = pos_;
  const bool ok = std::fclose(f_) == 0;
  f_ = nullptr;
  if (!ok) throw std::runtime_error(path_ + ": write failed");
}

// ---- Reader -----------------------------------------------------------------

Reader::Reader(const std::string& path, const ReaderOptions& options) : name_(path), opt_(options) {
  f_ = std::fopen(path.c_str(), "rb");
  if (!f_) throw std::runtime_error(path + ": cannot open");
  std::fseek(f_, 0, SEEK_END);
  size_ = static_cast<uint64_t>(std::ftell(f_));
  uint8_t m[8];
  if (!read_at(0, 8, m) || std::memcmp(m, kMagic, 8) != 0)
    throw std::runtime_error(path + ": not an MCAP file (no MCAP magic)");
}

Reader::Reader(const uint8_t* data, size_t size, const ReaderOptions& options)
    : name_("<memory>"), opt_(options) {
  f_ = size ? fmemopen(const_cast<uint8_t*>(data), size, "rb") : nullptr;
  size_ = size;
  uint8_t m[8];
  if (!f_ || !read_at(0, 8, m) || std::memcmp(m, kMagic, 8) != 0)
    throw std::runtime_error(name_ + ": not an MCAP file (no MCAP magic)");
}

Reader::~Reader() {
  if (f_) std::fclose(f_);
}

void Reader::problem(uint64_t at, const std::string& kind, const std::string& detail) {
  problems_.push_back(LogProblem{name_ + "@" + std::to_string(at), kind, detail});
}

bool Reader::read_at(uint64_t off, size_t n, uint8_t* out) {
  if (off > size_ || n > size_ - off) return false;
  if (std::fseek(f_, static_cast<long>(off), SEEK_SET) != 0) return false;
  return std::fread(out, 1, n, f_) == n;
}

bool Reader::decompress(const Chunk& c, uint64_t at, std::vector<uint8_t>& out) {
  if (c.uncompressed_size > opt_.max_chunk_bytes || c.compressed_size > opt_.max_chunk_bytes) {
    problem(at, "bad-length",
            "chunk of " + std::to_string(c.uncompressed_size) + " bytes exceeds the reader's limit; skipped");
    return false;
  }
  if (c.compression.empty()) {
    if (c.compressed_size != c.uncompressed_size) {
      problem(at, "bad-length", "uncompressed chunk whose two sizes differ; skipped");
      return false;
    }
    out.resize(c.uncompressed_size);
    if (!read_at(c.data_offset, out.size(), out.data()))
      return problem(at, "truncated", "chunk cut short"), false;
  } else {
    compressed_.resize(c.compressed_size);
    if (!read_at(c.data_offset, compressed_.size(), compressed_.data()))
      return problem(at, "truncated", "chunk cut short"), false;
    out.resize(c.uncompressed_size);
    if (c.compression == "zstd") {
      const size_t n = ZSTD_decompress(out.data(), out.size(), compressed_.data(), compressed_.size());
      if (ZSTD_isError(n) || n != out.size()) {
        return problem(at, "bad-chunk",
                       std::string("zstd: ") + (ZSTD_isError(n) ? ZSTD_getErrorName(n) : "size differs")),
               false;
      }
    } else if (c.compression == "lz4") {
      LZ4F_dctx* d = nullptr;
      if (LZ4F_isError(LZ4F_createDecompressionContext(&d, LZ4F_VERSION)))
        return problem(at, "bad-chunk", "lz4 context"), false;
      size_t src = compressed_.size(), dst = out.size(), done = 0, used = 0;
      size_t r = 1;
      while (r != 0 && used < compressed_.size()) {
        src = compressed_.size() - used, dst = out.size() - done;
        r = LZ4F_decompress(d, out.data() + done, &dst, compressed_.data() + used, &src, nullptr);
        if (LZ4F_isError(r)) break;
        used += src, done += dst;
        if (src == 0 && dst == 0) break;
      }
      LZ4F_freeDecompressionContext(d);
      if (LZ4F_isError(r) || done != out.size()) {
        return problem(at, "bad-chunk",
                       std::string("lz4: ") + (LZ4F_isError(r) ? LZ4F_getErrorName(r) : "size differs")),
               false;
      }
    } else {
      problem(at, "bad-encoding",
              "chunk compression \"" + c.compression + "\" (expected zstd, lz4 or none); skipped");
      return false;
    }
  }
  if (c.crc != 0 && crc(0, out.data(), out.size()) != c.crc) {
    problem(at, "bad-crc", "chunk CRC does not match its records; skipped");
    return false;
  }
  return true;
}

void Reader::record(uint8_t op, const uint8_t* body, uint64_t len, uint64_t at, int32_t chunk,
                    uint64_t offset,
                    const std::function<void(const MessageRef&, const uint8_t*, size_t)>* on_message,
                    size_t& n) {
  Cur c{body, len};
  switch (op) {
    case kHeader:
      profile_ = c.str();
      break;
    case kSchema: {
      SchemaRec s;
      s.id = c.le<uint16_t>();
      s.name = c.str();
      s.encoding = c.str();
      s.data = c.str();
      if (s.id != 0) schemas_[s.id] = std::move(s);
      break;
    }
    case kChannel: {
      ChannelRec ch;
      ch.id = c.le<uint16_t>();
      ch.schema_id = c.le<uint16_t>();
      ch.topic = c.str();
      ch.message_encoding = c.str();
      ch.metadata = c.str_map();
      channels_[ch.id] = std::move(ch);
      break;
    }
    case kMetadata: {
      std::string name = c.str();
      metadata_[name] = c.str_map();
      break;
    }
    case kMessage: {
      MessageRef m;
      m.channel_id = c.le<uint16_t>();
      m.sequence = c.le<uint32_t>();
      m.log_time_ns = c.le<uint64_t>();
      m.publish_time_ns = c.le<uint64_t>();
      m.chunk = chunk;
      m.offset = offset;
      m.size = static_cast<uint32_t>(len - c.i);
      if (!channels_.count(m.channel_id)) {
        problem(at, "bad-record",
                "message on channel " + std::to_string(m.channel_id) + " that no Channel record declared");
        break;
      }
      ++n;
      if (on_message) (*on_message)(m, body + c.i, m.size);
      break;
    }
    default:
      break;  // indexes and summary records: the scan rebuilds what it needs
  }
}

size_t Reader::scan(const std::function<void(const MessageRef&, const uint8_t*, size_t)>& on_message) {
  size_t n = 0;
  uint64_t pos = 8;
  std::vector<uint8_t> body;
  chunks_.clear();
  cached_chunk_ = -1;
  while (true) {
    uint8_t h[9];
    if (pos == size_) {
      problem(pos, "truncated", "file ends before DataEnd / Footer");
      break;
    }
    if (!read_at(pos, 9, h)) {
      problem(pos, "truncated", "record header cut short");
      break;
    }
    const uint8_t op = h[0];
    uint64_t len = 0;
    for (int k = 0; k < 8; ++k) len |= static_cast<uint64_t>(h[1 + k]) << (8 * k);
    const uint64_t at = pos;
    if (len > size_ - pos - 9) {
      problem(at, "truncated",
              "record (opcode " + std::to_string(op) + ") of " + std::to_string(len) +
                  " bytes runs past the end of the file");
      break;
    }
    pos += 9 + len;
    if (op == kDataEnd || op == kFooter) break;
    try {
      if (op == kChunk) {
        uint8_t ch[8 * 3 + 4 + 4];
        if (len < sizeof ch) throw std::runtime_error("chunk header cut short");
        if (!read_at(at + 9, sizeof ch, ch)) throw std::runtime_error("chunk header unreadable");
        Cur c{ch, sizeof ch};
        c.le<uint64_t>(), c.le<uint64_t>();
        Chunk k;
        k.uncompressed_size = c.le<uint64_t>();
        k.crc = c.le<uint32_t>();
        const uint32_t clen = c.le<uint32_t>();
        if (clen > 16 || len < sizeof ch + clen + 8)
          throw std::runtime_error("chunk compression name too long");
        uint8_t tail[16 + 8];
        if (!read_at(at + 9 + sizeof ch, clen + 8, tail)) throw std::runtime_error("chunk header unreadable");
        k.compression.assign(reinterpret_cast<const char*>(tail), clen);
        Cur t{tail + clen, 8};
        k.compressed_size = t.le<uint64_t>();
        k.data_offset = at + 9 + sizeof ch + clen + 8;
        if (k.compressed_size != len - (sizeof ch + clen + 8))
          throw std::runtime_error("chunk records length disagrees with the record length");
        if (!decompress(k, at, body)) continue;
        const int32_t idx = static_cast<int32_t>(chunks_.size());
        chunks_.push_back(k);
        uint64_t q = 0;
        while (q < body.size()) {
          if (body.size() - q < 9) {
            problem(at, "bad-record", "chunk ends inside a record header");
            break;
          }
          uint64_t rl = 0;
          for (int b = 0; b < 8; ++b) rl |= static_cast<uint64_t>(body[q + 1 + b]) << (8 * b);
          if (rl > body.size() - q - 9) {
            problem(at, "bad-record", "record in chunk runs past the chunk's end");
            break;
          }
          try {
            record(body[q], body.data() + q + 9, rl, at, idx, q + 9, &on_message, n);
          } catch (const std::exception& e) {
            problem(at, "bad-record", std::string("record in chunk: ") + e.what());
          }
          q += 9 + rl;
        }
      } else {
        if (op != kSchema && op != kChannel && op != kMessage && op != kHeader && op != kMetadata) continue;
        if (len > opt_.max_record_bytes) {
          problem(at, "bad-length",
                  "record of " + std::to_string(len) + " bytes exceeds the reader's limit; skipped");
          continue;
        }
        body.resize(len);
        if (!read_at(at + 9, len, body.data())) throw std::runtime_error("record unreadable");
        record(op, body.data(), len, at, -1, at + 9, &on_message, n);
      }
    } catch (const std::exception& e) {
      problem(at, "bad-record", std::string("opcode ") + std::to_string(op) + ": " + e.what());
    }
  }
  return n;
}

bool Reader::load(const MessageRef& m, std::vector<uint8_t>& scratch, const uint8_t*& data) {
  // The payload starts 2 + 4 + 8 + 8 bytes into the Message record body.
  const uint64_t skip = 22;
  if (m.chunk < 0) {
    scratch.resize(m.size);
    if (!read_at(m.offset + skip, m.size, scratch.data()))
      return problem(m.offset, "truncated", "message unreadable"), false;
    data = scratch.data();
    return true;
  }
  if (static_cast<size_t>(m.chunk) >= chunks_.size()) return false;
  if (cached_chunk_ != m.chunk) {
    cached_chunk_ = -1;
    if (!decompress(chunks_[static_cast<size_t>(m.chunk)], chunks_[static_cast<size_t>(m.chunk)].data_offset,
                    cache_))
      return false;
    cached_chunk_ = m.chunk;
  }
  if (m.offset + skip + m.size > cache_.size()) return false;
  data = cache_.data() + m.offset + skip;
  return true;
}

}  // namespace kestrel::drivers::mcap

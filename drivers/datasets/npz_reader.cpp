#include "kestrel/drivers/npz_reader.hpp"

#include <zip.h>

#include <cctype>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>
#include <stdexcept>

namespace kestrel::drivers {

namespace {

[[noreturn]] void fail(const std::string& what, const std::string& why) {
  throw std::runtime_error(what + ": " + why);
}

// The dict is Python literal syntax written by numpy: {'key': value, ...}
// with string, True/False and tuple-of-int values. A small cursor parser is
// enough, and it reports where it stopped understanding.
class DictParser {
 public:
  DictParser(const std::string& text, const std::string& what) : s_(text), what_(what) {}

  NpyHeader parse() {
    NpyHeader h;
    bool have_descr = false, have_order = false, have_shape = false;
    expect('{');
    while (true) {
      skip_ws();
      if (peek() == '}') break;
      const std::string key = parse_string();
      expect(':');
      skip_ws();
      if (key == "descr") {
        h.descr = parse_string();
        have_descr = true;
      } else if (key == "fortran_order") {
        h.fortran_order = parse_bool();
        have_order = true;
      } else if (key == "shape") {
        h.shape = parse_tuple();
        have_shape = true;
      } else {
        fail(what_, "npy header: unexpected key '" + key + "'");
      }
      skip_ws();
      if (peek() == ',') {
        ++i_;
        continue;
      }
      if (peek() == '}') break;
      error("',' or '}'");
    }
    if (!have_descr || !have_order || !have_shape)
      fail(what_, "npy header: missing 'descr', 'fortran_order' or 'shape'");
    return h;
  }

 private:
  char peek() const { return i_ < s_.size() ? s_[i_] : '\0'; }
  void skip_ws() {
    while (i_ < s_.size() && std::isspace(static_cast<unsigned char>(s_[i_]))) ++i_;
  }
  [[noreturn]] void error(const std::string& expected) const {
    fail(what_,
         "npy header: expected " + expected + " at offset " + std::to_string(i_) + " of \"" + s_ + "\"");
  }
  void expect(char c) {
    skip_ws();
    if (peek() != c) error(std::string("'") + c + "'");
    ++i_;
  }
  std::string parse_string() {
    skip_ws();
    const char q = peek();
    if (q != '\'' && q != '"') error("a quoted string");
    const size_t end = s_.find(q, i_ + 1);
    if (end == std::string::npos) error("the end of a string");
    std::string out = s_.substr(i_ + 1, end - i_ - 1);
    i_ = end + 1;
    return out;
  }
  bool parse_bool() {
    if (s_.compare(i_, 4, "True") == 0) {
      i_ += 4;
      return true;
    }
    if (s_.compare(i_, 5, "False") == 0) {
      i_ += 5;
      return false;
    }
    error("True or False");
  }
  std::vector<size_t> parse_tuple() {
    std::vector<size_t> dims;
    expect('(');
    while (true) {
      skip_ws();
      if (peek() == ')') {
        ++i_;
        return dims;
      }
      if (!std::isdigit(static_cast<unsigned char>(peek()))) error("a dimension");
      size_t v = 0;
      while (std::isdigit(static_cast<unsigned char>(peek()))) {
        const size_t digit = static_cast<size_t>(peek() - '0');
        if (v > (std::numeric_limits<size_t>::max() - digit) / 10)
          fail(what_, "npy header: dimension overflows");
        v = v * 10 + digit;
        ++i_;
      }
      dims.push_back(v);
      skip_ws();
      if (peek() == ',') ++i_;
    }
  }

  const std::string& s_;
  const std::string& what_;
  size_t i_ = 0;
};

size_t element_count(const std::vector<size_t>& shape, const std::string& what) {
  size_t n = 1;
  for (size_t d : shape) {
    if (d != 0 && n > std::numeric_limits<size_t>::max() / 8 / d) fail(what, "array too large");
    n *= d;
  }
  return n;
}

// Fortran (column-major) to C (row-major) order, any rank.
void to_c_order(NpyArray& a) {
  const size_t rank = a.shape.size();
  if (rank < 2) return;
  std::vector<double> out(a.data.size());
  std::vector<size_t> idx(rank, 0), fstride(rank, 1);
  for (size_t r = 1; r < rank; ++r) fstride[r] = fstride[r - 1] * a.shape[r - 1];
  for (size_t c = 0; c < out.size(); ++c) {
    size_t f = 0;
    for (size_t r = 0; r < rank; ++r) f += idx[r] * fstride[r];
    out[c] = a.data[f];
    for (size_t r = rank; r-- > 0;) {  // odometer over the C index, last axis fastest
      if (++idx[r] < a.shape[r]) break;
      idx[r] = 0;
    }
  }
  a.data.swap(out);
}

std::string zip_error_text(int code) {
  zip_error_t e;
  zip_error_init_with_code(&e, code);
  std::string s = zip_error_strerror(&e);
  zip_error_fini(&e);
  return s;
}

}  // namespace

std::string NpyArray::shape_string() const {
  std::ostringstream s;
  s << "(";
  for (size_t i = 0; i < shape.size(); ++i) s << (i ? ", " : "") << shape[i];
  if (shape.size() == 1) s << ",";
  s << ")";
  return s.str();
}

NpyHeader parse_npy_header(const uint8_t* bytes, size_t size, const std::string& what) {
  static const uint8_t kMagic[6] = {0x93, 'N', 'U', 'M', 'P', 'Y'};
  if (size < 10) fail(what, "truncated: " + std::to_string(size) + " bytes is shorter than an npy preamble");
  if (std::memcmp(bytes, kMagic, 6) != 0) fail(what, "bad magic: not a .npy array");
  const int major = bytes[6];
  size_t len = 0, pre = 0;
  if (major == 1) {
    len = static_cast<size_t>(bytes[8]) | static_cast<size_t>(bytes[9]) << 8;
    pre = 10;
  } else if (major == 2 || major == 3) {
    if (size < 12) fail(what, "truncated npy preamble");
    len = static_cast<size_t>(bytes[8]) | static_cast<size_t>(bytes[9]) << 8 |
          static_cast<size_t>(bytes[10]) << 16 | static_cast<size_t>(bytes[11]) << 24;
    pre = 12;
  } else {
    fail(what, "unsupported npy version " + std::to_string(major) + "." + std::to_string(bytes[7]));
  }
  if (size < pre + len) fail(what, "truncated: the npy header says " + std::to_string(len) + " bytes");
  const std::string dict(reinterpret_cast<const char*>(bytes + pre), len);
  NpyHeader h = DictParser(dict, what).parse();
  h.header_bytes = pre + len;
  if (h.descr != "<f8")
    fail(what, "unsupported dtype '" + h.descr + "' (only little-endian float64 '<f8' is read)");
  return h;
}

NpyArray parse_npy(const uint8_t* bytes, size_t size, const std::string& what) {
  const NpyHeader h = parse_npy_header(bytes, size, what);
  NpyArray a;
  a.shape = h.shape;
  a.was_fortran_order = h.fortran_order;
  const size_t n = element_count(h.shape, what);
  if (size - h.header_bytes != n * 8) {
    fail(what, "truncated or oversized: shape " + std::to_string(n) + " elements needs " +
                   std::to_string(n * 8) + " data bytes, found " + std::to_string(size - h.header_bytes));
  }
  a.data.resize(n);
  std::memcpy(a.data.data(), bytes + h.header_bytes, n * 8);
  if (h.fortran_order) to_c_order(a);
  return a;
}

NpyArray read_npy_file(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) fail(path, "cannot open");
  std::vector<uint8_t> buf((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  return parse_npy(buf.data(), buf.size(), path);
}

NpzFile::NpzFile(const std::string& path) : path_(path) {
  int err = 0;
  zip_t* z = zip_open(path.c_str(), ZIP_RDONLY | ZIP_CHECKCONS, &err);
  if (z == nullptr) fail(path, "cannot open as .npz (zip): " + zip_error_text(err));
  zip_ = z;
}

NpzFile::~NpzFile() {
  if (zip_ != nullptr) zip_discard(static_cast<zip_t*>(zip_));
}

std::vector<std::string> NpzFile::names() const {
  auto* z = static_cast<zip_t*>(zip_);
  std::vector<std::string> out;
  const zip_int64_t n = zip_get_num_entries(z, 0);
  for (zip_int64_t i = 0; i < n; ++i) {
    const char* name = zip_get_name(z, static_cast<zip_uint64_t>(i), ZIP_FL_ENC_GUESS);
    if (name == nullptr) continue;
    std::string s = name;
    if (s.size() > 4 && s.compare(s.size() - 4, 4, ".npy") == 0) s.resize(s.size() - 4);
    out.push_back(s);
  }
  return out;
}

bool NpzFile::contains(const std::string& name) const {
  return zip_name_locate(static_cast<zip_t*>(zip_), (name + ".npy").c_str(), 0) >= 0;
}

NpyArray NpzFile::read(const std::string& name) const {
  auto* z = static_cast<zip_t*>(zip_);
  const std::string what = path_ + ":" + name;
  const zip_int64_t idx = zip_name_locate(z, (name + ".npy").c_str(), 0);
  if (idx < 0) fail(what, "no such array in the archive");
  zip_stat_t st;
  zip_stat_init(&st);
  if (zip_stat_index(z, static_cast<zip_uint64_t>(idx), 0, &st) != 0 || !(st.valid & ZIP_STAT_SIZE))
    fail(what, "cannot stat the member");
  zip_file_t* f = zip_fopen_index(z, static_cast<zip_uint64_t>(idx), 0);
  if (f == nullptr) fail(what, std::string("cannot open the member: ") + zip_strerror(z));
  struct Closer {
    zip_file_t* f;
    ~Closer() { zip_fclose(f); }
  } closer{f};
  auto read_exact = [&](void* dst, size_t n) {
    size_t got = 0;
    while (got < n) {
      const zip_int64_t r = zip_fread(f, static_cast<uint8_t*>(dst) + got, n - got);
      if (r < 0) fail(what, std::string("decompression failed: ") + zip_file_strerror(f));
      if (r == 0) {
        fail(what,
             "truncated: member ends after " + std::to_string(got) + " of " + std::to_string(n) + " bytes");
      }
      got += static_cast<size_t>(r);
    }
  };
  const size_t total = static_cast<size_t>(st.size);
  // Header first (it is small), then the data straight into the array: the
  // 140 MB features array is never held twice.
  std::vector<uint8_t> head(std::min<size_t>(total, 12));
  read_exact(head.data(), head.size());
  size_t header_bytes = 0;
  if (head.size() >= 10 && head[6] == 1) {
    header_bytes = 10 + (static_cast<size_t>(head[8]) | static_cast<size_t>(head[9]) << 8);
  } else if (head.size() >= 12 && (head[6] == 2 || head[6] == 3)) {
    header_bytes = 12 + (static_cast<size_t>(head[8]) | static_cast<size_t>(head[9]) << 8 |
                         static_cast<size_t>(head[10]) << 16 | static_cast<size_t>(head[11]) << 24);
  } else {
    parse_npy_header(head.data(), head.size(), what);  // throws the precise reason
    fail(what, "bad npy preamble");
  }
  if (header_bytes > total) fail(what, "truncated: the npy header runs past the end of the member");
  const size_t have = head.size();
  if (header_bytes < have) fail(what, "malformed npy header (shorter than its preamble)");
  head.resize(header_bytes);
  read_exact(head.data() + have, header_bytes - have);
  const NpyHeader h = parse_npy_header(head.data(), head.size(), what);
  NpyArray a;
  a.shape = h.shape;
  a.was_fortran_order = h.fortran_order;
  const size_t n = element_count(h.shape, what);
  if (total - header_bytes != n * 8) {
    fail(what, "truncated or oversized: shape " + a.shape_string() + " needs " + std::to_string(n * 8) +
                   " data bytes, the member holds " + std::to_string(total - header_bytes));
  }
  a.data.resize(n);
  read_exact(a.data.data(), n * 8);
  if (h.fortran_order) to_c_order(a);
  return a;
}

// ---- KITTI ----------------------------------------------------------------------

KittiVislamSequence load_kitti_vislam_npz(const std::string& path) {
  NpzFile z(path);
  KittiVislamSequence seq;
  seq.path = path;
  auto need = [&](const std::string& name) {
    if (!z.contains(name)) fail(path, "missing array '" + name + "'");
    return z.read(name);
  };
  auto shape_error = [&](const std::string& name, const NpyArray& a, const std::string& want) {
    fail(path + ":" + name, "shape " + a.shape_string() + ", expected " + want);
  };
  const NpyArray t = need("time_stamps");
  if (t.dims() != 2 || t.shape[0] != 1) shape_error("time_stamps", t, "(1, N)");
  const size_t N = t.shape[1];
  seq.t_s = t.data;
  for (size_t i = 1; i < N; ++i) {
    if (!(seq.t_s[i] > seq.t_s[i - 1]))
      fail(path + ":time_stamps", "time does not increase at step " + std::to_string(i));
  }

  auto velocity = [&](const std::string& name, std::vector<double>& out) {
    const NpyArray a = need(name);
    if (a.dims() != 2 || a.shape[0] != 3 || a.shape[1] != N)
      shape_error(name, a, "(3, " + std::to_string(N) + ")");
    out.resize(3 * N);
    for (size_t i = 0; i < N; ++i) {
      for (size_t r = 0; r < 3; ++r) {
        out[3 * i + r] = a.at(r, i);
        if (!std::isfinite(out[3 * i + r]))
          fail(path + ":" + name, "non-finite value at step " + std::to_string(i));
      }
    }
  };
  velocity("linear_velocity", seq.v_B_mps);
  velocity("rotational_velocity", seq.w_B_rps);

  const NpyArray K = need("K");
  if (K.dims() != 2 || K.shape[0] != 3 || K.shape[1] != 3) shape_error("K", K, "(3, 3)");
  std::copy(K.data.begin(), K.data.end(), seq.K);
  const NpyArray b = need("b");
  if (b.size() != 1) shape_error("b", b, "a scalar");
  seq.baseline_m = b.data[0];
  if (!(seq.baseline_m > 0.0)) fail(path + ":b", "baseline must be > 0");
  const NpyArray T = need("cam_T_imu");
  if (T.dims() != 2 || T.shape[0] != 4 || T.shape[1] != 4) shape_error("cam_T_imu", T, "(4, 4)");
  std::copy(T.data.begin(), T.data.end(), seq.cam_T_imu);

  const NpyArray F = need("features");
  if (F.dims() != 3 || F.shape[0] != 4 || F.shape[2] != N)
    shape_error("features", F, "(4, M, " + std::to_string(N) + ")");
  const size_t M = F.shape[1];
  if (M > std::numeric_limits<uint32_t>::max()) fail(path + ":features", "too many landmarks");
  seq.num_landmarks = M;
  // Regroup per step: count, prefix sum, fill. Each of the four planes is
  // read along time (contiguous) for every landmark.
  const double* uL = F.data.data();
  const double* vL = uL + M * N;
  const double* uR = vL + M * N;
  const double* vR = uR + M * N;
  auto present = [](double a, double b2, double c, double d) {
    return a != -1.0 && b2 != -1.0 && c != -1.0 && d != -1.0;
  };
  auto absent = [](double a, double b2, double c, double d) {
    return a == -1.0 && b2 == -1.0 && c == -1.0 && d == -1.0;
  };
  seq.step_begin.assign(N + 1, 0);
  for (size_t j = 0; j < M; ++j) {
    for (size_t i = 0; i < N; ++i) {
      const size_t o = j * N + i;
      if (present(uL[o], vL[o], uR[o], vR[o])) ++seq.step_begin[i + 1];
    }
  }
  for (size_t i = 0; i < N; ++i) seq.step_begin[i + 1] += seq.step_begin[i];
  seq.features.resize(seq.step_begin[N]);
  std::vector<size_t> fill(seq.step_begin.begin(), seq.step_begin.end() - 1);
  for (size_t j = 0; j < M; ++j) {
    for (size_t i = 0; i < N; ++i) {
      const size_t o = j * N + i;
      if (present(uL[o], vL[o], uR[o], vR[o])) {
        if (!std::isfinite(uL[o]) || !std::isfinite(vL[o]) || !std::isfinite(uR[o]) ||
            !std::isfinite(vR[o])) {
          ++seq.missing_partial;
          continue;
        }
        seq.features[fill[i]++] = {static_cast<uint32_t>(j), uL[o], vL[o], uR[o], vR[o]};
      } else if (!absent(uL[o], vL[o], uR[o], vR[o])) {
        ++seq.missing_partial;
      }
    }
  }
  // Non-finite entries were counted but left holes: close them.
  if (seq.missing_partial > 0) {
    size_t w = 0;
    std::vector<size_t> begin(N + 1, 0);
    for (size_t i = 0; i < N; ++i) {
      begin[i] = w;
      for (size_t k = seq.step_begin[i]; k < fill[i]; ++k) seq.features[w++] = seq.features[k];
    }
    begin[N] = w;
    seq.features.resize(w);
    seq.step_begin.swap(begin);
  }
  return seq;
}

}  // namespace kestrel::drivers

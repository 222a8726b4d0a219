// Image pre-filters and codecs of the .klog format (docs/log-format.md).
//
// The median predictor of JPEG-LS (LOCO-I, Weinberger et al. 2000): with a
// the left, b the upper and c the upper-left neighbour, the prediction is
// median(a, b, a + b - c), i.e. a + b - c clamped to [min(a, b), max(a, b)].
// The first row predicts from the left, the first column from above, the
// first sample from 0. Residuals wrap modulo 2^8 (2^16 for depth), so the
// inverse is exact whatever the values.
#include "kestrel/drivers/klog_image_codec.hpp"

#include <lz4.h>
#include <zstd.h>

#include <algorithm>
#include <climits>
#include <cstring>
#include <new>

namespace kestrel::drivers::klog {
namespace {

template <class T>
inline T med_predict(T a, T b, T c) {
  const int lo = std::min<int>(a, b);
  const int hi = std::max<int>(a, b);
  return static_cast<T>(std::min(std::max(int{a} + int{b} - int{c}, lo), hi));
}

// r[x] = cur[x] - prediction; `up` is the row above (nullptr on the first row).
// No dependency between iterations, so the compiler vectorises it.
template <class T>
void residual_row(const T* cur, const T* up, int w, T* r) {
  if (w <= 0) return;
  if (!up) {
    r[0] = cur[0];
    for (int x = 1; x < w; ++x) r[x] = static_cast<T>(cur[x] - cur[x - 1]);
    return;
  }
  r[0] = static_cast<T>(cur[0] - up[0]);
  for (int x = 1; x < w; ++x) r[x] = static_cast<T>(cur[x] - med_predict<T>(cur[x - 1], up[x], up[x - 1]));
}

// In place: residuals of a plane become its values, in raster order (each
// prediction reads only samples already restored).
void restore_plane_u8(uint8_t* p, int w, int h) {
  for (int y = 0; y < h; ++y) {
    uint8_t* row = p + static_cast<size_t>(y) * w;
    if (y == 0) {
      for (int x = 1; x < w; ++x) row[x] = static_cast<uint8_t>(row[x] + row[x - 1]);
      continue;
    }
    const uint8_t* up = row - w;
    row[0] = static_cast<uint8_t>(row[0] + up[0]);
    for (int x = 1; x < w; ++x)
      row[x] = static_cast<uint8_t>(row[x] + med_predict<uint8_t>(row[x - 1], up[x], up[x - 1]));
  }
}

inline uint16_t load_le16(const uint8_t* p) { return static_cast<uint16_t>(p[0] | (p[1] << 8)); }

void forward_rgb(const ImageView& in, uint8_t* out, uint8_t* scratch) {
  const int w = in.width;
  const size_t n = static_cast<size_t>(w) * in.height;
  uint8_t* cur = scratch;  // 3 planes of one row: c0 - c1, c1, c2 - c1
  uint8_t* prev = scratch + 3 * static_cast<size_t>(w);
  for (int y = 0; y < in.height; ++y) {
    const uint8_t* s = in.data + static_cast<size_t>(y) * in.stride_bytes;
    for (int x = 0; x < w; ++x) {
      const uint8_t g = s[3 * x + 1];
      cur[x] = static_cast<uint8_t>(s[3 * x] - g);
      cur[w + x] = g;
      cur[2 * w + x] = static_cast<uint8_t>(s[3 * x + 2] - g);
    }
    for (int c = 0; c < 3; ++c) {
      residual_row<uint8_t>(cur + static_cast<size_t>(c) * w,
                            y > 0 ? prev + static_cast<size_t>(c) * w : nullptr, w,
                            out + c * n + static_cast<size_t>(y) * w);
    }
    std::swap(cur, prev);
  }
}

void forward_gray(const ImageView& in, uint8_t* out) {
  for (int y = 0; y < in.height; ++y) {
    residual_row<uint8_t>(in.data + static_cast<size_t>(y) * in.stride_bytes,
                          y > 0 ? in.data + static_cast<size_t>(y - 1) * in.stride_bytes : nullptr, in.width,
                          out + static_cast<size_t>(y) * in.width);
  }
}

void forward_depth(const ImageView& in, uint8_t* out, uint8_t* scratch) {
  const int w = in.width;
  const size_t n = static_cast<size_t>(w) * in.height;
  // Rows are copied out as host uint16 (the file is little-endian, the source
  // pointer may be unaligned).
  auto* cur = reinterpret_cast<uint16_t*>(scratch);
  uint16_t* prev = cur + w;
  uint16_t* res = prev + w;
  for (int y = 0; y < in.height; ++y) {
    const uint8_t* s = in.data + static_cast<size_t>(y) * in.stride_bytes;
    for (int x = 0; x < w; ++x) cur[x] = load_le16(s + 2 * x);
    residual_row<uint16_t>(cur, y > 0 ? prev : nullptr, w, res);
    uint8_t* lo = out + static_cast<size_t>(y) * w;
    uint8_t* hi = lo + n;
    for (int x = 0; x < w; ++x) {
      lo[x] = static_cast<uint8_t>(res[x] & 0xffu);
      hi[x] = static_cast<uint8_t>(res[x] >> 8);
    }
    std::swap(cur, prev);
  }
}

void inverse_depth(int w, int h, const uint8_t* residuals, uint8_t* out) {
  const size_t n = static_cast<size_t>(w) * h;
  const uint8_t* lo = residuals;
  const uint8_t* hi = residuals + n;
  for (int y = 0; y < h; ++y) {
    uint8_t* row = out + 2 * static_cast<size_t>(y) * w;
    const uint8_t* up = y > 0 ? row - 2 * static_cast<size_t>(w) : nullptr;
    const size_t i0 = static_cast<size_t>(y) * w;
    uint16_t left = 0;
    for (int x = 0; x < w; ++x) {
      const auto r = static_cast<uint16_t>(lo[i0 + x] | (hi[i0 + x] << 8));
      uint16_t pred = 0;
      if (!up) {
        pred = left;  // first row: left (0 for the first sample)
      } else if (x == 0) {
        pred = load_le16(up);
      } else {
        pred = med_predict<uint16_t>(left, load_le16(up + 2 * x), load_le16(up + 2 * x - 2));
      }
      const auto v = static_cast<uint16_t>(r + pred);
      row[2 * x] = static_cast<uint8_t>(v & 0xffu);
      row[2 * x + 1] = static_cast<uint8_t>(v >> 8);
      left = v;
    }
  }
}

size_t pixel_bytes(PixelFormat f, int width, int height) {
  return static_cast<size_t>(width) * static_cast<size_t>(height) * static_cast<size_t>(bytes_per_pixel(f));
}

void append_rows(const ImageView& v, std::string& out) {
  const size_t row = static_cast<size_t>(v.width) * static_cast<size_t>(bytes_per_pixel(v.format));
  if (static_cast<size_t>(v.stride_bytes) == row) {
    out.append(reinterpret_cast<const char*>(v.data), row * static_cast<size_t>(v.height));
    return;
  }
  for (int y = 0; y < v.height; ++y)
    out.append(reinterpret_cast<const char*>(v.data) + static_cast<size_t>(y) * v.stride_bytes, row);
}

}  // namespace

bool is_valid_codec(uint8_t codec) { return codec <= static_cast<uint8_t>(ImageCodec::kLz4); }
bool is_valid_filter(uint8_t filter) { return filter <= static_cast<uint8_t>(ImageFilter::kMedPlanar); }

const char* codec_name(ImageCodec c) {
  switch (c) {
    case ImageCodec::kRaw:
      return "none";
    case ImageCodec::kZstd:
      return "zstd";
    case ImageCodec::kLz4:
      return "lz4";
  }
  return "?";
}

bool parse_codec(const std::string& name, ImageCodec& out) {
  if (name == "zstd") {
    out = ImageCodec::kZstd;
  } else if (name == "lz4") {
    out = ImageCodec::kLz4;
  } else if (name == "none") {
    out = ImageCodec::kRaw;
  } else {
    return false;
  }
  return true;
}

std::string describe(const ImageCompression& c) {
  const std::string plain = c.prefilter || c.codec == ImageCodec::kRaw ? "" : " without pre-filter";
  if (c.codec == ImageCodec::kZstd) return "zstd level " + std::to_string(c.zstd_level) + plain;
  return codec_name(c.codec) + plain;
}

int zstd_min_level() { return ZSTD_minCLevel(); }
int zstd_max_level() { return ZSTD_maxCLevel(); }

ImageFilter filter_for(PixelFormat f) {
  // YUYV interleaves two resolutions (Y per pixel, U and V per pair): no
  // plane predictor fits it without a layout of its own.
  return f == PixelFormat::kYuyv ? ImageFilter::kNone : ImageFilter::kMedPlanar;
}

bool filter_applies(ImageFilter filter, PixelFormat f) {
  return filter == ImageFilter::kNone || (filter == ImageFilter::kMedPlanar && f != PixelFormat::kYuyv);
}

void filter_forward(ImageFilter filter, const ImageView& in, uint8_t* out, uint8_t* scratch) {
  if (in.width <= 0 || in.height <= 0) return;
  if (filter == ImageFilter::kNone) {
    const size_t row = static_cast<size_t>(in.width) * bytes_per_pixel(in.format);
    for (int y = 0; y < in.height; ++y)
      std::memcpy(out + row * y, in.data + static_cast<size_t>(y) * in.stride_bytes, row);
    return;
  }
  switch (in.format) {
    case PixelFormat::kRgb8:
    case PixelFormat::kBgr8:
      forward_rgb(in, out, scratch);
      break;
    case PixelFormat::kGray8:
      forward_gray(in, out);
      break;
    case PixelFormat::kDepthU16:
      forward_depth(in, out, scratch);
      break;
    case PixelFormat::kYuyv:
      break;  // never chosen (filter_applies)
  }
}

size_t filter_scratch_bytes(int width) { return 6 * static_cast<size_t>(std::max(width, 0)); }

void filter_inverse(ImageFilter filter, PixelFormat f, int width, int height, uint8_t* residuals,
                    uint8_t* out) {
  const size_t bytes = pixel_bytes(f, width, height);
  if (bytes == 0) return;
  if (filter == ImageFilter::kNone) {
    std::memcpy(out, residuals, bytes);
    return;
  }
  const size_t n = static_cast<size_t>(width) * height;
  switch (f) {
    case PixelFormat::kRgb8:
    case PixelFormat::kBgr8: {
      for (int c = 0; c < 3; ++c) restore_plane_u8(residuals + c * n, width, height);
      const uint8_t* p0 = residuals;
      const uint8_t* p1 = residuals + n;
      const uint8_t* p2 = residuals + 2 * n;
      for (size_t i = 0; i < n; ++i) {
        const uint8_t g = p1[i];
        out[3 * i] = static_cast<uint8_t>(p0[i] + g);
        out[3 * i + 1] = g;
        out[3 * i + 2] = static_cast<uint8_t>(p2[i] + g);
      }
      break;
    }
    case PixelFormat::kGray8:
      restore_plane_u8(residuals, width, height);
      std::memcpy(out, residuals, n);
      break;
    case PixelFormat::kDepthU16:
      inverse_depth(width, height, residuals, out);
      break;
    case PixelFormat::kYuyv:
      break;
  }
}

// ---- encoder ---------------------------------------------------------------------------------------------

ImageEncoder::~ImageEncoder() { ZSTD_freeCCtx(static_cast<ZSTD_CCtx*>(zstd_)); }

size_t ImageEncoder::compress(const uint8_t* src, size_t n, std::string& out, size_t at) {
  if (compression_.codec == ImageCodec::kZstd) {
    if (!zstd_) {
      zstd_ = ZSTD_createCCtx();
      if (!zstd_) throw std::bad_alloc();
    }
    auto* cctx = static_cast<ZSTD_CCtx*>(zstd_);
    ZSTD_CCtx_setParameter(cctx, ZSTD_c_compressionLevel, compression_.zstd_level);
    // A content checksum (4 bytes, xxh64) lets the reader tell a damaged
    // stream from a good one even when the record CRC was resealed over it.
    ZSTD_CCtx_setParameter(cctx, ZSTD_c_checksumFlag, 1);
    out.resize(at + ZSTD_compressBound(n));
    const size_t z = ZSTD_compress2(cctx, &out[at], out.size() - at, src, n);
    return ZSTD_isError(z) ? 0 : z;
  }
  if (compression_.codec == ImageCodec::kLz4 && n <= static_cast<size_t>(LZ4_MAX_INPUT_SIZE)) {
    if (lz4_state_.size() < static_cast<size_t>(LZ4_sizeofState()))
      lz4_state_.resize(static_cast<size_t>(LZ4_sizeofState()));
    const int bound = LZ4_compressBound(static_cast<int>(n));
    out.resize(at + static_cast<size_t>(bound));
    const int got = LZ4_compress_fast_extState(lz4_state_.data(), reinterpret_cast<const char*>(src),
                                               &out[at], static_cast<int>(n), bound, 1);
    return got > 0 ? static_cast<size_t>(got) : 0;
  }
  return 0;
}

void ImageEncoder::encode(const ImageView& view, std::string& out, ImageCodec& codec, ImageFilter& filter) {
  const size_t raw = pixel_bytes(view.format, view.width, view.height);
  codec = ImageCodec::kRaw;
  filter = ImageFilter::kNone;
  if (compression_.codec == ImageCodec::kRaw || raw == 0) {
    append_rows(view, out);
    return;
  }
  ImageFilter f = compression_.prefilter ? filter_for(view.format) : ImageFilter::kNone;
  const size_t scratch = filter_scratch_bytes(view.width);
  if (filtered_.size() < raw + scratch) filtered_.resize(raw + scratch);
  filter_forward(f, view, filtered_.data(), filtered_.data() + raw);
  const size_t at = out.size();
  size_t z = compress(filtered_.data(), raw, out, at);
  // Depth is tried both ways, and the smaller kept: a structured-light
  // sensor's depth (quantised disparity, long equal runs) compresses better
  // as it is, a time-of-flight or simulated one with noise after the
  // predictor (docs/log-format.md "Compressed images").
  if (f != ImageFilter::kNone && view.format == PixelFormat::kDepthU16) {
    filter_forward(ImageFilter::kNone, view, filtered_.data(), nullptr);
    const size_t plain = compress(filtered_.data(), raw, alternative_, 0);
    if (plain > 0 && (z == 0 || plain < z)) {
      out.resize(at);
      out.append(alternative_.data(), plain);
      z = plain;
      f = ImageFilter::kNone;
    }
  }
  if (z == 0 || z >= raw) {
    out.resize(at);
    append_rows(view, out);
    return;
  }
  out.resize(at + z);
  codec = compression_.codec;
  filter = f;
}

uint64_t ImageDecoder::max_decoded_bytes(ImageCodec codec, size_t n) {
  switch (codec) {
    case ImageCodec::kRaw:
      return n;
    case ImageCodec::kZstd:
      return (uint64_t{n} / 4 + 1) * ZSTD_BLOCKSIZE_MAX;
    case ImageCodec::kLz4:
      return uint64_t{n} * 256 + 64;
  }
  return 0;
}

// ---- decoder ---------------------------------------------------------------------------------------------

ImageDecoder::~ImageDecoder() { ZSTD_freeDCtx(static_cast<ZSTD_DCtx*>(zstd_)); }

bool ImageDecoder::decode(ImageCodec codec, ImageFilter filter, PixelFormat f, int width, int height,
                          const uint8_t* src, size_t n, uint8_t* dst, std::string& why) {
  const size_t expected = pixel_bytes(f, width, height);
  if (!filter_applies(filter, f)) {
    why = "pre-filter " + std::to_string(static_cast<int>(filter)) + " does not apply to pixel format " +
          std::to_string(static_cast<int>(f));
    return false;
  }
  if (codec == ImageCodec::kRaw) {
    if (filter != ImageFilter::kNone) {
      why = "raw pixels with a pre-filter";
      return false;
    }
    if (n != expected) {
      why = "image " + std::to_string(width) + "x" + std::to_string(height) + " needs " +
            std::to_string(expected) + " pixel bytes, payload has " + std::to_string(n);
      return false;
    }
    if (n > 0) std::memcpy(dst, src, n);
    return true;
  }
  uint8_t* target = dst;
  if (filter != ImageFilter::kNone) {
    if (residuals_.size() < expected) residuals_.resize(expected);
    target = residuals_.data();
  }
  if (codec == ImageCodec::kZstd) {
    const unsigned long long declared = ZSTD_getFrameContentSize(src, n);
    if (declared == ZSTD_CONTENTSIZE_ERROR) {
      why = "compressed pixels are not a zstd frame";
      return false;
    }
    if (declared != ZSTD_CONTENTSIZE_UNKNOWN && declared != expected) {
      why = "zstd frame declares " + std::to_string(declared) + " bytes, the " + std::to_string(width) + "x" +
            std::to_string(height) + " image has " + std::to_string(expected);
      return false;
    }
    if (!zstd_) {
      zstd_ = ZSTD_createDCtx();
      if (!zstd_) throw std::bad_alloc();
    }
    // The output capacity is the image's own size: zstd stops with an
    // error rather than write past it, whatever the stream claims.
    const size_t got = ZSTD_decompressDCtx(static_cast<ZSTD_DCtx*>(zstd_), target, expected, src, n);
    if (ZSTD_isError(got)) {
      why = std::string("zstd: ") + ZSTD_getErrorName(got);
      return false;
    }
    if (got != expected) {
      why = "zstd stream decodes to " + std::to_string(got) + " bytes, the image has " +
            std::to_string(expected);
      return false;
    }
  } else if (codec == ImageCodec::kLz4) {
    if (n > static_cast<size_t>(INT_MAX) || expected > static_cast<size_t>(LZ4_MAX_INPUT_SIZE)) {
      why = "lz4 block too large";
      return false;
    }
    const int got = LZ4_decompress_safe(reinterpret_cast<const char*>(src), reinterpret_cast<char*>(target),
                                        static_cast<int>(n), static_cast<int>(expected));
    if (got < 0) {
      why = "lz4 block is damaged";
      return false;
    }
    if (static_cast<size_t>(got) != expected) {
      why =
          "lz4 block decodes to " + std::to_string(got) + " bytes, the image has " + std::to_string(expected);
      return false;
    }
  } else {
    why = "unknown codec " + std::to_string(static_cast<int>(codec));
    return false;
  }
  if (filter != ImageFilter::kNone) filter_inverse(filter, f, width, height, residuals_.data(), dst);
  return true;
}

}  // namespace kestrel::drivers::klog

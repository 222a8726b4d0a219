// Lossless image compression of .klog image records (format version 2,
// docs/log-format.md "Compressed images").
//
// An image payload's pixels go through a pre-filter (a predictor whose
// residuals are small numbers) and then a general-purpose codec (zstd or
// lz4). Both steps are exactly invertible, so a replay sees the recorded
// bytes bit for bit. The filter is chosen by pixel format (the choice and the
// measurements behind it: docs/log-format.md).
//
// Decoding treats the payload as untrusted: the decoded size is always the
// width * height * bpp of the record's own header (itself capped), the codec
// writes into a buffer of exactly that size and must fill it exactly.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/msgs.hpp"

namespace kestrel::drivers::klog {

// Byte 33 of an image payload.
enum class ImageCodec : uint8_t { kRaw = 0, kZstd = 1, kLz4 = 2 };
// Byte 34 of an image payload.
enum class ImageFilter : uint8_t {
  kNone = 0,
  // JPEG-LS (LOCO-I) median predictor, per plane. 3-byte pixels first become
  // the planes c0 - c1, c1, c2 - c1 (mod 256; green-difference for RGB and
  // BGR alike); gray8 is one plane; depth u16 is predicted on 16-bit values and
  // its residuals are stored as a low-byte plane then a high-byte plane.
  kMedPlanar = 1,
};

bool is_valid_codec(uint8_t codec);
bool is_valid_filter(uint8_t filter);
const char* codec_name(ImageCodec c);
// "zstd" | "lz4" | "none" -> codec; false for anything else.
bool parse_codec(const std::string& name, ImageCodec& out);

// The filter the writer applies to a pixel format (kNone where none helps: YUYV).
ImageFilter filter_for(PixelFormat f);
// Whether a record may carry `filter` for `f` (the reader refuses other pairs).
bool filter_applies(ImageFilter filter, PixelFormat f);

// Pure filter functions over packed pixels. `out` holds width * height * bpp
// bytes; the forward filter takes any stride >= width * bpp and a scratch of
// filter_scratch_bytes(width); the inverse consumes (overwrites) its
// residuals. No allocation.
size_t filter_scratch_bytes(int width);
void filter_forward(ImageFilter filter, const ImageView& in, uint8_t* out, uint8_t* scratch);
void filter_inverse(ImageFilter filter, PixelFormat f, int width, int height, uint8_t* residuals,
                    uint8_t* out);

// What a writer does with image pixels. zstd_level follows zstd's scale
// (negative = faster); lz4 has no level here.
struct ImageCompression {
  ImageCodec codec = ImageCodec::kZstd;
  int zstd_level = 1;
  // Off only to measure what the pre-filter buys (bench_log_klog_compression);
  // not a config key.
  bool prefilter = true;
};
// "zstd level 1", "lz4", "none".
std::string describe(const ImageCompression& c);
// zstd's accepted level range, for config checks.
int zstd_min_level();
int zstd_max_level();

// Compresses image pixels; owns the codec contexts and a filter buffer that
// grow to the largest frame and are reused. Not thread-safe (the writer's).
class ImageEncoder {
 public:
  ImageEncoder() = default;
  ~ImageEncoder();
  ImageEncoder(const ImageEncoder&) = delete;
  ImageEncoder& operator=(const ImageEncoder&) = delete;

  void set_compression(const ImageCompression& c) { compression_ = c; }
  const ImageCompression& compression() const { return compression_; }

  // Appends the record's pixel section to `out` and says how it is encoded.
  // When compression does not make the pixels smaller they are stored raw
  // (codec kRaw, filter kNone), so a record is never larger than raw. Depth
  // is compressed with and without its pre-filter and the smaller kept.
  void encode(const ImageView& view, std::string& out, ImageCodec& codec, ImageFilter& filter);

 private:
  // Compresses n bytes at src into out from offset `at`; the compressed
  // size, 0 on failure (out is left resized to at + bound).
  size_t compress(const uint8_t* src, size_t n, std::string& out, size_t at);
  ImageCompression compression_;
  void* zstd_ = nullptr;  // ZSTD_CCtx
  std::vector<uint8_t> lz4_state_;
  std::vector<uint8_t> filtered_;
  std::string alternative_;
};

// Decompresses image pixels; the contexts and residual buffer are reused.
class ImageDecoder {
 public:
  ImageDecoder() = default;
  ~ImageDecoder();
  ImageDecoder(const ImageDecoder&) = delete;
  ImageDecoder& operator=(const ImageDecoder&) = delete;

  // Decodes `n` bytes at `src` into exactly width * height * bpp bytes at
  // `dst`. False, with `why`, when the stream is damaged, decodes to any other
  // size, or the codec / filter is not valid for the format.
  bool decode(ImageCodec codec, ImageFilter filter, PixelFormat f, int width, int height, const uint8_t* src,
              size_t n, uint8_t* dst, std::string& why);
  // The most `n` bytes of `codec` can decode to (zstd: a 4-byte RLE block per
  // 128 KiB; lz4: about 255 to 1). A record claiming more is damaged, and is
  // refused before its image buffer is sized.
  static uint64_t max_decoded_bytes(ImageCodec codec, size_t n);

 private:
  void* zstd_ = nullptr;  // ZSTD_DCtx
  std::vector<uint8_t> residuals_;
};

}  // namespace kestrel::drivers::klog

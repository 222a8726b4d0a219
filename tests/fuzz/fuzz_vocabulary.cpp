// The place-recognition vocabulary file (core/place, `map.vocabulary`). The
// file carries a CRC-32 over its payload, which a fuzzer cannot forge, so
// each input is read twice: as a whole file, and as a payload sealed here with
// a good magic, version and CRC. A vocabulary it accepts must place
// descriptors on words it has and serialise to the bytes it came from.
// Seeds: payloads of small vocabularies trained as the place tests train them.
#include <random>

#include "fuzz_target.hpp"
#include "kestrel/core/bytes.hpp"
#include "kestrel/core/vocabulary.hpp"

using kestrel::core::Vocabulary;

namespace {

void check(const uint8_t* data, size_t size) {
  std::string err;
  const Vocabulary v = Vocabulary::deserialise(data, size, &err);
  if (!err.empty()) return;
  std::mt19937_64 rng(size);
  for (int i = 0; i < 8; ++i) {
    kestrel::core::OrbDescriptor d;
    for (auto& w : d) w = rng();
    const uint32_t word = v.word_of(d);
    if (!v.empty() && word >= static_cast<uint32_t>(v.words())) std::abort();
    v.idf(word);
  }
  const std::vector<uint8_t> again = v.serialise();
  std::string err2;
  const Vocabulary w = Vocabulary::deserialise(again.data(), again.size(), &err2);
  if (!err2.empty() || w.checksum() != v.checksum() || w.serialise() != again) std::abort();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  check(data, size);
  const std::vector<uint8_t> sealed =
      kestrel::core::seal(Vocabulary::kMagic, Vocabulary::kVersion, std::vector<uint8_t>(data, data + size));
  check(sealed.data(), sealed.size());
  return 0;
}

size_t kestrel::fuzz::write_seeds(const std::string& dir) {
  std::mt19937_64 rng(1);
  std::vector<std::vector<kestrel::core::OrbDescriptor>> images(6);
  for (auto& img : images)
    for (int i = 0; i < 40; ++i) {
      kestrel::core::OrbDescriptor d;
      for (auto& w : d) w = rng();
      img.push_back(d);
    }
  size_t n = 0;
  for (int k : {2, 3}) {
    Vocabulary::TrainOptions o;
    o.k = k;
    o.levels = 2;
    const std::vector<uint8_t> file = Vocabulary::train(images, o).serialise();
    const uint8_t* payload = nullptr;
    size_t payload_n = 0;
    if (!kestrel::core::open_sealed(file.data(), file.size(), Vocabulary::kMagic, Vocabulary::kVersion,
                                    &payload, &payload_n)
             .empty())
      std::abort();
    write_file(dir + "/k" + std::to_string(k) + "_payload.bin", payload, payload_n);
    write_file(dir + "/k" + std::to_string(k) + "_file.kvoc", file.data(), file.size());
    n += 2;
  }
  return n;
}

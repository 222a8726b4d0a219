// `kestrel vocab --out FILE INPUTS...`: trains a place-recognition vocabulary
// (core/place/vocabulary.hpp) on the ORB descriptors of recorded frames:
// any log `kestrel replay` opens (.klog, EuRoC, TUM, ...) or a folder of
// images (png/jpg). Deterministic: the same inputs, options and seed give a
// byte-identical file. docs/map.md says how the default one was made.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <opencv2/imgcodecs.hpp>

#include "kestrel/commands.hpp"
#include "kestrel/core/orb.hpp"
#include "kestrel/core/vocabulary.hpp"
#include "kestrel/drivers/open_log.hpp"

namespace fs = std::filesystem;

namespace kestrel::cli {
namespace {

bool is_image_file(const fs::path& p) {
  std::string e = p.extension().string();
  std::transform(e.begin(), e.end(), e.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return e == ".png" || e == ".jpg" || e == ".jpeg" || e == ".bmp" || e == ".pgm";
}

// Image files directly in a folder (not a dataset's layout), sorted by name;
// depth images (16-bit, "depth" in the name) are not colour frames.
std::vector<fs::path> image_files(const fs::path& dir) {
  std::vector<fs::path> out;
  if (!fs::is_directory(dir)) return out;
  for (const auto& e : fs::directory_iterator(dir)) {
    const std::string name = e.path().filename().string();
    if (e.is_regular_file() && is_image_file(e.path()) && name.find("depth") == std::string::npos)
      out.push_back(e.path());
  }
  std::sort(out.begin(), out.end());
  return out;
}

struct Extractor {
  core::OrbOptions opt;
  std::map<std::pair<int, int>, std::unique_ptr<core::OrbExtractor>> by_size;
  core::OrbFeatures feats;
  explicit Extractor(int n_features) {
    opt.n_features = n_features;
    feats.reserve(n_features);
  }
  std::vector<core::OrbDescriptor> run(const ImageView& v) {
    auto& ex = by_size[{v.width, v.height}];
    if (!ex) ex = std::make_unique<core::OrbExtractor>(opt, v.width, v.height);
    std::vector<core::OrbDescriptor> d;
    if (ex->extract(v, feats) != core::OrbStatus::kOk) return d;
    for (int i = 0; i < feats.size(); ++i) d.push_back(feats.descriptor(i));
    return d;
  }
};

}  // namespace

Subcommand add_vocab_command(CLI::App& parent) {
  struct Args {
    std::string out;
    std::vector<std::string> inputs;
    int k = 10, levels = 4, every = 10, features = 500, iterations = 10;
    uint64_t seed = 1;
  };
  auto a = std::make_shared<Args>();
  CLI::App* app =
      parent.add_subcommand("vocab", "train a place-recognition vocabulary from logs or image folders");
  app->add_option("--out", a->out, "vocabulary file to write (.kvoc)")->required();
  app->add_option("inputs", a->inputs,
                  "logs (.klog, EuRoC, TUM, ... as `kestrel replay` opens them) or image folders")
      ->required();
  app->add_option("--k", a->k, "branching factor of the word tree")->capture_default_str();
  app->add_option("--levels", a->levels, "depth of the word tree (up to k^levels words)")
      ->capture_default_str();
  app->add_option("--every", a->every, "take every n-th colour frame / image")->capture_default_str();
  app->add_option("--features", a->features, "ORB features per image (our extractor, default pattern)")
      ->capture_default_str();
  app->add_option("--iterations", a->iterations, "k-majority iterations per node")->capture_default_str();
  app->add_option("--seed", a->seed, "seeds the k-means++ initialisation")->capture_default_str();
  app->footer("Deterministic: the same inputs, options and seed give a byte-identical file (docs/map.md).");
  Subcommand s;
  s.app = app;
  s.run = [a] {
    if (a->k < 2 || a->k > 64) throw UsageError("--k must be in 2..64");
    if (a->levels < 1 || a->levels > 8) throw UsageError("--levels must be in 1..8");
    if (a->every < 1) throw UsageError("--every must be >= 1");
    if (a->features < 10 || a->features > 5000) throw UsageError("--features must be in 10..5000");
    if (a->iterations < 1) throw UsageError("--iterations must be >= 1");
    Extractor ex(a->features);
    std::vector<std::vector<core::OrbDescriptor>> images;
    for (const std::string& in : a->inputs) {
      if (!fs::exists(in)) throw UsageError("input not found: " + in);
      const std::vector<fs::path> files = image_files(in);
      size_t used = 0;
      if (!files.empty()) {
        for (size_t i = 0; i < files.size(); i += static_cast<size_t>(a->every)) {
          const cv::Mat img = cv::imread(files[i].string(), cv::IMREAD_GRAYSCALE);
          if (img.empty()) throw std::runtime_error(files[i].string() + ": cannot read image");
          const ImageView v{img.cols, img.rows, static_cast<int>(img.step[0]), PixelFormat::kGray8, img.data};
          images.push_back(ex.run(v));
          ++used;
        }
      } else {
        auto log = drivers::open_log(in);
        drivers::LogRecord rec;
        uint64_t frame = 0;
        while (log->next(rec)) {
          if (rec.type != drivers::RecordType::kRgb) continue;
          if (frame++ % static_cast<uint64_t>(a->every) != 0) continue;
          images.push_back(ex.run(rec.image.view()));
          ++used;
        }
      }
      std::printf("%s: %zu images\n", in.c_str(), used);
    }
    size_t n_desc = 0;
    for (const auto& im : images) n_desc += im.size();
    if (n_desc < static_cast<size_t>(a->k)) throw std::runtime_error("too few descriptors to train on");
    core::Vocabulary::TrainOptions to;
    to.k = a->k;
    to.levels = a->levels;
    to.seed = a->seed;
    to.max_iterations = a->iterations;
    to.pattern_seed = ex.opt.pattern_seed;
    const core::Vocabulary v = core::Vocabulary::train(images, to);
    const std::vector<uint8_t> bytes = v.serialise();
    std::ofstream f(a->out, std::ios::binary);
    if (!f) throw std::runtime_error("cannot write " + a->out);
    f.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
    if (!f) throw std::runtime_error("write failed: " + a->out);
    std::printf(
        "vocabulary: %zu images, %zu descriptors -> %d words (%d nodes, k %d, %d levels), %zu bytes, "
        "checksum %08x: %s\n",
        images.size(), n_desc, v.words(), v.nodes(), v.k(), v.levels(), bytes.size(), v.checksum(),
        a->out.c_str());
    return 0;
  };
  return s;
}

}  // namespace kestrel::cli

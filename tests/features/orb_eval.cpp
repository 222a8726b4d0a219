#include "orb_eval.hpp"

#include <cstring>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/video/tracking.hpp>
#include <stdexcept>

namespace kestrel::test {

std::string shared_data_dir_nogtest() {
  if (const char* env = std::getenv("KESTREL_SHARED_DATA")) return env;
  return KESTREL_SHARED_DATA;
}

std::vector<cv::Mat> load_euroc_cam0(const std::string& mav0_dir) {
  const std::string csv = mav0_dir + "/cam0/data.csv";
  std::ifstream in(csv);
  if (!in) throw std::runtime_error(csv + ": cannot open");
  std::vector<cv::Mat> frames;
  std::string line;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    if (line.empty() || line[0] == '#') continue;
    const auto comma = line.find(',');
    if (comma == std::string::npos)
      throw std::runtime_error(csv + ":" + std::to_string(line_no) + ": no comma");
    std::string name = line.substr(comma + 1);
    while (!name.empty() && (name.back() == '\r' || name.back() == ' ')) name.pop_back();
    const std::string path = mav0_dir + "/cam0/data/" + name;
    cv::Mat im = cv::imread(path, cv::IMREAD_GRAYSCALE);
    if (im.empty())
      throw std::runtime_error(path + " (" + csv + ":" + std::to_string(line_no) + "): unreadable");
    frames.push_back(im);
  }
  return frames;
}

Features run_ours(core::OrbExtractor& ex, core::OrbFeatures& f, const cv::Mat& gray) {
  const ImageView v{gray.cols, gray.rows, static_cast<int>(gray.step[0]), PixelFormat::kGray8, gray.data};
  Features out;
  if (ex.extract(v, f) != core::OrbStatus::kOk) return out;
  for (int i = 0; i < f.size(); ++i) {
    out.pts.emplace_back(f.keypoint(i).x, f.keypoint(i).y);
    out.desc.push_back(f.descriptor(i));
  }
  return out;
}

cv::Ptr<cv::ORB> make_cv_orb(int n_features, int n_levels, cv::ORB::ScoreType score) {
  return cv::ORB::create(n_features, 1.2f, n_levels, 31, 0, 2, score, 31, 20);
}

Features run_opencv(cv::ORB& orb, const cv::Mat& gray) {
  std::vector<cv::KeyPoint> kps;
  cv::Mat desc;
  orb.detectAndCompute(gray, cv::noArray(), kps, desc);
  Features out;
  for (int i = 0; i < static_cast<int>(kps.size()); ++i) {
    out.pts.push_back(kps[i].pt);
    core::OrbDescriptor d{};
    std::memcpy(d.data(), desc.ptr<uint8_t>(i), 32);
    out.desc.push_back(d);
  }
  return out;
}

std::vector<std::optional<cv::Point2f>> klt_map(const cv::Mat& a, const cv::Mat& b,
                                                const std::vector<cv::Point2f>& pts) {
  std::vector<std::optional<cv::Point2f>> out(pts.size());
  if (pts.empty()) return out;
  std::vector<cv::Point2f> fwd, back;
  std::vector<uint8_t> st1, st2;
  std::vector<float> err;
  const cv::TermCriteria crit(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 30, 0.01);
  cv::calcOpticalFlowPyrLK(a, b, pts, fwd, st1, err, cv::Size(21, 21), 3, crit);
  cv::calcOpticalFlowPyrLK(b, a, fwd, back, st2, err, cv::Size(21, 21), 3, crit);
  for (std::size_t i = 0; i < pts.size(); ++i)
    if (st1[i] && st2[i] && cv::norm(back[i] - pts[i]) < 0.5) out[i] = fwd[i];
  return out;
}

std::vector<std::optional<cv::Point2f>> affine_map(const cv::Mat& A, const std::vector<cv::Point2f>& pts) {
  std::vector<std::optional<cv::Point2f>> out;
  for (const auto& p : pts)
    out.emplace_back(cv::Point2f(
        static_cast<float>(A.at<double>(0, 0) * p.x + A.at<double>(0, 1) * p.y + A.at<double>(0, 2)),
        static_cast<float>(A.at<double>(1, 0) * p.x + A.at<double>(1, 1) * p.y + A.at<double>(1, 2))));
  return out;
}

void accumulate(Scores& s, const Features& a, const Features& b,
                const std::vector<std::optional<cv::Point2f>>& mapped, cv::Size size_b, float border,
                float radius, float ratio) {
  const float r2 = radius * radius;
  auto inside = [&](const cv::Point2f& p) {
    return p.x >= border && p.y >= border && p.x <= size_b.width - 1 - border &&
           p.y <= size_b.height - 1 - border;
  };
  auto d2 = [](const cv::Point2f& p, const cv::Point2f& q) {
    return (p.x - q.x) * (p.x - q.x) + (p.y - q.y) * (p.y - q.y);
  };
  s.features += static_cast<long>(a.pts.size());
  for (std::size_t i = 0; i < a.pts.size(); ++i) {
    if (!mapped[i] || !inside(*mapped[i])) continue;
    ++s.rep_total;
    for (const auto& q : b.pts)
      if (d2(*mapped[i], q) <= r2) {
        ++s.rep_hits;
        break;
      }
  }
  const auto m = core::match_brute_force(a.desc.data(), static_cast<int>(a.desc.size()), b.desc.data(),
                                         static_cast<int>(b.desc.size()), ratio);
  s.matches += static_cast<long>(m.size());
  for (const auto& x : m) {
    const auto& p = mapped[x.query];
    if (!p || !inside(*p)) continue;
    ++s.match_total;
    if (d2(*p, b.pts[x.train]) <= r2) ++s.match_good;
  }
}

}  // namespace kestrel::test

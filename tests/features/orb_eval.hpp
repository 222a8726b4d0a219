// The comparison protocol of our ORB against cv::ORB (docs/orb.md), shared by
// test_features_orb_euroc and bench_orb. Test-side code: OpenCV is fine here.
#pragma once

#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <optional>
#include <string>
#include <vector>

#include "kestrel/core/orb.hpp"

namespace kestrel::test {

// cam0 frames of an EuRoC ASL folder (mav0/cam0/data.csv order), as 8-bit grey.
// Throws std::runtime_error naming the file when a listed image is unreadable.
std::vector<cv::Mat> load_euroc_cam0(const std::string& mav0_dir);

// Where ../shared/data is, without GoogleTest (for the benchmark).
std::string shared_data_dir_nogtest();

struct Features {
  std::vector<cv::Point2f> pts;  // level-0 pixels
  std::vector<core::OrbDescriptor> desc;
};

Features run_ours(core::OrbExtractor& ex, core::OrbFeatures& scratch, const cv::Mat& gray);
Features run_opencv(cv::ORB& orb, const cv::Mat& gray);
// cv::ORB as the comparison uses it: same budget, levels and FAST threshold.
cv::Ptr<cv::ORB> make_cv_orb(int n_features, int n_levels, cv::ORB::ScoreType score);

// Where each point of `pts` (image a) lies in image b, by pyramidal KLT with a
// forward-backward check (< 0.5 px); nullopt when the track is not trusted.
std::vector<std::optional<cv::Point2f>> klt_map(const cv::Mat& a, const cv::Mat& b,
                                                const std::vector<cv::Point2f>& pts);
// The same through a known 2x3 affine map.
std::vector<std::optional<cv::Point2f>> affine_map(const cv::Mat& A, const std::vector<cv::Point2f>& pts);

struct Scores {
  long rep_hits = 0, rep_total = 0;      // keypoints of a with a keypoint of b within radius of their image
  long match_good = 0, match_total = 0;  // ratio-test matches landing within radius of the true image
  long matches = 0;
  long features = 0;
  double repeatability() const { return rep_total ? double(rep_hits) / rep_total : 0; }
  double precision() const { return match_total ? double(match_good) / match_total : 0; }
};

// Adds one image pair. Only keypoints of a whose true image lies at least
// `border` px inside b count, so both extractors' edge margins are off the table.
void accumulate(Scores& s, const Features& a, const Features& b,
                const std::vector<std::optional<cv::Point2f>>& mapped, cv::Size size_b, float border = 32.0f,
                float radius = 3.0f, float ratio = 0.8f);

}  // namespace kestrel::test

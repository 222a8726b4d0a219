#include "text_log.hpp"

#include <algorithm>
#include <cstdint>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "kestrel/drivers/camera_time_shift.hpp"
#include "kestrel/drivers/folder_logs.hpp"

namespace kestrel::drivers::text {

void StreamLogSource::order_streams(const std::string& imu_file, const std::string& gt_file) {
  auto check = [this](auto& rows, auto time_of, auto line_of, const std::string& file) {
    for (size_t i = 1; i < rows.size(); ++i) {
      if (time_of(rows[i]) <= time_of(rows[i - 1])) {
        problem(file + ":" + std::to_string(line_of(rows[i])), "time-order",
                "timestamp " + std::to_string(time_of(rows[i])) + " not after the previous row's " +
                    std::to_string(time_of(rows[i - 1])) + "; replayed in sorted order");
      }
    }
    std::stable_sort(rows.begin(), rows.end(),
                     [&](const auto& a, const auto& b) { return time_of(a) < time_of(b); });
  };
  check(
      imu_, [](const Row<ImuSample>& r) { return r.value.t_ns; }, [](const auto& r) { return r.line; },
      imu_file);
  check(
      gt_, [](const Row<GroundTruthPose>& r) { return r.value.t_ns; }, [](const auto& r) { return r.line; },
      gt_file);
  // Camera stamps onto the IMU's clock (the rig's time_offset_cam_imu_ns);
  // the merge in next() then interleaves them where they belong.
  for (auto* images : {&rgb_, &depth_, &right_})
    for (ImageEntry& e : *images) e.t_ns = camera_stamp_on_imu_clock(rig_, e.t_ns);
  // Image rows carry their own "file:line".
  for (auto* images : {&rgb_, &depth_, &right_}) {
    for (size_t i = 1; i < images->size(); ++i) {
      if ((*images)[i].t_ns <= (*images)[i - 1].t_ns) {
        problem((*images)[i].where, "time-order",
                "image timestamp not after the previous row's; replayed in sorted order");
      }
    }
    std::stable_sort(images->begin(), images->end(),
                     [](const ImageEntry& a, const ImageEntry& b) { return a.t_ns < b.t_ns; });
  }
  std::stable_sort(events_.begin(), events_.end(),
                   [](const Row<Event>& a, const Row<Event>& b) { return a.value.t_ns < b.value.t_ns; });
}

bool StreamLogSource::load_image(const ImageEntry& e, RecordType type, LogImage& img) {
  ++images_seen_;
  const bool report = images_seen_ > images_reported_until_;
  if (report) images_reported_until_ = images_seen_;
  cv::Mat m;
  try {
    m = cv::imread(e.path, cv::IMREAD_UNCHANGED);
  } catch (const cv::Exception& ex) {
    if (report) problem(e.where, "bad-image", e.path + ": " + ex.what());
    return false;
  }
  if (m.empty()) {
    if (report) problem(e.where, "bad-image", e.path + ": cannot be read or decoded");
    return false;
  }
  cv::Mat out;
  PixelFormat fmt;
  if (type == RecordType::kDepth) {
    if (m.type() != CV_16UC1) {
      if (report) problem(e.where, "bad-image", e.path + ": depth must be a 16-bit single-channel PNG");
      return false;
    }
    out = m;
    fmt = PixelFormat::kDepthU16;
  } else if (m.type() == CV_8UC1) {
    out = m;
    fmt = PixelFormat::kGray8;
  } else if (m.type() == CV_16UC1) {
    // 16-bit grey (TUM-VI's *_16 exports): the top 8 bits, as the tracker reads 8-bit grey.
    m.convertTo(out, CV_8U, 1.0 / 256.0);
    fmt = PixelFormat::kGray8;
  } else if (m.type() == CV_8UC3) {
    cv::cvtColor(m, out, cv::COLOR_BGR2RGB);
    fmt = PixelFormat::kRgb8;
  } else if (m.type() == CV_8UC4) {
    cv::cvtColor(m, out, cv::COLOR_BGRA2RGB);
    fmt = PixelFormat::kRgb8;
  } else {
    if (report) {
      problem(e.where, "bad-image",
              e.path + ": expected an 8-bit gray, RGB or RGBA image or a 16-bit gray one");
    }
    return false;
  }
  img.t_ns = e.t_ns;
  img.t_recv_ns = e.t_recv_ns;
  img.seq = e.seq;
  img.exposure_us = 0;
  img.width = out.cols;
  img.height = out.rows;
  img.format = fmt;
  const size_t row = static_cast<size_t>(out.cols) * static_cast<size_t>(bytes_per_pixel(fmt));
  img.pixels.resize(row * static_cast<size_t>(out.rows));
  for (int y = 0; y < out.rows; ++y) std::copy_n(out.ptr<uint8_t>(y), row, img.pixels.data() + row * y);
  return true;
}

bool StreamLogSource::next(LogRecord& out) {
  for (;;) {
    // At equal times IMU goes first, so a consumer can propagate up to the image it then receives.
    int best = -1;
    int64_t t_best = 0;
    auto consider = [&](int which, bool has, int64_t t) {
      if (has && (best < 0 || t < t_best)) {
        best = which;
        t_best = t;
      }
    };
    consider(0, i_imu_ < imu_.size(), i_imu_ < imu_.size() ? imu_[i_imu_].value.t_ns : 0);
    consider(1, i_rgb_ < rgb_.size(), i_rgb_ < rgb_.size() ? rgb_[i_rgb_].t_ns : 0);
    consider(2, i_depth_ < depth_.size(), i_depth_ < depth_.size() ? depth_[i_depth_].t_ns : 0);
    consider(3, i_gt_ < gt_.size(), i_gt_ < gt_.size() ? gt_[i_gt_].value.t_ns : 0);
    consider(4, i_ev_ < events_.size(), i_ev_ < events_.size() ? events_[i_ev_].value.t_ns : 0);
    // Last at equal times: the right image follows its left one, as depth follows colour.
    consider(5, i_right_ < right_.size(), i_right_ < right_.size() ? right_[i_right_].t_ns : 0);
    switch (best) {
      case 0:
        out.type = RecordType::kImu;
        out.offset = imu_[i_imu_].line;
        out.imu = imu_[i_imu_++].value;
        return true;
      case 1:
      case 2: {
        const ImageEntry& e = best == 1 ? rgb_[i_rgb_++] : depth_[i_depth_++];
        out.type = best == 1 ? RecordType::kRgb : RecordType::kDepth;
        out.offset = e.line;
        if (load_image(e, out.type, out.image)) return true;
        continue;
      }
      case 3:
        out.type = RecordType::kGroundTruth;
        out.offset = gt_[i_gt_].line;
        out.gt = gt_[i_gt_++].value;
        return true;
      case 4:
        out.type = RecordType::kEvent;
        out.offset = events_[i_ev_].line;
        out.event = events_[i_ev_++].value;
        return true;
      case 5: {
        const ImageEntry& e = right_[i_right_++];
        out.type = RecordType::kRight;
        out.offset = e.line;
        if (load_image(e, out.type, out.image)) return true;
        continue;
      }
      default:
        return false;
    }
  }
}

void StreamLogSource::rewind() {
  i_imu_ = i_rgb_ = i_depth_ = i_right_ = i_gt_ = i_ev_ = 0;
  images_seen_ = 0;
}

}  // namespace kestrel::drivers::text

namespace kestrel::drivers {

FolderLogSource::FolderLogSource() : impl_(std::make_unique<text::StreamLogSource>()) {}
FolderLogSource::~FolderLogSource() = default;
const Rig& FolderLogSource::rig() const { return impl_->rig(); }
bool FolderLogSource::next(LogRecord& out) { return impl_->next(out); }
void FolderLogSource::rewind() { impl_->rewind(); }
const std::vector<LogProblem>& FolderLogSource::problems() const { return impl_->problems(); }
size_t FolderLogSource::imu_count() const { return impl_->imu_.size(); }
size_t FolderLogSource::rgb_count() const { return impl_->rgb_.size(); }
size_t FolderLogSource::depth_count() const { return impl_->depth_.size(); }
size_t FolderLogSource::right_count() const { return impl_->right_.size(); }
size_t FolderLogSource::ground_truth_count() const { return impl_->gt_.size(); }

}  // namespace kestrel::drivers

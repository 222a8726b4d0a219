// Every tunable of every backend in one table.
//
// EstimatorConfig holds the options of all backends; visit_options() walks
// them as sections of keys (units in the key names) with a one-line doc each.
// The config loader, `--print-config`, the metrics JSON and docs/config.md all
// walk this one table (tools/config), so a tunable cannot exist in code
// without a key and a documented default. Core stays free of I/O: the visitor
// only hands out references.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/core/divergence.hpp"
#include "kestrel/core/ekf_estimator.hpp"
#include "kestrel/core/frontend_odometry.hpp"
#include "kestrel/core/rgbd_estimator.hpp"
#include "kestrel/core/window_estimator.hpp"

namespace kestrel::core {

// LONSC as paper 000's Algorithm 1 prints it, or with this project's measured
// improvements (docs/lonsc.md, "Deviations from the paper").
enum class LonscVariant : uint8_t { kTuned = 0, kPaper = 1 };

struct EstimatorConfig {
  // "auto": window when the rig has an IMU (imu.rate_hz > 0), rgbd when it has none.
  std::string backend = "auto";
  LonscVariant lonsc_variant = LonscVariant::kTuned;
  // The tracker is shared by every backend that tracks (vo, window, ekf).
  TrackerOptions tracker;
  // The vo backend's fusion, and the window backend's front end (whose start
  // after no still window is window_moving_start_after_ns instead).
  FrontendOdometryOptions vo;
  WindowEstimatorOptions window;
  int64_t window_moving_start_after_ns = 250'000'000;
  EkfEstimatorOptions ekf;
  // Divergence detection, the same for every backend that uses vision.
  DivergenceOptions safety;
  RgbdEstimatorOptions rgbd;

  // The defaults of a backend ("window-embedded" is S = 2, N = 3; "window-ceres"
  // solves with Ceres) with a LONSC variant applied. Throws
  // std::invalid_argument for an unknown backend.
  static EstimatorConfig defaults(const std::string& backend, LonscVariant variant = LonscVariant::kTuned);

  // The options each backend is built with (the shared tracker copied in).
  FrontendOdometryOptions vo_options() const;
  WindowEstimatorOptions window_options() const;
  EkfEstimatorOptions ekf_options() const;
  RgbdEstimatorOptions rgbd_options() const;
};

// The backend a config runs on a rig: its own, or for "auto" window with an
// IMU and rgbd without one.
std::string resolve_backend(const std::string& backend, const Rig& rig);

// The LONSC options of a variant (kTuned: LonscOptions{}).
LonscOptions lonsc_options(LonscVariant v);
const char* to_string(LonscVariant v);

// What a table walker sees. Choices (enums) come as an index into `names`.
class OptionVisitor {
 public:
  virtual ~OptionVisitor() = default;
  virtual void begin_section(const char* name, const char* doc) = 0;
  virtual void end_section() = 0;
  virtual void value(const char* key, double& v, const char* doc) = 0;
  virtual void value(const char* key, float& v, const char* doc) = 0;
  virtual void value(const char* key, int& v, const char* doc) = 0;
  virtual void value(const char* key, int64_t& v, const char* doc) = 0;
  virtual void value(const char* key, uint64_t& v, const char* doc) = 0;
  virtual void value(const char* key, bool& v, const char* doc) = 0;
  virtual void value(const char* key, std::string& v, const char* doc) = 0;
  virtual void choice(const char* key, int& index, const std::vector<const char*>& names,
                      const char* doc) = 0;
};

// Walks every option of `c`, section by section. The keys `estimator.backend`
// and `frontend.lonsc_variant` select defaults (EstimatorConfig::defaults): a
// loader reads them first, then applies every other key on top.
void visit_options(EstimatorConfig& c, OptionVisitor& v);

// Empty when every backend's options are usable, else one line per problem.
std::string validate(const EstimatorConfig& c);

}  // namespace kestrel::core

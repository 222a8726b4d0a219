#include <stdexcept>

#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/core/ekf_estimator.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/core/frontend_odometry.hpp"
#include "kestrel/core/window_estimator.hpp"

namespace kestrel::core {

const char* estimator_names() { return "window, window-embedded, window-ceres, vo, ekf, imu"; }

bool estimator_known(const std::string& name) {
  return name == "vo" || name == "imu" || name == "ekf" || name == "window" || name == "window-embedded" ||
         name == "window-ceres";
}

std::unique_ptr<Estimator> make_estimator(const std::string& name, const Rig& rig) {
  if (name == "imu") return std::make_unique<DeadReckoningEstimator>(rig);
  if (name == "vo") return std::make_unique<FrontendOdometry>(rig);
  if (name == "window") return std::make_unique<WindowEstimator>(rig);
  if (name == "window-embedded" || name == "window-ceres") {
    WindowEstimatorOptions o;
    if (name == "window-embedded") o.window = WindowOptions::embedded();
    if (name == "window-ceres") o.window.solver = WindowOptions::Solver::kCeres;
    return std::make_unique<WindowEstimator>(rig, o);
  }
  if (name == "ekf") return std::make_unique<EkfEstimator>(rig);
  throw std::invalid_argument("unknown estimator '" + name + "' (expected one of: " + estimator_names() + ")");
}

const Tracker* tracker_of(const Estimator& est) {
  if (const auto* w = dynamic_cast<const WindowEstimator*>(&est)) return &w->front().tracker();
  if (const auto* vo = dynamic_cast<const FrontendOdometry*>(&est)) return &vo->tracker();
  if (const auto* e = dynamic_cast<const EkfEstimator*>(&est)) return &e->tracker();
  return nullptr;
}

const WindowEstimator* window_of(const Estimator& est) { return dynamic_cast<const WindowEstimator*>(&est); }

}  // namespace kestrel::core

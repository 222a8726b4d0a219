#include "kestrel/core/estimator_factory.hpp"

#include <stdexcept>

#include "kestrel/core/ekf_estimator.hpp"
#include "kestrel/core/estimator.hpp"
#include "kestrel/core/estimator_config.hpp"
#include "kestrel/core/frontend_odometry.hpp"
#include "kestrel/core/rgbd_estimator.hpp"
#include "kestrel/core/window_estimator.hpp"

namespace kestrel::core {

const char* estimator_names() { return "auto, window, window-embedded, window-ceres, vo, ekf, imu, rgbd"; }

bool estimator_known(const std::string& name) {
  return name == "auto" || name == "vo" || name == "imu" || name == "ekf" || name == "window" ||
         name == "window-embedded" || name == "window-ceres" || name == "rgbd";
}

std::unique_ptr<Estimator> make_estimator(const std::string& name, const Rig& rig) {
  return make_estimator(EstimatorConfig::defaults(name), rig);
}

std::unique_ptr<Estimator> make_estimator(const EstimatorConfig& c, const Rig& rig) {
  const std::string err = validate(c);
  if (!err.empty()) throw std::invalid_argument("estimator config:\n" + err);
  const std::string name = resolve_backend(c.backend, rig);
  if (name == "imu") return std::make_unique<DeadReckoningEstimator>(rig, c.vo.moving_start_after_ns);
  if (name == "vo") return std::make_unique<FrontendOdometry>(rig, c.vo_options());
  if (name == "window" || name == "window-embedded" || name == "window-ceres")
    return std::make_unique<WindowEstimator>(rig, c.window_options());
  if (name == "ekf") return std::make_unique<EkfEstimator>(rig, c.ekf_options());
  if (name == "rgbd") return std::make_unique<RgbdEstimator>(rig, c.rgbd_options());
  throw std::invalid_argument("unknown estimator '" + name + "' (expected one of: " + estimator_names() +
                              ")");
}

const Tracker* tracker_of(const Estimator& est) { return est.view().tracker; }

}  // namespace kestrel::core

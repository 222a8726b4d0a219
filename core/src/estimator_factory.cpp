#include <stdexcept>

#include "kestrel/core/estimator.hpp"
#include "kestrel/core/frontend_odometry.hpp"

namespace kestrel::core {

const char* estimator_names() { return "vo, imu"; }

bool estimator_known(const std::string& name) { return name == "vo" || name == "imu"; }

std::unique_ptr<Estimator> make_estimator(const std::string& name, const Rig& rig) {
  if (name == "imu") return std::make_unique<DeadReckoningEstimator>(rig);
  if (name == "vo") return std::make_unique<FrontendOdometry>(rig);
  throw std::invalid_argument("unknown estimator '" + name + "' (expected one of: " + estimator_names() + ")");
}

}  // namespace kestrel::core

// Every backend by name: the one place that knows them all, so it sits above
// the estimator, window and EKF modules.
#pragma once

#include <memory>
#include <string>

#include "kestrel/core/estimator.hpp"

namespace kestrel::core {

// The backends by name: "window" (the default with an IMU), "window-embedded",
// "window-ceres", "vo" (front end only), "ekf", "imu" (dead reckoning),
// "rgbd" (no IMU), "auto" (window with an IMU, rgbd without).
// Throws std::invalid_argument listing the names for an unknown one.
std::unique_ptr<Estimator> make_estimator(const std::string& name, const Rig& rig);
// A backend with every option from a config (estimator_config.hpp; its
// `backend` names the backend). Throws std::invalid_argument listing every
// option that is out of range.
struct EstimatorConfig;
std::unique_ptr<Estimator> make_estimator(const EstimatorConfig& config, const Rig& rig);
const char* estimator_names();
bool estimator_known(const std::string& name);

class Tracker;
// The tracker of the backends built on one (vo, window, ekf, rgbd; nullptr
// for imu), for status lines and the live viewer: Estimator::view().tracker.
const Tracker* tracker_of(const Estimator& est);

}  // namespace kestrel::core

// The rig as YAML: configs/*.yaml, the .klog file header, exported folders.
//
// Every key carries its unit in its name (docs/log-format.md lists them all).
// Unknown keys are errors, so a misspelt or unit-less key ("fx") never
// silently falls back to a default.
#pragma once

#include <yaml-cpp/yaml.h>

#include <string>

#include "kestrel/msgs.hpp"

namespace kestrel::drivers {

// Parses a rig. `where` names the source in errors ("configs/x.yaml"), which
// read "configs/x.yaml: camera.fx_px: expected a number". Throws std::runtime_error.
Rig rig_from_yaml(const std::string& yaml_text, const std::string& where);

// The same, from a node already parsed (a `rig:` section of a larger config);
// `prefix` is prepended to field names in errors ("rig.").
Rig rig_from_yaml_node(const YAML::Node& node, const std::string& where, const std::string& prefix = "");

// Emits every field; doubles with %.17g, so rig_from_yaml(rig_to_yaml(r)) == r exactly.
std::string rig_to_yaml(const Rig& rig);

// Reads and parses a rig file; errors name the path.
Rig load_rig_file(const std::string& path);

// Field-by-field equality (exact), for round-trip checks.
bool rig_equal(const Rig& a, const Rig& b);

const char* distortion_name(DistortionModel m);  // "none" | "radtan" | "equidistant"

// T^-1 of a rigid transform, its rotation re-orthonormalised first: printed
// calibrations (Kalibr's digits, rs-enumerate-devices' six) are not quite
// orthonormal, and the rig file checks rotations tightly.
Mat4d rigid_inverse(const Mat4d& T);

}  // namespace kestrel::drivers

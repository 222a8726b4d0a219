// core's options table (kestrel/core/estimator_config.hpp) to and from YAML.
//
// A config file's estimator sections (`estimator:`, `frontend:`, `window:`,
// `ekf:`) are read key by key against the table: an unknown key, a value of
// the wrong type or out of range is an error naming the file, the line and
// the key. Other top-level sections (rig, drivers, threads, camera, imu, ...)
// belong to other readers and are not looked at here.
#pragma once

#include <yaml-cpp/node/node.h>

#include <string>
#include <utility>
#include <vector>

#include "kestrel/core/estimator_config.hpp"

namespace kestrel::tools {

// The top-level section names the table uses.
std::vector<std::string> estimator_config_sections();

// The estimator's sections of a config document: the defaults of
// `backend_override` (or of the document's `estimator.backend`, or "auto"),
// with the document's keys applied; its other top-level sections are not
// looked at (the one reader, tools::load_config, checks those). Throws
// std::runtime_error "FILE:LINE: window.recent_frames: expected an integer".
// The vocabulary is not resolved here (tools::load_config does it).
core::EstimatorConfig estimator_config_from_node(const YAML::Node& document, const std::string& where,
                                                 const std::string& backend_override = "");
// YAML text as a document; a syntax error is std::runtime_error "where:LINE: YAML syntax error: ...".
YAML::Node yaml_document(const std::string& text, const std::string& where);
// The estimator's sections from YAML text (the fuzzers' and tests' entry); `where` names it in errors.
core::EstimatorConfig estimator_config_from_yaml(const std::string& text, const std::string& where,
                                                 const std::string& backend_override = "");

// The effective settings as YAML, one commented key per line (what
// `--print-config` prints; loading it back gives the same config).
std::string estimator_config_to_yaml(const core::EstimatorConfig& c);
// The command-line switches `--mapping on|off` and `--loop on|off` (empty:
// the config's value). `--loop on` with mapping off is refused, as is any
// other value: std::invalid_argument naming the option.
void apply_map_switches(core::EstimatorConfig& c, const std::string& mapping, const std::string& loop);

// Every key as ("section.key", value as YAML text), in table order (metrics JSON).
std::vector<std::pair<std::string, std::string>> estimator_config_entries(const core::EstimatorConfig& c);

// The reference table of docs/config.md: every key, its default (window
// backend, tuned LONSC) and its doc line, as Markdown.
std::string estimator_config_reference_markdown();

}  // namespace kestrel::tools

// Each subcommand of `kestrel` lives in its own cmd_<name>.cpp and registers
// itself on the top-level CLI11 app. main() parses, finds the subcommand that
// was given and calls its run function; the return value is the exit code.
#pragma once

#include <CLI/CLI.hpp>
#include <functional>
#include <stdexcept>
#include <string>

namespace kestrel::cli {

struct Subcommand {
  CLI::App* app = nullptr;
  std::function<int()> run;
};

// A user mistake found after parsing (a bad value, a missing file): main()
// prints it with the usage of the subcommand and exits with 2.
struct UsageError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

Subcommand add_sim_command(CLI::App& parent);
Subcommand add_eval_command(CLI::App& parent);
Subcommand add_replay_command(CLI::App& parent);
Subcommand add_bench_command(CLI::App& parent);
Subcommand add_devices_command(CLI::App& parent);
Subcommand add_record_command(CLI::App& parent);
Subcommand add_run_command(CLI::App& parent);
Subcommand add_ekf_slam_command(CLI::App& parent);
Subcommand add_convert_command(CLI::App& parent);
Subcommand add_config_command(CLI::App& parent);
Subcommand add_calib_command(CLI::App& parent);
Subcommand add_vocab_command(CLI::App& parent);

}  // namespace kestrel::cli

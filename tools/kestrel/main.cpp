// `kestrel`: one command line, git-style subcommands.
#include <cstdio>
#include <exception>
#include <iostream>
#include <string>
#include <vector>

#include "kestrel/commands.hpp"
#include "kestrel/drivers/dataset_logs.hpp"
#include "kestrel/drivers/devices.hpp"
#include "kestrel_git_rev.h"

namespace {

constexpr int kExitUsage = 2;

void print_subcommands(const CLI::App& app) {
  std::printf("usage: kestrel <command> [options]\n\ncommands:\n");
  std::printf("  %-8s %s\n", "help", "show this list, or `kestrel help <command>` for its options");
  std::printf("  %-8s %s\n", "version", "print the version and the optional drivers built in");
  for (const CLI::App* sub : app.get_subcommands([](const CLI::App*) { return true; })) {
    if (sub->get_name() == "help" || sub->get_name() == "version") continue;
    std::printf("  %-8s %s\n", sub->get_name().c_str(), sub->get_description().c_str());
  }
}

}  // namespace

namespace {

int run_kestrel(int argc, char** argv) {
  using namespace kestrel::cli;
  CLI::App app{"Kestrel: onboard RGB-D + IMU visual-inertial estimator", "kestrel"};
  app.require_subcommand(1, 1);
  app.fallthrough(false);

  std::vector<Subcommand> commands;
  auto* help = app.add_subcommand("help", "show the commands, or one command's options");
  std::string help_topic;
  help->add_option("command", help_topic, "a subcommand");
  auto* version = app.add_subcommand("version", "print the version and the optional drivers built in");

  commands.push_back(add_sim_command(app));
  commands.push_back(add_replay_command(app));
  commands.push_back(add_eval_command(app));
  commands.push_back(add_bench_command(app));
  commands.push_back(add_devices_command(app));
  commands.push_back(add_record_command(app));
  commands.push_back(add_run_command(app));
  commands.push_back(add_ekf_slam_command(app));
  commands.push_back(add_convert_command(app));
  commands.push_back(add_config_command(app));
  commands.push_back(add_calib_command(app));
  commands.push_back(add_vocab_command(app));

  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForAllHelp& e) {
    return app.exit(e);
  } catch (const CLI::ParseError& e) {
    if (argc < 2) {
      print_subcommands(app);
      return kExitUsage;
    }
    const std::string first = argv[1];
    bool known = first == "help" || first == "version";
    for (const auto& c : commands) known = known || c.app->get_name() == first;
    if (!known && !first.empty() && first[0] != '-') {
      std::fprintf(stderr, "kestrel: unknown command '%s'\n\n", first.c_str());
    } else {
      std::fprintf(stderr, "kestrel: %s\n\n", e.what());
    }
    const CLI::App* failing = nullptr;
    for (const auto& c : commands)
      if (c.app->parsed()) failing = c.app;
    if (failing != nullptr) {
      std::cerr << failing->help();
    } else {
      print_subcommands(app);
    }
    return kExitUsage;
  }

  if (help->parsed()) {
    if (help_topic.empty()) {
      print_subcommands(app);
      return 0;
    }
    for (const auto& c : commands) {
      if (c.app->get_name() == help_topic) {
        std::cout << c.app->help();
        return 0;
      }
    }
    std::fprintf(stderr, "kestrel: no command '%s'\n\n", help_topic.c_str());
    print_subcommands(app);
    return kExitUsage;
  }
  if (version->parsed()) {
    std::printf("kestrel %s (%s)\n", KESTREL_VERSION, KESTREL_GIT_REV);
    std::printf("drivers: %s\n", kestrel::drivers::built_drivers_summary().c_str());
    std::printf(
        "logs: klog, euroc, tum, eth3d, openloris; rosbag %s\n",
        kestrel::drivers::rosbag_built() ? "built" : "NOT built (librosbag-dev missing at build time)");
    std::printf("flight controller: MAVLink v2 over UDP and serial (termios)\n");
    return 0;
  }
  for (const auto& c : commands) {
    if (!c.app->parsed()) continue;
    try {
      return c.run();
    } catch (const UsageError& e) {
      std::fprintf(stderr, "kestrel %s: %s\n\n", c.app->get_name().c_str(), e.what());
      std::cerr << c.app->help();
      return kExitUsage;
    } catch (const std::exception& e) {
      std::fprintf(stderr, "kestrel %s: error: %s\n", c.app->get_name().c_str(), e.what());
      return 1;
    }
  }
  print_subcommands(app);
  return kExitUsage;
}

}  // namespace

// Commands report their own errors; this catches what escapes before one runs
// (building the command table), so the process says why instead of aborting.
int main(int argc, char** argv) {
  try {
    return run_kestrel(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "kestrel: error: %s\n", e.what());
  } catch (...) {
    std::fprintf(stderr, "kestrel: error: an unknown exception\n");
  }
  return 1;
}

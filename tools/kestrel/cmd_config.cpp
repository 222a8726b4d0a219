// kestrel config: the estimator's settings, without running anything.
#include <iostream>
#include <memory>

#include "kestrel/commands.hpp"
#include "kestrel/core/estimator_factory.hpp"
#include "kestrel/dense/dense_config.hpp"
#include "kestrel/tools/config_file.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"

namespace kestrel::cli {

Subcommand add_config_command(CLI::App& parent) {
  struct Args {
    std::string config;
    std::string backend;
    bool markdown = false;
  };
  auto a = std::make_shared<Args>();
  CLI::App* app =
      parent.add_subcommand("config", "print the estimator settings (every tunable, docs/config.md)");
  app->add_option("--config", a->config, "a config file whose estimator sections are applied");
  app->add_option("--estimator", a->backend,
                  std::string("backend whose defaults to start from: ") + core::estimator_names());
  app->add_flag("--markdown", a->markdown,
                "print the reference table of docs/config.md instead (every key, its default, what it does)");
  app->footer(
      "Prints YAML that `kestrel replay|run --config` reads back. docs/config.md's table is this command's\n"
      "--markdown output; a test fails when they disagree.");
  Subcommand s;
  s.app = app;
  s.run = [a] {
    if (a->markdown) {
      std::cout << tools::estimator_config_reference_markdown();
      return 0;
    }
    if (!a->backend.empty() && !core::estimator_known(a->backend)) {
      throw UsageError("unknown --estimator '" + a->backend +
                       "' (expected one of: " + core::estimator_names() + ")");
    }
    const tools::Config file = tools::load_config(a->config, a->backend);
    std::cout << tools::estimator_config_to_yaml(file.estimator)
              << dense::dense_sections_yaml(file.dense, file.dense_view);
    return 0;
  };
  return s;
}

}  // namespace kestrel::cli

// `--view` and its companions, shared by `kestrel replay` and `kestrel run`.
#pragma once

#include <CLI/CLI.hpp>
#include <string>

#include "kestrel/viewer/server.hpp"

namespace kestrel::cli {

struct ViewArgs {
  std::string endpoint;  // "[ADDR:]PORT"; "" = no viewer
  int clients = 4;
  double bandwidth_kbytes_per_s = 1000;
  double wait_s = 0;
};

// with_wait: the command can hold its start for a browser (replay).
void add_view_options(CLI::App* app, ViewArgs& a, bool with_wait);
// Throws UsageError naming the option.
viewer::ServerOptions view_server_options(const ViewArgs& a, const std::string& title);
// "viewer: http://host:8080/ ..." on stdout, once it listens.
void print_view_ready(const viewer::Server& s, const ViewArgs& a);

}  // namespace kestrel::cli

#include "kestrel/view_cli.hpp"

#include <unistd.h>

#include <cstdio>
#include <stdexcept>

#include "kestrel/commands.hpp"

namespace kestrel::cli {

void add_view_options(CLI::App* app, ViewArgs& a, bool with_wait) {
  app->add_option(
      "--view", a.endpoint,
      "serve the live viewer on [ADDR:]PORT (e.g. 8080 or 127.0.0.1:8080): a web page with the camera "
      "image, the features, the 3-D trajectory and map and the state (docs/viewer.md)");
  app->add_option("--view-clients", a.clients, "browsers the viewer streams to at once")
      ->capture_default_str();
  app->add_option("--view-bandwidth", a.bandwidth_kbytes_per_s,
                  "cap of each browser's stream [kB/s]; camera frames are skipped to hold it")
      ->capture_default_str();
  if (with_wait) {
    app->add_option("--view-wait", a.wait_s,
                    "wait up to this many seconds for a browser before the replay starts")
        ->capture_default_str();
  }
}

viewer::ServerOptions view_server_options(const ViewArgs& a, const std::string& title) {
  viewer::ServerOptions o;
  try {
    viewer::parse_view_endpoint(a.endpoint, o);
  } catch (const std::invalid_argument& e) {
    throw UsageError(std::string("--view ") + e.what());
  }
  if (a.clients < 1 || a.clients > 64) throw UsageError("--view-clients must be 1..64");
  if (!(a.bandwidth_kbytes_per_s >= 10)) throw UsageError("--view-bandwidth must be >= 10 kB/s");
  if (!(a.wait_s >= 0)) throw UsageError("--view-wait must be >= 0 seconds");
  o.max_clients = a.clients;
  o.max_connections = 8 * a.clients;
  o.max_kbytes_per_s = a.bandwidth_kbytes_per_s;
  o.title = title;
  return o;
}

void print_view_ready(const viewer::Server& s, const ViewArgs& a) {
  char host[256] = "localhost";
  gethostname(host, sizeof host - 1);
  std::string where = s.url();
  const std::string any = "<this machine>";
  const size_t at = where.find(any);
  if (at != std::string::npos) where.replace(at, any.size(), host);
  std::printf("viewer: %s (at most %d browsers, %.0f kB/s each)%s\n", where.c_str(), a.clients,
              a.bandwidth_kbytes_per_s, a.wait_s > 0 ? "; waiting for a browser" : "");
  std::fflush(stdout);
}

}  // namespace kestrel::cli

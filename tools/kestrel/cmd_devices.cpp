// `kestrel devices`: the cameras and IMUs this machine can see, and which
// drivers this build has.
#include <cstdio>

#include "kestrel/commands.hpp"
#include "kestrel/drivers/devices.hpp"

namespace kestrel::cli {

Subcommand add_devices_command(CLI::App& parent) {
  CLI::App* app =
      parent.add_subcommand("devices", "list connected cameras and IMUs, and the drivers built in");
  app->footer(
      "Probes V4L2 (/dev/video*), OpenNI2, I2C adapters (BMX055 chip ids, reads only) and the USB IMU "
      "bridge.\n"
      "Drivers: docs/drivers/README.md");
  Subcommand s;
  s.app = app;
  s.run = [] {
    std::printf("drivers in this build: %s\n", drivers::built_drivers_summary().c_str());
    const drivers::DeviceReport r = drivers::probe_devices();
    int cams = 0, imus = 0;
    for (const auto& d : r.found) (d.kind == "camera" ? cams : imus)++;
    if (r.found.empty()) {
      std::printf("no cameras and no IMUs found.\n");
    } else {
      std::printf("%d camera(s), %d IMU(s):\n", cams, imus);
      for (const auto& d : r.found) {
        std::printf("  %-6s %-10s %-24s %s\n", d.kind.c_str(), d.driver.c_str(), d.where.c_str(),
                    d.detail.c_str());
      }
    }
    for (const auto& n : r.notes) std::printf("  note: %s\n", n.c_str());
    return 0;
  };
  return s;
}

}  // namespace kestrel::cli

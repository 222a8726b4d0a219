// Internal to kestrel_drivers_datasets: the ASL "data.csv" tables that EuRoC and
// TUM-VI share (mav0/<sensor>/data.csv), one reader for both (euroc_reader.cpp).
// Bad rows are reported on the source and skipped; a missing file is reported
// where the stream is optional.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

#include "text_log.hpp"

namespace kestrel::drivers::asl {

std::string where(const std::string& file, size_t line);
// Not blank and not a '#' comment (the header row of every ASL table).
bool data_line(const std::string& line);
// t_ns, gyro xyz [rad/s], acc xyz [m/s^2]; throws naming the file when it cannot be read.
void read_imu_csv(const std::string& path, text::StreamLogSource& s);
// t_ns, p_WB xyz, q_WB wxyz [, v_WB xyz, ...] (8, 11 or 17 columns).
void read_gt_csv(const std::string& path, text::StreamLogSource& s);
// A camera's t_ns,filename table; the images live in `data_dir`. Rows whose
// file is absent are named and skipped.
void read_image_csv(const std::string& csv, const std::string& data_dir, text::StreamLogSource& s,
                    std::vector<text::ImageEntry>& out);

}  // namespace kestrel::drivers::asl

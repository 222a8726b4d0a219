// Internal to kestrel_drivers: what the ETH3D, OpenLORIS and rosbag readers
// and exporters share — transform algebra on Mat4d, colour/depth association,
// TUM-style "t file" listings and OpenCV-flavoured YAML.
#pragma once

#include <yaml-cpp/yaml.h>

#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/msgs.hpp"
#include "text_log.hpp"

namespace kestrel::drivers::ds {

Mat4d mat_mul(const Mat4d& a, const Mat4d& b);
Mat4d mat_inv(const Mat4d& t);  // rigid inverse
bool is_identity(const Mat4d& t);
Mat4d pose_to_mat(const Vec3d& p, const Quatd& q_wxyz);
void mat_to_pose(const Mat4d& t, Vec3d& p, Quatd& q_wxyz);
// T_WB = T_WX * T_XB, exact when T_XB is the identity.
GroundTruthPose compose(const GroundTruthPose& g, const Mat4d& T_XB);

struct Listed {
  int64_t t_ns = 0;
  std::string file;
  uint64_t line = 0;
};

// "t[s] filename" rows ('#' comments); bad rows become problems naming file:line.
std::vector<Listed> read_list(const std::string& path, text::StreamLogSource& s);

// Colour/depth association: nearest in time within max_dt, closest pairs
// first, each frame used once. Returns, per colour frame, the depth index or -1.
std::vector<long> associate(const std::vector<Listed>& rgb, const std::vector<Listed>& depth,
                            int64_t max_dt_ns, size_t& pairs);

// Adds rgb + associated depth entries to `s`, skipping (and reporting) rows
// whose file is absent; the depth record carries the colour stamp (its own
// in t_recv_ns), as the TUM reader does.
void add_pairs(const std::string& root, const std::vector<Listed>& rgb, const std::string& rgb_list,
               const std::vector<Listed>& depth, const std::string& depth_list,
               const std::vector<long>& depth_of, text::StreamLogSource& s);

// TUM-style ground truth "t tx ty tz qx qy qz qw" (pose of some frame X in W).
void read_tum_poses(const std::string& path, text::StreamLogSource& s,
                    std::vector<text::Row<GroundTruthPose>>& out);

// Removes IMU rows whose stamp repeats the previous one (after sorting),
// reporting each; two samples at one instant would give a zero time step.
void drop_duplicate_imu(text::StreamLogSource& s, const std::string& file);

// None of the three formats states IMU noise densities, and the estimators need them. Without a
// --rig, the figures of the Bosch BMI055/BMX055 class (the D435i's IMU; Kestrel's own IMU, as in
// configs/sim_rgbd_bmx055.yaml) are put in and said to be assumed, naming `where`.
void assume_imu_noise(Rig& r, text::StreamLogSource* s, std::vector<LogProblem>* problems,
                      const std::string& where);

// yaml-cpp over files that start with OpenCV's "%YAML:1.0" directive.
YAML::Node load_cv_yaml(const std::string& path);

// Width/height of an image file without keeping it (0,0 when unreadable).
bool image_size(const std::string& path, int& w, int& h);

}  // namespace kestrel::drivers::ds

// NumPy .npy / .npz reading (no Python at run time), and the KITTI features
// of paper 003's course project (../shared/data/kitti-vislam-features).
//
// .npz is a zip archive (libzip) of .npy members; a .npy is a magic string, a
// version, a header length and a Python-dict header ({'descr': '<f8',
// 'fortran_order': False, 'shape': (4, 3950, 1106), }) followed by the raw
// array. Only little-endian float64 ('<f8') is accepted; anything else is
// rejected with an error naming the file and the array.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace kestrel::drivers {

// A float64 array, always held in C (row-major) order whatever the file used.
struct NpyArray {
  std::vector<size_t> shape;
  std::vector<double> data;
  bool was_fortran_order = false;

  size_t size() const { return data.size(); }
  size_t dims() const { return shape.size(); }
  // Row-major element access; no bounds check.
  double at(size_t i, size_t j) const { return data[i * shape[1] + j]; }
  double at(size_t i, size_t j, size_t k) const { return data[(i * shape[1] + j) * shape[2] + k]; }
  std::string shape_string() const;
};

// The parsed .npy header.
struct NpyHeader {
  std::string descr;
  bool fortran_order = false;
  std::vector<size_t> shape;
  size_t header_bytes = 0;  // magic + version + length field + dict (= offset of the data)
};

// Parses the header at the start of `bytes` (at least its first `size` bytes).
// `what` names the array in errors ("0027.npz:features"). Throws
// std::runtime_error for a bad magic, an unknown version, a truncated or
// malformed dict, or a dtype other than '<f8'.
NpyHeader parse_npy_header(const uint8_t* bytes, size_t size, const std::string& what);

// A whole .npy held in memory.
NpyArray parse_npy(const uint8_t* bytes, size_t size, const std::string& what);
// A .npy file on disk.
NpyArray read_npy_file(const std::string& path);

// Read access to the members of a .npz (zip, stored or deflated).
class NpzFile {
 public:
  // Throws std::runtime_error naming the path when it is not a readable zip.
  explicit NpzFile(const std::string& path);
  ~NpzFile();
  NpzFile(const NpzFile&) = delete;
  NpzFile& operator=(const NpzFile&) = delete;

  // Array names without the ".npy" suffix, in archive order.
  std::vector<std::string> names() const;
  bool contains(const std::string& name) const;
  // Throws std::runtime_error naming "path:name" when missing or malformed.
  NpyArray read(const std::string& name) const;

 private:
  std::string path_;
  void* zip_ = nullptr;  // zip_t*
};

// One stereo feature of the KITTI data: [uL, vL, uR, vR] of landmark `id` (its
// index in the features array).
struct KittiFeature {
  uint32_t id = 0;
  double uL = 0.0, vL = 0.0, uR = 0.0, vR = 0.0;
};

// A whole sequence, features regrouped per time step (CSR: the features of
// step t are features[step_begin[t] .. step_begin[t + 1])).
struct KittiVislamSequence {
  std::string path;
  std::vector<double> t_s;         // time_stamps (1, N) [s]
  std::vector<double> v_B_mps;     // linear_velocity (3, N), per step x y z, IMU frame
  std::vector<double> w_B_rps;     // rotational_velocity (3, N), IMU frame
  double K[9] = {};                // row-major 3x3 intrinsics
  double baseline_m = 0.0;         // b
  double cam_T_imu[16] = {};       // row-major, as stored (see docs/ekf.md for its direction)
  size_t num_landmarks = 0;        // M
  std::vector<size_t> step_begin;  // N + 1
  std::vector<KittiFeature> features;
  size_t missing_partial = 0;  // entries with some but not all of the 4 values = -1 (skipped)

  size_t num_steps() const { return t_s.size(); }
};

// Reads and checks shapes: time_stamps (1,N), features (4,M,N), velocities
// (3,N), K (3,3), b scalar or (1,) or (1,1), cam_T_imu (4,4). Throws
// std::runtime_error naming the file and the array on any mismatch.
KittiVislamSequence load_kitti_vislam_npz(const std::string& path);

}  // namespace kestrel::drivers

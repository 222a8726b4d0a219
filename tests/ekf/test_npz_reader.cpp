// The .npy / .npz reader: small archives written here with libzip (stored and
// deflated members, C and Fortran order, npy 1.0 and 2.0), malformed inputs
// with clear errors, and paper 003's real KITTI files.
#include <gtest/gtest.h>
#include <zip.h>

#include <chrono>
#include <cstring>
#include <fstream>
#include <functional>
#include <string>
#include <vector>

#include "kestrel/core/ekf_slam.hpp"
#include "kestrel/drivers/npz_reader.hpp"
#include "kitti_npz_run.hpp"
#include "test_data.hpp"

namespace {

using kestrel::drivers::NpyArray;
using kestrel::drivers::NpzFile;

std::vector<uint8_t> make_npy(const std::string& descr, bool fortran, const std::string& shape,
                              const std::vector<double>& data, int version = 1) {
  std::string dict = "{'descr': '" + descr + "', 'fortran_order': " + (fortran ? "True" : "False") +
                     ", 'shape': " + shape + ", }";
  const size_t pre = version == 1 ? 10 : 12;
  while ((pre + dict.size() + 1) % 64 != 0) dict += ' ';
  dict += '\n';
  std::vector<uint8_t> out = {0x93, 'N', 'U', 'M', 'P', 'Y', static_cast<uint8_t>(version), 0};
  const size_t len = dict.size();
  out.push_back(static_cast<uint8_t>(len & 0xff));
  out.push_back(static_cast<uint8_t>((len >> 8) & 0xff));
  if (version != 1) {
    out.push_back(static_cast<uint8_t>((len >> 16) & 0xff));
    out.push_back(static_cast<uint8_t>((len >> 24) & 0xff));
  }
  out.insert(out.end(), dict.begin(), dict.end());
  const auto* b = reinterpret_cast<const uint8_t*>(data.data());
  out.insert(out.end(), b, b + data.size() * sizeof(double));
  return out;
}

struct Member {
  std::string name;
  std::vector<uint8_t> bytes;
  bool deflate = true;
};

void write_npz(const std::string& path, const std::vector<Member>& members) {
  int err = 0;
  zip_t* z = zip_open(path.c_str(), ZIP_CREATE | ZIP_TRUNCATE, &err);
  ASSERT_NE(z, nullptr);
  for (const auto& m : members) {
    zip_source_t* src = zip_source_buffer(z, m.bytes.data(), m.bytes.size(), 0);
    ASSERT_NE(src, nullptr);
    const zip_int64_t idx = zip_file_add(z, (m.name + ".npy").c_str(), src, ZIP_FL_OVERWRITE);
    ASSERT_GE(idx, 0);
    ASSERT_EQ(zip_set_file_compression(z, static_cast<zip_uint64_t>(idx),
                                       m.deflate ? ZIP_CM_DEFLATE : ZIP_CM_STORE, 0),
              0);
  }
  ASSERT_EQ(zip_close(z), 0);  // the buffers are read here, so they outlive the call
}

std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::exception& e) {
    return e.what();
  }
  return "(no error)";
}

TEST(NpzReader, ReadsStoredDeflatedCAndFortranOrder) {
  const std::string dir = kestrel::test::temp_dir("npz_reader");
  const std::string path = dir + "/small.npz";
  // The same 2x3 matrix [[1,2,3],[4,5,6]] stored both ways.
  const std::vector<Member> members = {
      {"c", make_npy("<f8", false, "(2, 3)", {1, 2, 3, 4, 5, 6}), true},
      {"f", make_npy("<f8", true, "(2, 3)", {1, 4, 2, 5, 3, 6}), false},
      {"f3", make_npy("<f8", true, "(2, 2, 2)", {0, 4, 2, 6, 1, 5, 3, 7}, 2), true},
      {"scalar", make_npy("<f8", false, "()", {0.5}), true},
  };
  write_npz(path, members);
  NpzFile z(path);
  EXPECT_EQ(z.names(), (std::vector<std::string>{"c", "f", "f3", "scalar"}));
  for (const char* name : {"c", "f"}) {
    const NpyArray a = z.read(name);
    ASSERT_EQ(a.shape, (std::vector<size_t>{2, 3})) << name;
    for (size_t i = 0; i < 2; ++i)
      for (size_t j = 0; j < 3; ++j) EXPECT_EQ(a.at(i, j), static_cast<double>(1 + 3 * i + j)) << name;
  }
  const NpyArray f3 = z.read("f3");
  EXPECT_TRUE(f3.was_fortran_order);
  for (size_t i = 0; i < 8; ++i) EXPECT_EQ(f3.data[i], static_cast<double>(i));
  const NpyArray s = z.read("scalar");
  EXPECT_TRUE(s.shape.empty());
  ASSERT_EQ(s.size(), 1u);
  EXPECT_EQ(s.data[0], 0.5);
}

TEST(NpzReader, MalformedInputsGiveClearErrors) {
  const std::string dir = kestrel::test::temp_dir("npz_reader_bad");
  const std::string path = dir + "/bad.npz";
  std::vector<uint8_t> bad_magic = make_npy("<f8", false, "(2,)", {1, 2});
  bad_magic[1] = 'X';
  std::vector<uint8_t> truncated = make_npy("<f8", false, "(4,)", {1, 2, 3, 4});
  truncated.resize(truncated.size() - 8);
  std::vector<uint8_t> bad_version = make_npy("<f8", false, "(2,)", {1, 2});
  bad_version[6] = 9;
  std::vector<uint8_t> bad_dict = make_npy("<f8", false, "(2,", {1, 2});
  write_npz(path, {{"magic", bad_magic},
                   {"short", truncated},
                   {"f4", make_npy("<f4", false, "(2,)", {1}), true},
                   {"big_endian", make_npy(">f8", false, "(2,)", {1, 2}), false},
                   {"version", bad_version},
                   {"dict", bad_dict},
                   {"tiny", {0x93, 'N', 'U'}}});
  NpzFile z(path);
  auto expect_error = [&](const std::string& name, const std::string& needle) {
    const std::string e = error_of([&] { z.read(name); });
    EXPECT_NE(e.find(path + ":" + name), std::string::npos) << e;
    EXPECT_NE(e.find(needle), std::string::npos) << e;
  };
  expect_error("magic", "bad magic");
  expect_error("short", "truncated");
  expect_error("f4", "unsupported dtype '<f4'");
  expect_error("big_endian", "unsupported dtype '>f8'");
  expect_error("version", "unsupported npy version 9");
  expect_error("dict", "npy header");
  expect_error("tiny", "truncated");
  expect_error("missing", "no such array");
  // Not a zip at all, and a file that is not there.
  const std::string not_zip = dir + "/not_zip.npz";
  std::ofstream(not_zip) << "hello";
  EXPECT_NE(error_of([&] { NpzFile bad(not_zip); }).find(not_zip), std::string::npos);
  EXPECT_NE(error_of([&] { NpzFile bad(dir + "/absent.npz"); }).find("absent.npz"), std::string::npos);
  // A KITTI file with a wrong shape names the array.
  const std::string kitti = dir + "/kitti_bad.npz";
  write_npz(kitti, {{"time_stamps", make_npy("<f8", false, "(2, 2)", {0, 1, 2, 3})}});
  const std::string e = error_of([&] { kestrel::drivers::load_kitti_vislam_npz(kitti); });
  EXPECT_NE(e.find("time_stamps"), std::string::npos) << e;
  EXPECT_NE(e.find("(1, N)"), std::string::npos) << e;
}

// A complete KITTI-style file built here: the loader regroups features per
// step and skips (and counts) half-missing entries.
TEST(NpzReader, KittiLoaderRegroupsFeatures) {
  const std::string dir = kestrel::test::temp_dir("npz_reader_kitti");
  const std::string path = dir + "/k.npz";
  const size_t M = 3, N = 4;
  std::vector<double> feat(4 * M * N, -1.0);
  auto set = [&](size_t j, size_t t, double uL, double vL, double uR, double vR) {
    const double v[4] = {uL, vL, uR, vR};
    for (size_t k = 0; k < 4; ++k) feat[(k * M + j) * N + t] = v[k];
  };
  set(0, 0, 10, 20, 5, 20);
  set(0, 1, 11, 20, 6, 20);
  set(2, 1, 30, 40, 25, 40);
  set(1, 3, 50, 60, 45, 60);
  feat[(2 * M + 1) * N + 2] = 7.0;  // landmark 1 at t=2: only uR present
  std::vector<double> vel(3 * N, 1.0), T(16, 0.0);
  for (int i = 0; i < 4; ++i) T[static_cast<size_t>(5 * i)] = 1.0;
  write_npz(path, {{"time_stamps", make_npy("<f8", false, "(1, 4)", {0.0, 0.1, 0.2, 0.3})},
                   {"features", make_npy("<f8", false, "(4, 3, 4)", feat)},
                   {"linear_velocity", make_npy("<f8", true, "(3, 4)", vel)},
                   {"rotational_velocity", make_npy("<f8", true, "(3, 4)", vel)},
                   {"K", make_npy("<f8", false, "(3, 3)", {700, 0, 600, 0, 700, 180, 0, 0, 1})},
                   {"b", make_npy("<f8", false, "()", {0.5})},
                   {"cam_T_imu", make_npy("<f8", true, "(4, 4)", T)}});
  const auto seq = kestrel::drivers::load_kitti_vislam_npz(path);
  EXPECT_EQ(seq.num_steps(), 4u);
  EXPECT_EQ(seq.num_landmarks, 3u);
  EXPECT_EQ(seq.step_begin, (std::vector<size_t>{0, 1, 3, 3, 4}));
  EXPECT_EQ(seq.missing_partial, 1u);
  EXPECT_EQ(seq.features[1].id, 0u);
  EXPECT_EQ(seq.features[2].id, 2u);
  EXPECT_EQ(seq.features[2].uR, 25.0);
  EXPECT_EQ(seq.features[3].id, 1u);
  EXPECT_EQ(seq.baseline_m, 0.5);
  EXPECT_EQ(seq.K[2], 600.0);
}

// Paper 003's own data: shapes, the extrinsic's direction, and a short run
// of the filter. How long the load and the run take is test_npz_timing's
// (label timing): a sanitized build runs this one several times slower.
TEST(NpzReader, RealKitti0027ShapesAndShortRun) {
  KESTREL_REQUIRE_SHARED("kitti-vislam-features/0027.npz");
  const auto seq =
      kestrel::drivers::load_kitti_vislam_npz(kestrel::test::shared_path("kitti-vislam-features/0027.npz"));
  EXPECT_EQ(seq.num_steps(), 1106u);
  EXPECT_EQ(seq.num_landmarks, 3950u);
  EXPECT_NEAR(seq.K[0], 707.0912, 1e-3);
  EXPECT_NEAR(seq.baseline_m, 0.5372, 1e-3);
  EXPECT_GT(seq.features.size(), 50000u);
  // The car drives along IMU +x ...
  Eigen::Vector3d v_mean = Eigen::Vector3d::Zero();
  for (size_t i = 0; i < seq.num_steps(); ++i) v_mean += Eigen::Vector3d(&seq.v_B_mps[3 * i]);
  v_mean /= static_cast<double>(seq.num_steps());
  EXPECT_GT(v_mean.x(), 3.0);
  // ... and the stored cam_T_imu, read honouring fortran_order, maps IMU
  // coordinates into the camera: IMU +x (forward) becomes the optical axis +z,
  // IMU +y (left) camera -x, IMU +z (up) camera -y.
  EXPECT_GT(seq.cam_T_imu[8], 0.99);   // row 2, col 0
  EXPECT_LT(seq.cam_T_imu[1], -0.99);  // row 0, col 1
  EXPECT_LT(seq.cam_T_imu[6], -0.99);  // row 1, col 2

  const kestrel::test::KittiShortRun run = kestrel::test::run_kitti_100_steps(seq);
  std::printf("[ kitti 0027 ] 100 steps: %d observations used, %d gated\n", run.used, run.gated);
  EXPECT_GT(run.used, 2000);
  EXPECT_LT(run.gated, run.used / 10);  // with the right extrinsic nearly every track fits
  // It drove ~54 m in these 10 s, turning left (velocity dead reckoning ends
  // near (-3, 49) m); the filter must stay close to that, not diverge.
  EXPECT_GT(run.p_norm_m, 40.0);
  EXPECT_LT(run.p_norm_m, 65.0);
}

}  // namespace

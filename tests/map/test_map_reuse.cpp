// Map reuse through the whole harness (`--map-out`, `--map-in`): one
// simulated figure-8 is cut in two flights through the same room. The first
// (its first lap) saves its map; the second (the laps after, starting
// elsewhere and moving, so its odometry frame is another one) loads it, maps
// nothing until it relocalises, and from then on its map-frame trajectory is
// in the first flight's frame: compared with the ground truth through the
// first flight's alignment alone, no re-alignment of its own.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>

#include "kestrel/drivers/klog.hpp"
#include "kestrel/replay_runner.hpp"
#include "kestrel/tools/map_files.hpp"
#include "kestrel/tools/simulator.hpp"
#include "kestrel/tools/trajectory_eval.hpp"
#include "map_pipeline.hpp"
#include "test_data.hpp"

namespace kestrel::map_test {
namespace {

// Records before split_s (from the first record) go to one log, the rest to another.
class SplitSink final : public tools::SimSink {
 public:
  SplitSink(const std::string& a, const std::string& b, double split_s) : path_{a, b}, split_s_(split_s) {}
  void begin(const Rig& rig) override {
    for (int i = 0; i < 2; ++i) w_[i].open(path_[i], rig);
  }
  void imu(const ImuSample& s) override { at(s.t_ns).write_imu(s); }
  void image(drivers::RecordType type, int64_t t_ns, uint32_t seq, const ImageView& v) override {
    at(t_ns).write_image(type, t_ns, t_ns, seq, 0, v);
  }
  void ground_truth(const GroundTruthPose& gt) override { at(gt.t_ns).write_ground_truth(gt); }
  void event(const Event& e) override {
    for (auto& w : w_) w.write_event(e);  // the run's description, in both
  }
  void end() override {
    for (auto& w : w_) w.close();
  }

 private:
  drivers::KlogWriter& at(int64_t t_ns) {
    if (t0_ < 0) t0_ = t_ns;
    return w_[1e-9 * static_cast<double>(t_ns - t0_) < split_s_ ? 0 : 1];
  }
  std::string path_[2];
  double split_s_;
  int64_t t0_ = -1;
  drivers::KlogWriter w_[2];
};

tools::Trajectory transformed(const tools::Sim3& T, const tools::Trajectory& in) {
  tools::Trajectory out = in;
  for (auto& p : out) {
    p.p = T.R * p.p + T.t;
    p.q = Eigen::Quaterniond(T.R * p.q.toRotationMatrix());
  }
  return out;
}

TEST(MapReuse, ASecondFlightLandsInTheFirstFlightsFrame) {
  const std::string dir = test::temp_dir("map_reuse");
  const tools::SimOptions so = figure8(30, 4, 320, 240);
  const std::string first = dir + "/first.klog", second = dir + "/second.klog", map = dir + "/first.kmap";
  SplitSink sink(first, second, 14.0);
  tools::run_simulation(so, sink);
  std::vector<std::string> w;

  // The first flight: its map, and where its frame sits in the truth's.
  cli::ReplayOptions a;
  a.path = first;
  a.pace = drivers::ReplayPace::kLockstep;
  a.config = map_config();
  a.map_out = map;
  const cli::ReplayReport ra = cli::run_replay(a);
  ASSERT_TRUE(std::filesystem::exists(map));
  tools::EvalOptions se3;
  se3.align = tools::Alignment::kSe3;
  const tools::EvalResult ea = tools::evaluate(tools::load_trajectory(first, &w), ra.trajectory, se3);

  // The second flight on the first one's map.
  cli::ReplayOptions b;
  b.path = second;
  b.pace = drivers::ReplayPace::kLockstep;
  core::EstimatorConfig cb = map_config();
  tools::set_map_in(cb, map);
  b.config = cb;
  int64_t t0 = -1;
  double localised_at_s = NAN;
  b.on_pose = [&](const core::PoseSample& p) {
    if (t0 < 0) t0 = p.t_ns;
    if (std::isnan(localised_at_s) && p.map.localized)
      localised_at_s = 1e-9 * static_cast<double>(p.t_ns - t0);
  };
  const cli::ReplayReport rb = cli::run_replay(b);
  // From the relocalisation on, the map frame is the first flight's.
  tools::Trajectory after;
  for (const auto& p : rb.map_trajectory)
    if (1e-9 * static_cast<double>(p.t_ns - t0) > localised_at_s + 0.5) after.push_back(p);
  ASSERT_GT(after.size(), 30u) << "the second flight never relocalised in the first one's map";
  tools::EvalOptions none;
  none.align = tools::Alignment::kNone;
  const tools::Trajectory gt_b = tools::load_trajectory(second, &w);
  const tools::EvalResult eb = tools::evaluate(gt_b, transformed(ea.T_align, after), none);
  const tools::EvalResult eb_odom = tools::evaluate(gt_b, transformed(ea.T_align, rb.trajectory), none);
  std::printf(
      "MAP-REUSE: first flight se3 ATE %.1f mm (%u keyframes); second flight localised at %.2f s, %llu "
      "relocalisations; ATE in the first flight's frame, no re-alignment: map frame %.1f mm, its own "
      "odometry frame %.1f mm\n%s\n",
      1e3 * ea.ate_m.rmse, ra.map.keyframes, localised_at_s,
      static_cast<unsigned long long>(rb.map.relocalisations), 1e3 * eb.ate_m.rmse, 1e3 * eb_odom.ate_m.rmse,
      rb.backend_summary.c_str());
  EXPECT_GE(rb.map.relocalisations, 1u);
  EXPECT_LT(localised_at_s, 4.0) << "localised within its first seconds";
  EXPECT_LT(eb.ate_m.rmse, 0.03);
  EXPECT_GT(eb_odom.ate_m.rmse, 0.1)
      << "the second flight's own frame was the first's anyway: nothing was tested";

  // A damaged map is refused by name.
  {
    std::vector<char> bytes;
    {
      std::ifstream f(map, std::ios::binary);
      bytes.assign(std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>());
    }
    bytes[bytes.size() / 2] ^= 4;
    const std::string bad = dir + "/bad.kmap";
    std::ofstream(bad, std::ios::binary).write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
    core::EstimatorConfig cc = map_config();
    tools::set_map_in(cc, bad);
    b.config = cc;
    b.on_pose = nullptr;
    try {
      (void)cli::run_replay(b);
      ADD_FAILURE() << "a damaged map was used";
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find(bad + ": not a usable map: checksum mismatch"), std::string::npos)
          << e.what();
    }
  }
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace kestrel::map_test

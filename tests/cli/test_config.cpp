// The estimator's options table as a config file (tools/config, docs/config.md):
// every key reads back, bad keys and values name the file, line and key, the
// two preset keys select defaults, and docs/config.md agrees with the code.
// The one reader of a config file (config_file.hpp): each section reaches its
// owner's parser, a misspelt section is an error.
#include <gtest/gtest.h>
#include <unistd.h>

#include <fstream>
#include <set>
#include <sstream>
#include <string>

#include "kestrel/core/estimator_config.hpp"
#include "kestrel/drivers/rig_yaml.hpp"
#include "kestrel/tools/config_file.hpp"
#include "kestrel/tools/estimator_config_yaml.hpp"
#include "run_command.hpp"
#include "test_data.hpp"

namespace {

using kestrel::core::EstimatorConfig;
using kestrel::core::LonscVariant;
using kestrel::tools::estimator_config_entries;
using kestrel::tools::estimator_config_from_yaml;
using kestrel::tools::estimator_config_to_yaml;

std::string error_of(const std::string& yaml) {
  try {
    estimator_config_from_yaml(yaml, "x.yaml");
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

std::string slurp(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  std::ostringstream s;
  s << f.rdbuf();
  return s.str();
}

}  // namespace

TEST(ConfigFile, EmptyFileGivesTheBackendsDefaults) {
  const EstimatorConfig c = estimator_config_from_yaml("", "x.yaml");
  // "auto": window with an IMU, rgbd without; the window's defaults either way.
  EXPECT_EQ(c.backend, "auto");
  EXPECT_EQ(c.window.window.S, 3);
  EXPECT_EQ(c.window.imu_noise_inflation, 30.0);
  EXPECT_EQ(estimator_config_entries(c), estimator_config_entries(EstimatorConfig::defaults("auto")));
  auto without_backend = [](std::vector<std::pair<std::string, std::string>> v) {
    v.erase(v.begin());
    return v;
  };
  EXPECT_EQ(without_backend(estimator_config_entries(c)),
            without_backend(estimator_config_entries(EstimatorConfig::defaults("window"))));
  const EstimatorConfig e = estimator_config_from_yaml("estimator: {backend: window-embedded}\n", "x.yaml");
  EXPECT_EQ(e.window.window.S, 2);
  EXPECT_EQ(e.window.window.N, 3);
}

TEST(ConfigFile, PrintedSettingsReadBackToTheSame) {
  EstimatorConfig c = EstimatorConfig::defaults("ekf", LonscVariant::kPaper);
  c.tracker.orb.n_features = 512;
  c.tracker.match_ratio = 0.7f;
  c.window.window.acc_bias_model = kestrel::core::WindowOptions::AccBiasModel::kBoundedRandomWalk;
  c.window.max_imu_gap_ns = 123'456'789;
  c.ekf.gate_chi2 = 9.49;
  const std::string yaml = estimator_config_to_yaml(c);
  const EstimatorConfig back = estimator_config_from_yaml(yaml, "printed.yaml");
  EXPECT_EQ(estimator_config_entries(back), estimator_config_entries(c));
  EXPECT_EQ(estimator_config_to_yaml(back), yaml);
  EXPECT_GT(estimator_config_entries(c).size(), 100u) << "the table lost its tunables";
}

// A name or path holding YAML syntax (": ", " #", quotes) prints quoted and
// reads back as itself; one with a control character or a byte that is not
// UTF-8 is refused naming the key (the fuzzer's estimator_config finding: an
// accepted multi-line vocabulary path printed into YAML that did not parse).
TEST(ConfigFile, NamesWithYamlSyntaxReadBackAndDamagedOnesAreRefused) {
  for (const std::string name : {"my voc: v2 #1.kvoc", "- dash", "'quoted'", "with \"double\" quotes", "true",
                                 "~", "caf\xc3\xa9.kvoc"}) {
    EstimatorConfig c = estimator_config_from_yaml("{}", "x.yaml");
    c.window.map.vocabulary_path = name;
    const std::string yaml = estimator_config_to_yaml(c);
    const EstimatorConfig back = estimator_config_from_yaml(yaml, "printed.yaml");
    EXPECT_EQ(back.window.map.vocabulary_path, name);
    EXPECT_EQ(estimator_config_to_yaml(back), yaml);
  }
  EXPECT_NE(error_of("map: {vocabulary: \"a\\nb\"}\n")
                .find("x.yaml:1: map.vocabulary: expected printable UTF-8 text"),
            std::string::npos)
      << error_of("map: {vocabulary: \"a\\nb\"}\n");
  EXPECT_NE(
      error_of("map: {vocabulary: \"a\xff.kvoc\"}\n").find("map.vocabulary: expected printable UTF-8 text"),
      std::string::npos);
  // Defaults stay bare, so the printed config and docs/config.md read as before.
  EXPECT_NE(estimator_config_to_yaml(EstimatorConfig::defaults("auto")).find("  backend: auto  #"),
            std::string::npos);
}

TEST(ConfigFile, KeysOverrideWhateverTheirPlace) {
  const EstimatorConfig c = estimator_config_from_yaml(
      "window:\n  imu_noise_inflation: 10\n  solver: ceres\nfrontend:\n  orb: {n_features: 450}\n"
      "  lonsc: {candidate_runs: 2}\n  min_inliers: 12\n  moving_start_after_ns: 1000000000\n"
      "ekf: {landmark_capacity: 96, moving_start_after_ns: 500000000}\n",
      "x.yaml");
  EXPECT_EQ(c.window.imu_noise_inflation, 10.0);
  EXPECT_EQ(c.window.window.solver, kestrel::core::WindowOptions::Solver::kCeres);
  EXPECT_EQ(c.tracker.orb.n_features, 450);
  EXPECT_EQ(c.tracker.lonsc.candidate_runs, 2);
  EXPECT_EQ(c.tracker.min_inliers, 12);
  EXPECT_EQ(c.ekf.landmark_capacity, 96);
  // The backends are built with the shared tracker.
  EXPECT_EQ(c.window_options().frontend.tracker.orb.n_features, 450);
  EXPECT_EQ(c.ekf_options().tracker.orb.n_features, 450);
  // frontend's moving start is vo's; the window keeps its own.
  EXPECT_EQ(c.window_options().frontend.moving_start_after_ns, 250'000'000);
  EXPECT_EQ(c.vo_options().moving_start_after_ns, 1'000'000'000);
  EXPECT_EQ(c.ekf_options().moving_start_after_ns, 500'000'000);
  // The ekf runs the map only when asked; it shares the map: section.
  EXPECT_FALSE(c.ekf_options().mapping);
  const EstimatorConfig m = estimator_config_from_yaml(
      "estimator: {backend: ekf}\nekf: {mapping: true}\nmap: {max_keyframes: 500}\n", "x.yaml");
  EXPECT_TRUE(m.ekf_options().mapping);
  EXPECT_EQ(m.ekf_options().map.map.max_keyframes, 500);
  // --mapping on|off reaches the ekf as it reaches the window.
  EstimatorConfig e = EstimatorConfig::defaults("ekf");
  kestrel::tools::apply_map_switches(e, "on", "off");
  EXPECT_TRUE(e.ekf_options().mapping);
  EXPECT_FALSE(e.ekf_options().map.loop);
  kestrel::tools::apply_map_switches(e, "off", "");
  EXPECT_FALSE(e.ekf_options().mapping);
  EXPECT_FALSE(e.window.map.mapping);
}

TEST(ConfigFile, LonscVariantSelectsThePapersAlgorithmAndKeysStillOverride) {
  const EstimatorConfig p = estimator_config_from_yaml("frontend: {lonsc_variant: paper}\n", "x.yaml");
  EXPECT_EQ(p.lonsc_variant, LonscVariant::kPaper);
  EXPECT_FALSE(p.tracker.lonsc.grow_model);
  EXPECT_FALSE(p.tracker.lonsc.verify_seed_pair);
  EXPECT_FALSE(p.tracker.lonsc.weighted_least_squares);
  EXPECT_EQ(p.tracker.lonsc.candidate_runs, 1);
  EXPECT_EQ(p.tracker.lonsc.refine_passes, 0);
  EXPECT_EQ(p.tracker.lonsc.min_run_length, 2);
  // A key written before the variant still wins: presets apply first.
  const EstimatorConfig q = estimator_config_from_yaml(
      "frontend:\n  lonsc: {refine_passes: 2}\n  lonsc_variant: paper\n", "x.yaml");
  EXPECT_EQ(q.tracker.lonsc.refine_passes, 2);
  EXPECT_FALSE(q.tracker.lonsc.grow_model);
  const EstimatorConfig t = estimator_config_from_yaml("frontend: {lonsc_variant: tuned}\n", "x.yaml");
  EXPECT_TRUE(t.tracker.lonsc.grow_model);
}

TEST(ConfigFile, BadInputNamesFileLineAndKey) {
  EXPECT_NE(
      error_of("window:\n  recent_frames: 3\n  bogus_ms: 1\n").find("x.yaml:3: window.bogus_ms: unknown key"),
      std::string::npos);
  EXPECT_NE(error_of("frontend:\n  orb:\n    n_features: lots\n")
                .find("x.yaml:3: frontend.orb.n_features: expected an integer"),
            std::string::npos);
  EXPECT_NE(error_of("window: {use_depth: maybe}\n").find("window.use_depth: expected true or false"),
            std::string::npos);
  EXPECT_NE(error_of("window: {huber_px: .nan}\n").find("window.huber_px: expected a finite number"),
            std::string::npos);
  EXPECT_NE(error_of("window: {solver: gtsam}\n").find("window.solver: expected one of ours, ceres"),
            std::string::npos);
  EXPECT_NE(error_of("window: [1, 2]\n").find("window: expected a mapping"), std::string::npos);
  EXPECT_NE(error_of("window: {recent_frames: [3]}\n").find("window.recent_frames: expected a single value"),
            std::string::npos);
  EXPECT_NE(error_of("estimator: {backend: kalman}\n").find("estimator.backend: unknown backend 'kalman'"),
            std::string::npos);
  EXPECT_NE(error_of("frontend: {lonsc_variant: ransac}\n").find("frontend.lonsc_variant: expected one of"),
            std::string::npos);
  EXPECT_NE(error_of("window: {recent_frames: 0}\n").find("S must be >= 1"), std::string::npos);
  EXPECT_NE(error_of("frontend: {moving_start_after_ns: -1}\n")
                .find("frontend: moving_start_after_ns: must be >= 0"),
            std::string::npos);
  // vo's own keys are checked like every backend's (they used to take any value).
  EXPECT_NE(error_of("frontend: {gate_sigma: -1}\n").find("frontend: gate_sigma: must be > 0"),
            std::string::npos);
  EXPECT_NE(error_of("frontend: {max_lost_frames: -3}\n").find("frontend: max_lost_frames: at least 1"),
            std::string::npos);
  EXPECT_NE(error_of("frontend: {attitude_gain: 1.5}\n").find("frontend: attitude_gain: in [0, 1]"),
            std::string::npos);
  EXPECT_NE(error_of("ekf: {spread_grid_cols: 4}\n")
                .find("ekf: spread_grid_cols/rows: both 0 (off) or both in [1, 32]"),
            std::string::npos);
  // The map's keys are named under map, once, without the loop closer's indentation.
  const std::string map_err = error_of("map: {loop_connected_min_shared: 0, max_points: 1}\n");
  EXPECT_NE(map_err.find("map: loop_connected_min_shared must be >= 1\n"), std::string::npos) << map_err;
  EXPECT_NE(map_err.find("map: max_points: at least 16\n"), std::string::npos) << map_err;
  EXPECT_EQ(map_err.find("window: "), std::string::npos) << map_err;
  // Two bad keys: each line names its section and key.
  const std::string two = error_of("frontend: {position_sigma_m: 0, imu_outage_after_ns: -1}\n");
  EXPECT_NE(two.find("frontend: position_sigma_m: must be > 0\n"), std::string::npos) << two;
  EXPECT_NE(two.find("frontend: imu_outage_after_ns: must be >= 0"), std::string::npos) << two;
  // A tracker key reaches every backend: it is named once, under frontend.
  const std::string tracker = error_of("frontend: {match_ratio: 2}\n");
  EXPECT_NE(tracker.find("frontend: match_ratio: in (0, 1]"), std::string::npos) << tracker;
  EXPECT_EQ(tracker.find("match_ratio", tracker.find("match_ratio") + 1), std::string::npos) << tracker;
  // ... also beside a window error, whose validator joins its messages with "; ".
  const std::string both = error_of("frontend: {match_ratio: 2}\nwindow: {recent_frames: 0}\n");
  EXPECT_NE(both.find("window: S must be >= 1"), std::string::npos) << both;
  EXPECT_EQ(both.find("match_ratio", both.find("match_ratio") + 1), std::string::npos) << both;
  EXPECT_NE(
      error_of("window: {moving_start_after_ns: -1}\n").find("window: moving_start_after_ns: must be >= 0"),
      std::string::npos);
  EXPECT_NE(error_of("ekf: {moving_start_after_ns: -1}\n").find("ekf: moving_start_after_ns: must be >= 0"),
            std::string::npos);
  EXPECT_NE(
      error_of("ekf: {restart_position_sigma_m: 0}\n").find("ekf: restart_position_sigma_m: must be > 0"),
      std::string::npos);
  // The whole message on one line (the table splits on "; ").
  EXPECT_NE(error_of("ekf: {min_frame_interval_ms: 5000}\n")
                .find("ekf: min_frame_interval_ms: at most 1000 (0: every frame, below 0: the default)\n"),
            std::string::npos);
  EXPECT_NE(error_of("ekf: {min_frame_interval_ms: .nan}\n")
                .find("ekf.min_frame_interval_ms: expected a finite number"),
            std::string::npos);
  EXPECT_NE(error_of("window: {recent_frames: 99999999999}\n").find("window.recent_frames: out of range"),
            std::string::npos);
  EXPECT_NE(error_of("window:\n  recent_frames: 3\n bad indent: [\n").find("x.yaml:"), std::string::npos);
  // Sections of other owners are not this table's business (the one reader checks them).
  EXPECT_EQ(error_of("rig: {name: x}\nthreads: {}\ncamera: {width_px: 640}\n"), "");
}

std::string file_error_of(const std::string& yaml) {
  try {
    kestrel::tools::config_from_yaml(yaml, "x.yaml");
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

// One file, one parse: every section reaches the struct of the folder that owns it.
TEST(ConfigFileReader, EverySectionReachesItsOwner) {
  const std::string dir = kestrel::test::temp_dir("cfg_reader_" + std::to_string(getpid()));
  kestrel::Rig rig;
  rig.name = "own-rig";
  rig.rgb.width = 320;
  rig.rgb.height = 240;
  rig.rgb.fx = rig.rgb.fy = 300;
  rig.rgb.cx = 160;
  rig.rgb.cy = 120;
  {
    std::ofstream f(dir + "/r.yaml");
    f << kestrel::drivers::rig_to_yaml(rig);
  }
  const std::string text =
      "rig: r.yaml\n"
      "drivers:\n  camera: {type: none}\n"
      "threads:\n  kst-optimizer: {cpu: 1, policy: other}\n"
      "mavlink:\n  sysid: 7\n"
      "record:\n  image_codec: lz4\n"
      "ros2:\n  map_points_rate_hz: 2\n"
      "estimator:\n  backend: vo\n"
      "frontend:\n  orb: {n_features: 333}\n"
      "dense:\n  voxel_size_m: 0.08\n"
      "viewer:\n  dense_max_kbps: 250\n";
  {
    std::ofstream f(dir + "/c.yaml");
    f << text;
  }
  const kestrel::tools::Config c = kestrel::tools::load_config(dir + "/c.yaml");
  ASSERT_TRUE(c.rig.has_value());
  EXPECT_EQ(c.rig->name, "own-rig");  // `rig: FILE` is read relative to the config
  EXPECT_EQ(c.drivers.camera.type, kestrel::drivers::CameraType::kNone);
  EXPECT_TRUE(c.threads.from_config);
  EXPECT_EQ(c.threads[kestrel::drivers::PipelineThread::kOptimizer].cpu, 1);
  EXPECT_EQ(c.mavlink.sysid, 7);
  EXPECT_EQ(c.record.compression.codec, kestrel::drivers::klog::ImageCodec::kLz4);
  EXPECT_DOUBLE_EQ(c.ros2.map_points_rate_hz, 2.0);
  EXPECT_EQ(c.estimator.backend, "vo");
  EXPECT_TRUE(c.backend_from_file);
  EXPECT_EQ(c.estimator.tracker.orb.n_features, 333);
  EXPECT_DOUBLE_EQ(c.dense.tsdf.voxel_size_m, 0.08);
  EXPECT_DOUBLE_EQ(c.dense_view.max_kbps, 250.0);
  const kestrel::drivers::LiveConfig live = kestrel::tools::live_config(c);
  EXPECT_EQ(live.rig.name, "own-rig");
  EXPECT_EQ(live.mavlink.sysid, 7);
  // --estimator replaces the file's backend, and the file no longer chose it.
  const kestrel::tools::Config o = kestrel::tools::load_config(dir + "/c.yaml", "ekf");
  EXPECT_EQ(o.estimator.backend, "ekf");
  EXPECT_FALSE(o.backend_from_file);
  EXPECT_EQ(o.estimator.tracker.orb.n_features, 333);
  // No file: the command line's defaults, and no rig.
  const kestrel::tools::Config d = kestrel::tools::load_config("");
  EXPECT_EQ(d.estimator.backend, "auto");
  EXPECT_FALSE(d.rig.has_value());
  EXPECT_FALSE(d.threads.from_config);
  EXPECT_FALSE(d.dense.enabled);
  // Live sensors need their devices, and a rig unless they are a log.
  const std::pair<std::string, const char*> live_cases[] = {
      {"estimator: {backend: vo}\n", "x.yaml: drivers: missing"},
      {"drivers:\n  camera: {type: none}\n", "x.yaml: rig: missing"},
  };
  for (const auto& [yaml, needle] : live_cases) {
    try {
      (void)kestrel::tools::live_config_from_yaml(yaml, "x.yaml");
      ADD_FAILURE() << "accepted as a live config: " << yaml;
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  }
}

TEST(ConfigFileReader, SectionTableHasOneOwnerPerSection) {
  const auto& sections = kestrel::tools::config_sections();
  std::set<std::string> names;
  for (const auto& s : sections) {
    EXPECT_TRUE(names.insert(s.name).second) << s.name << " has two owners";
    EXPECT_FALSE(s.owner.empty()) << s.name;
  }
  for (const char* n : {"rig", "drivers", "threads", "mavlink", "record", "ros2", "dense", "viewer"})
    EXPECT_EQ(names.count(n), 1u) << n;
  for (const std::string& e : kestrel::tools::estimator_config_sections()) EXPECT_EQ(names.count(e), 1u) << e;
}

// Each owner's errors reach the caller with the file named; a misspelt
// section is an error (it used to be ignored by every reader, so its keys
// silently kept their defaults).
TEST(ConfigFileReader, BadSectionsNameFileLineAndKey) {
  const std::string misspelt = file_error_of("estimator: {backend: vo}\n\nwindw: {recent_frames: 3}\n");
  EXPECT_EQ(misspelt.rfind("x.yaml:3: windw: unknown section (expected one of: rig, drivers, threads,", 0),
            0u)
      << misspelt;
  EXPECT_NE(misspelt.find(", window,"), std::string::npos) << misspelt;
  EXPECT_NE(misspelt.find("dense, viewer)"), std::string::npos) << misspelt;
  const std::pair<const char*, const char*> cases[] = {
      {"threads:\n  kst-nope: {cpu: 1}\n", "threads.kst-nope: unknown thread"},
      {"mavlink:\n  sysid: 0\n", "mavlink.sysid"},
      {"record:\n  image_codec: gif\n", "record.image_codec"},
      {"ros2:\n  map_points_rate_hz: 99\n", "ros2.map_points_rate_hz"},
      {"dense:\n  voxel_size: 0.1\n", "dense.voxel_size: unknown key"},
      {"viewer:\n  dense_max_kbs: 1\n", "viewer.dense_max_kbs: unknown key"},
      {"drivers:\n  camera: {type: kinect}\n", "drivers.camera.type"},
      {"rig: /nonexistent/rig.yaml\n", "/nonexistent/rig.yaml"},
      {"rig:\n  camera: {fx: 1}\n", "rig.camera.fx"},
      {"window: {recent_frames: x}\n", "window.recent_frames"},
      {"- a list\n", "expected a mapping of sections"},
      {"window: [\n", "YAML syntax error"},
  };
  for (const auto& [yaml, needle] : cases) {
    const std::string e = file_error_of(yaml);
    EXPECT_NE(e.find(needle), std::string::npos) << yaml << " -> " << e;
    EXPECT_EQ(e.rfind(e.rfind("/nonexistent", 0) == 0 ? "/nonexistent" : "x.yaml", 0), 0u) << e;
  }
}

// docs/config.md's "One file" table lists every section with its owner.
TEST(ConfigDocs, SectionTableListsEverySectionAndItsOwner) {
  const std::string doc = slurp(std::string(KESTREL_SOURCE_DIR) + "/docs/config.md");
  for (const auto& s : kestrel::tools::config_sections()) {
    EXPECT_NE(doc.find("| `" + s.name + ":` | " + s.owner + " |"), std::string::npos)
        << "docs/config.md's section table lacks the row | `" << s.name << ":` | " << s.owner << " |";
  }
}

TEST(ConfigDocs, ReferenceTableMatchesTheCode) {
  const std::string doc = slurp(std::string(KESTREL_SOURCE_DIR) + "/docs/config.md");
  const std::string marker = "<!-- generated: kestrel config --markdown -->\n";
  const size_t at = doc.find(marker);
  ASSERT_NE(at, std::string::npos) << "docs/config.md lost its generated-table marker";
  EXPECT_EQ(doc.substr(at + marker.size()), kestrel::tools::estimator_config_reference_markdown())
      << "docs/config.md's table disagrees with the options table: regenerate it with `kestrel config "
         "--markdown`";
}

TEST(ConfigCli, PrintConfigPrintsTheEffectiveSettingsAndExits) {
  const std::string dir = kestrel::test::temp_dir("cfg_cli_" + std::to_string(getpid()));
  {
    std::ofstream f(dir + "/c.yaml");
    f << "estimator: {backend: vo}\nfrontend: {orb: {n_features: 222}}\nthreads: {}\n";
  }
  auto r = kestrel::test::run_kestrel("replay --config " + dir + "/c.yaml --print-config");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("backend: vo"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("n_features: 222"), std::string::npos) << r.out;
  // --estimator overrides the file's backend.
  r = kestrel::test::run_kestrel("replay --config " + dir + "/c.yaml --estimator ekf --print-config");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("backend: ekf"), std::string::npos) << r.out;
  // With a log, the log is opened first: a missing one is an error.
  r = kestrel::test::run_kestrel("replay /nonexistent/x.klog --print-config");
  EXPECT_NE(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("/nonexistent/x.klog"), std::string::npos) << r.out;
  // A bad key fails the command with the file and key named.
  {
    std::ofstream f(dir + "/bad.yaml");
    f << "window:\n  recentframes: 3\n";
  }
  r = kestrel::test::run_kestrel("replay --config " + dir + "/bad.yaml --print-config");
  EXPECT_NE(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("bad.yaml:2: window.recentframes: unknown key"), std::string::npos) << r.out;
  // So does a misspelt section, in replay as in run (the one reader checks every section).
  {
    std::ofstream f(dir + "/typo.yaml");
    f << "windw:\n  recent_frames: 3\n";
  }
  for (const char* cmd :
       {"replay --print-config --config ", "config --config ", "run --print-config --config "}) {
    r = kestrel::test::run_kestrel(cmd + dir + "/typo.yaml");
    EXPECT_NE(r.code, 0) << cmd << r.out;
    EXPECT_NE(r.out.find("typo.yaml:1: windw: unknown section"), std::string::npos) << cmd << r.out;
  }
  // kestrel config prints the same as --print-config.
  const auto a = kestrel::test::run_kestrel("config --config " + dir + "/c.yaml");
  const auto b = kestrel::test::run_kestrel("replay --config " + dir + "/c.yaml --print-config");
  EXPECT_EQ(a.out, b.out);
}

// The tool-side sections (dense:, viewer:) are printed beside the estimator's,
// and what is printed reads back to the same print.
TEST(ConfigCli, PrintConfigPrintsTheDenseAndViewerSectionsAndReadsBack) {
  const std::string dir = kestrel::test::temp_dir("cfg_dense_" + std::to_string(getpid()));
  {
    std::ofstream f(dir + "/c.yaml");
    f << "dense: {voxel_size_m: 0.1, live_reanchor: true}\nviewer: {dense_max_kbps: 300}\n";
  }
  const auto r = kestrel::test::run_kestrel("replay --config " + dir + "/c.yaml --print-config");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("\ndense:\n  enabled: false\n  voxel_size_m: 0.1\n"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("  live_reanchor: true\n"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("\nviewer:\n  dense_max_kbps: 300\n  dense_period_s: 0.5\n"), std::string::npos)
      << r.out;
  {
    std::ofstream f(dir + "/printed.yaml");
    f << r.out;
  }
  const auto back = kestrel::test::run_kestrel("replay --config " + dir + "/printed.yaml --print-config");
  ASSERT_EQ(back.code, 0) << back.out;
  EXPECT_EQ(back.out, r.out);
  const auto cfg = kestrel::test::run_kestrel("config --config " + dir + "/c.yaml");
  EXPECT_EQ(cfg.out, r.out);
}

TEST(ConfigCli, MetricsJsonCarriesTheSettings) {
  const std::string dir = kestrel::test::temp_dir("cfg_metrics_" + std::to_string(getpid()));
  auto r = kestrel::test::run_kestrel(
      "sim --scenario hover --duration 3 --seed 2 --width 160 --height 120 --out " + dir + "/h.klog");
  ASSERT_EQ(r.code, 0) << r.out;
  {
    std::ofstream f(dir + "/c.yaml");
    f << "window: {imu_noise_inflation: 12.5, keyframes: 4}\n";
  }
  r = kestrel::test::run_kestrel("replay " + dir + "/h.klog --config " + dir + "/c.yaml -q --metrics-out " +
                                 dir + "/m.json");
  ASSERT_EQ(r.code, 0) << r.out;
  const std::string m = slurp(dir + "/m.json");
  EXPECT_NE(m.find("\"config\""), std::string::npos) << m.substr(0, 400);
  EXPECT_NE(m.find("\"window.imu_noise_inflation\": 12.5"), std::string::npos);
  EXPECT_NE(m.find("\"window.keyframes\": 4"), std::string::npos);
  EXPECT_NE(m.find("\"frontend.lonsc_variant\": \"tuned\""), std::string::npos);
}

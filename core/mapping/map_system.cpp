#include "kestrel/core/map_system.hpp"

#include <algorithm>
#include <sstream>
#include <stdexcept>

#include "kestrel/core/map_file.hpp"
#include "kestrel/core/pose_graph.hpp"
#include "kestrel/rt/clock.hpp"

namespace kestrel::core {

std::string MapSystemOptions::validate() const {
  return map.validate() + closing.validate() + global_ba.validate();
}

MapSystem::MapSystem(const MapCamera& cam, int features_per_keyframe, const MapSystemOptions& opt)
    : opt_(opt), cam_(cam) {
  const std::string err = opt.validate();
  if (!err.empty()) throw std::invalid_argument("MapSystemOptions:\n" + err);
  map_ = std::make_unique<Map>(opt.map, features_per_keyframe, opt.loop ? opt.vocabulary : nullptr);
  mapper_ = std::make_unique<LocalMapper>(*map_, cam);
  closer_ = std::make_unique<LoopCloser>(*map_, cam, opt.closing);
  if (map_->vocabulary() != nullptr) reloc_ = std::make_unique<Relocaliser>(*map_, cam, opt.closing);
  if (opt.loop && opt.global_ba.enabled) gba_ = std::make_unique<GlobalBundleAdjustment>(cam, opt.global_ba);
  if (opt.map_in) {
    const std::string where = opt.map_in_path.empty() ? std::string("the map") : opt.map_in_path;
    if (!opt.mapping) throw std::runtime_error(where + ": a map to start from needs the map (--mapping on)");
    MapFileInfo info;
    const std::string e = decode_map(opt.map_in->data(), opt.map_in->size(), cam, map_.get(), &info);
    if (!e.empty()) throw std::runtime_error(where + ": not a usable map: " + e);
    if (reloc_ == nullptr) {
      throw std::runtime_error(where +
                               ": a loaded map is found by relocalisation, which needs the loop on and a "
                               "vocabulary (--loop on, map.vocabulary)");
    }
    last_kf_ = map_->newest_keyframe();
    loaded_unfound_ = info.keyframes > 0;
  }
  packets_.reset(new KeyframePacket[kPackets]);
  packet_features_.reset(new KeyframeFeature[static_cast<size_t>(kPackets) * features_per_keyframe]);
  for (int i = 0; i < kPackets; ++i)
    packets_[i].features = packet_features_.get() + i * features_per_keyframe;
  for (int i = kPackets - 1; i >= 0; --i) free_packets_[n_free_packets_++] = i;
  const int cap = std::max(1, opt.map.update_max_points);
  updates_.reset(new MapUpdate[kUpdates]);
  update_points_.reset(new MapPointUpdate[static_cast<size_t>(kUpdates) * cap]);
  for (int i = 0; i < kUpdates; ++i) {
    updates_[i].points = update_points_.get() + static_cast<size_t>(i) * cap;
    (void)update_free_.try_push(static_cast<uint8_t>(i));
  }
  state_.active = true;
  state_.localized = !loaded_unfound_;
  state_.keyframes = static_cast<uint32_t>(map_->num_keyframes());  // a loaded map's, from the start
  state_.points = static_cast<uint32_t>(map_->num_points());
  frame_.publish(state_);
}

MapSystem::~MapSystem() = default;

void MapSystem::enable_depth_grid(const CameraIntrinsics& rgb, const DepthModel& depth) {
  if (grid_sampler_.enabled()) return;
  const DepthGridShape shape =
      DepthGridShape::make(opt_.map.depth_grid_cols, cam_.K, cam_.width, cam_.height);
  if (shape.cells() <= 0) return;
  grid_sampler_ = DepthGridSampler(shape, rgb, depth, opt_.map.depth_grid_edge_rel);
  packet_grids_.reset(new uint16_t[static_cast<size_t>(kPackets) * shape.cells()]());
  for (int i = 0; i < kPackets; ++i)
    packets_[i].grid_z_mm = packet_grids_.get() + static_cast<size_t>(i) * shape.cells();
  map_->enable_depth_grids(shape.cells());
  closer_->set_depth_grid(shape);
}

// ---- tracking side -------------------------------------------------------------

void MapSystem::fill_depth_grid(KeyframePacket* p, const ImageView& depth) const {
  if (p == nullptr || p->grid_z_mm == nullptr) return;
  p->grid_n = grid_sampler_.sample(depth, p->grid_z_mm);
}

KeyframePacket* MapSystem::begin_keyframe() {
  while (const uint8_t* s = packet_free_.front()) {
    free_packets_[n_free_packets_++] = *s;
    packet_free_.pop();
  }
  if (n_free_packets_ == 0) {
    overrun_.fetch_add(1, std::memory_order_relaxed);
    return nullptr;
  }
  KeyframePacket* p = &packets_[free_packets_[--n_free_packets_]];
  p->n = 0;
  p->chain = 0;
  p->grid_n = 0;
  return p;
}

void MapSystem::cancel_keyframe(KeyframePacket* p) {
  if (p != nullptr) free_packets_[n_free_packets_++] = static_cast<int>(p - packets_.get());
}

void MapSystem::submit_keyframe(KeyframePacket* p) {
  p->seq = next_seq_++;
  in_flight_.fetch_add(1, std::memory_order_acq_rel);
  // Cannot fail: the ring holds more than the pool.
  (void)packet_todo_.try_push(static_cast<uint8_t>(p - packets_.get()));
}

const MapUpdate* MapSystem::take_update() {
  const MapUpdate* newest = nullptr;
  while (const uint8_t* s = update_ready_.front()) {
    if (newest != nullptr) (void)update_free_.try_push(static_cast<uint8_t>(newest - updates_.get()));
    newest = &updates_[*s];
    update_ready_.pop();
  }
  return newest;
}

void MapSystem::release_update(const MapUpdate* u) {
  if (u == nullptr) return;
  applied_.fetch_add(1, std::memory_order_relaxed);
  (void)update_free_.try_push(static_cast<uint8_t>(u - updates_.get()));
}

MapFrameState MapSystem::frame() const {
  MapFrameState s;
  frame_.read(s);
  return s;
}

// ---- mapping thread ------------------------------------------------------------

bool MapSystem::mapping_step() {
  const uint8_t* s = packet_todo_.front();
  if (s == nullptr) return false;
  const int slot = *s;
  packet_todo_.pop();
  const int64_t t0 = rt::now_ns();
  KeyframePacket& pk = packets_[slot];
  int kf = -1;
  if (opt_.mapping && localise(pk)) {
    const int64_t min_dt = static_cast<int64_t>(opt_.map.min_keyframe_interval_s * 1e9);
    const bool too_soon =
        last_kf_ >= 0 && map_->keyframe_used(last_kf_) && pk.t_ns - map_->keyframe(last_kf_).t_ns < min_dt;
    if (!too_soon) kf = mapper_->insert(pk, state_.T_map_odom(), last_kf_);
  }
  if (kf >= 0) {
    last_kf_ = kf;
    ++counters_.keyframes_mapped;
    publish_update(kf, pk.seq);
  }
  publish_frame();
  const int64_t dt_ns = rt::now_ns() - t0;
  mapping_latency_.record(dt_ns);
  if (mapping_elapsed_ != nullptr) mapping_elapsed_->add_elapsed(dt_ns);
  mirror(mapping_mirror_);
  // The packet goes back before the loop thread looks at the keyframe: the map holds a copy.
  (void)packet_free_.try_push(static_cast<uint8_t>(slot));
  if (opt_.loop && kf >= 0 && loop_todo_.try_push(kf)) return true;
  in_flight_.fetch_sub(1, std::memory_order_acq_rel);
  return true;
}

bool MapSystem::localise(const KeyframePacket& pk) {
  if (state_.localized && pk.chain == chain_) return true;
  if (state_.localized) {
    // The odometry lost its chain: until the place is found again, where
    // this keyframe sits in the map is not known.
    state_.localized = false;
    lost_since_ns_ = pk.t_ns;
    if (reloc_) reloc_->reset();
  }
  if (lost_since_ns_ < 0) lost_since_ns_ = pk.t_ns;
  const Eigen::Isometry3d T_MO = state_.T_map_odom();
  Eigen::Isometry3d correction;
  if (reloc_ == nullptr || map_->num_keyframes() == 0) {
    // Nothing to find it in (no vocabulary, or an empty map): go on as before.
  } else if (reloc_->relocalise(pk.features, pk.n, T_MO * pk.T_WC, pk.seq, &correction)) {
    // The odometry stays; the map frame moves against it.
    state_.set_T_map_odom(project_4dof(correction * T_MO));
    ++state_.alignment;
    ++state_.relocalisations;
    realigned_ = true;
    loaded_unfound_ = false;
  } else if (loaded_unfound_ ||
             pk.t_ns - lost_since_ns_ < static_cast<int64_t>(opt_.closing.reloc_timeout_s * 1e9)) {
    ++counters_.keyframes_lost;
    return false;
  } else {
    // Lost mid-flight and not found: the map goes on in the odometry's
    // current alignment (off by what it drifted while lost; a loop may
    // correct it later) rather than stop growing.
    ++counters_.reloc_timeouts;
  }
  state_.localized = true;
  chain_ = pk.chain;
  lost_since_ns_ = -1;
  return true;
}

std::vector<uint8_t> MapSystem::save() const { return encode_map(*map_, cam_); }

void MapSystem::publish_update(int kf, uint64_t seq) {
  const uint8_t* s = update_free_.front();
  if (s == nullptr) {
    ++counters_.updates_skipped;
    return;
  }
  MapUpdate& u = updates_[*s];
  update_free_.pop();
  u.keyframe_seq = seq;
  u.realigned = realigned_;
  realigned_ = false;
  u.n = mapper_->export_points(kf, state_.T_map_odom().inverse(), u.points, opt_.map.update_max_points);
  state_.keyframes = static_cast<uint32_t>(map_->num_keyframes());
  state_.points = static_cast<uint32_t>(map_->num_points());
  u.frame = state_;
  (void)update_ready_.try_push(static_cast<uint8_t>(&u - updates_.get()));
  ++counters_.updates_published;
}

void MapSystem::publish_frame() {
  state_.keyframes = static_cast<uint32_t>(map_->num_keyframes());
  state_.points = static_cast<uint32_t>(map_->num_points());
  frame_.publish(state_);
}

// ---- loop thread ---------------------------------------------------------------

bool MapSystem::loop_step() {
  // The odometry stays where it is; the map frame moves against it: W sits in
  // M where keyframe kf's corrected pose says (4 DoF: both see gravity). This
  // also takes in what local BA moved since the last change.
  auto realign_to = [this](int kf) {
    const MapKeyframe& N = map_->keyframe(kf);
    state_.set_T_map_odom(project_4dof(N.T_MC * N.T_WC.inverse()));
    ++state_.alignment;
    realigned_ = true;
  };
  if (gba_ && gba_->snapshotted()) return false;  // global_ba_step() first
  if (gba_ && gba_->solved()) {
    if (gba_->apply(*map_) && map_->newest_keyframe() >= 0) {
      realign_to(map_->newest_keyframe());
      publish_frame();
    }
    in_flight_.fetch_sub(1, std::memory_order_acq_rel);  // taken by the snapshot
    mirror(loop_mirror_);
    return true;
  }
  const int32_t* k = loop_todo_.front();
  if (k == nullptr) return false;
  loop_todo_.pop();
  const int64_t t0 = rt::now_ns();
  const LoopClosure c = closer_->process(*k);
  if (c.closed) {
    realign_to(c.newest);
    ++state_.loop_closures;
    for (int i = 0; i < 3; ++i) {
      if (map_->keyframe_used(c.match.query))
        state_.loop_p_M_query[i] = map_->keyframe(c.match.query).T_MC.translation()[i];
      if (map_->keyframe_used(c.match.candidate))
        state_.loop_p_M_candidate[i] = map_->keyframe(c.match.candidate).T_MC.translation()[i];
    }
    publish_frame();
    // The map is held (a deterministic pace waits) until the solution is back.
    if (gba_) {
      std::vector<GlobalBaLoop> loops;
      for (const LoopCloser::LoopEdge& e : closer_->loop_edges())
        loops.push_back({e.id_a, e.id_b, e.R_ab, e.t_ab, e.sigma_m, e.sigma_rad});
      if (gba_->snapshot(*map_, loops)) in_flight_.fetch_add(1, std::memory_order_acq_rel);
    }
  }
  const int64_t dt_ns = rt::now_ns() - t0;
  loop_latency_.record(dt_ns);
  if (loop_elapsed_ != nullptr) loop_elapsed_->add_elapsed(dt_ns);
  mirror(loop_mirror_);
  in_flight_.fetch_sub(1, std::memory_order_acq_rel);
  return true;
}

bool MapSystem::global_ba_step() {
  if (!gba_ || !gba_->snapshotted()) return false;
  const int64_t t0 = rt::now_ns();
  (void)gba_->solve();
  const int64_t dt_ns = rt::now_ns() - t0;
  gba_latency_.record(dt_ns);
  if (gba_elapsed_ != nullptr) gba_elapsed_->add_elapsed(dt_ns);
  mirror(loop_mirror_);
  return true;
}

void MapSystem::register_counters(rt::PerfRegistry& r) {
  const auto add = [&r](std::vector<Mirror>& to, const char* path, const uint64_t* figure,
                        const std::atomic<uint64_t>* shared = nullptr) {
    to.push_back({r.register_counter(path, rt::PerfKind::kCount), figure, shared});
  };
  mapping_mirror_.clear();
  loop_mirror_.clear();
  std::vector<Mirror>& m = mapping_mirror_;
  add(m, "map.keyframes_mapped", &counters_.keyframes_mapped);
  add(m, "map.keyframes_overrun", nullptr, &overrun_);
  add(m, "map.keyframes_lost", &counters_.keyframes_lost);
  add(m, "map.reloc_timeouts", &counters_.reloc_timeouts);
  add(m, "map.updates_published", &counters_.updates_published);
  add(m, "map.updates_applied", nullptr, &applied_);
  add(m, "map.updates_skipped", &counters_.updates_skipped);
  const LocalMapperStats& l = mapper_->stats();
  add(m, "map.local.keyframes", &l.keyframes);
  add(m, "map.local.refused_full", &l.refused_full);
  add(m, "map.local.points_created", &l.points_created);
  add(m, "map.local.points_fused", &l.points_fused);
  add(m, "map.local.observations_added", &l.observations_added);
  add(m, "map.local.points_culled", &l.points_culled);
  add(m, "map.local.keyframes_culled", &l.keyframes_culled);
  add(m, "map.local.ba_runs", &l.ba_runs);
  add(m, "map.local.ba_failures", &l.ba_failures);
  add(m, "map.local.ba_outliers", &l.ba_outliers);
  // Relocalisation runs on the mapping thread (localise()).
  if (reloc_) {
    const RelocStats& q = reloc_->stats();
    add(m, "map.reloc.queries", &q.queries);
    add(m, "map.reloc.candidates", &q.candidates);
    add(m, "map.reloc.verified", &q.verified);
    add(m, "map.reloc.rejected_ambiguous", &q.rejected_ambiguous);
    add(m, "map.reloc.rejected_consistency", &q.rejected_consistency);
    add(m, "map.reloc.relocalisations", &q.relocalisations);
  }
  mapping_elapsed_ = r.register_counter("map.mapping_step", rt::PerfKind::kElapsed);
  if (!opt_.loop) return;
  std::vector<Mirror>& o = loop_mirror_;
  const LoopStats& c = closer_->stats();
  add(o, "map.loop.queries", &c.queries);
  add(o, "map.loop.candidates", &c.candidates);
  add(o, "map.loop.geometric_candidates", &c.geometric_candidates);
  add(o, "map.loop.verified", &c.verified);
  add(o, "map.loop.surface_tried", &c.surface_tried);
  add(o, "map.loop.surface_aligned", &c.surface_aligned);
  add(o, "map.loop.rejected_inliers", &c.rejected_inliers);
  add(o, "map.loop.rejected_drift", &c.rejected_drift);
  add(o, "map.loop.rejected_planar", &c.rejected_planar);
  add(o, "map.loop.rejected_consistency", &c.rejected_consistency);
  add(o, "map.loop.skipped_insignificant", &c.skipped_insignificant);
  add(o, "map.loop.closures", &c.closures);
  add(o, "map.loop.pose_graph_failures", &c.pose_graph_failures);
  add(o, "map.loop.points_merged", &c.points_merged);
  loop_elapsed_ = r.register_counter("map.loop_step", rt::PerfKind::kElapsed);
  if (!gba_) return;
  const GlobalBaStats& g = gba_->stats();
  add(o, "map.global_ba.runs", &g.runs);
  add(o, "map.global_ba.failures", &g.failures);
  add(o, "map.global_ba.followed_keyframes", &g.followed_keyframes);
  add(o, "map.global_ba.followed_points", &g.followed_points);
  add(o, "map.global_ba.lost_keyframes", &g.lost_keyframes);
  gba_elapsed_ = r.register_counter("map.global_ba.solve", rt::PerfKind::kElapsed);
}

void MapSystem::mirror(const std::vector<Mirror>& mirrors) noexcept {
  for (const Mirror& x : mirrors)
    x.counter->set(x.figure != nullptr ? *x.figure : x.shared->load(std::memory_order_relaxed));
}

void MapSystem::mirror_counters() noexcept {
  mirror(mapping_mirror_);
  mirror(loop_mirror_);
}

std::vector<MapKeyframePose> MapSystem::keyframe_poses(const Eigen::Isometry3d& T_CB) const {
  std::vector<MapKeyframePose> out;
  const Map& m = *map_;
  // A loaded map's keyframes (session > 0) were taken in another flight's odometry frame.
  m.for_each_keyframe([&](int k) {
    const MapKeyframe& K = m.keyframe(k);
    if (K.session == 0) out.push_back({K.t_ns, K.T_MC * T_CB, K.T_WC * T_CB});
  });
  std::sort(out.begin(), out.end(),
            [](const MapKeyframePose& a, const MapKeyframePose& b) { return a.t_ns < b.t_ns; });
  return out;
}

std::string MapSystem::summary() const {
  const LocalMapperStats& m = mapper_->stats();
  std::ostringstream o;
  o << "map: " << map_->num_keyframes() << " keyframes, " << map_->num_points()
    << " points; keyframes mapped " << counters_.keyframes_mapped << " (overrun " << overrun_.load()
    << ", refused full " << m.refused_full << "), culled " << m.keyframes_culled << "; points created "
    << m.points_created << ", fused " << m.points_fused << ", culled " << m.points_culled
    << ", observations by projection " << m.observations_added << "; local BA " << m.ba_runs << " (failed "
    << m.ba_failures << ", outliers " << m.ba_outliers << "); updates " << counters_.updates_published
    << " published, " << applied_.load() << " applied, " << counters_.updates_skipped
    << " skipped; lost keyframes " << counters_.keyframes_lost << ", relocalisation timeouts "
    << counters_.reloc_timeouts;
  const LoopStats& l = closer_->stats();
  o << "; loop: " << l.queries << " queries, " << l.candidates << " candidates, " << l.verified
    << " verified, rejected " << l.rejected_inliers << " inliers / " << l.rejected_planar << " planar / "
    << l.rejected_drift << " drift / " << l.rejected_consistency << " consistency, "
    << l.skipped_insignificant << " within their uncertainty, " << l.closures << " closed (pose graph failed "
    << l.pose_graph_failures << "), " << l.points_merged << " points merged; surface verification "
    << l.surface_tried << " tried, " << l.surface_aligned << " aligned";
  if (gba_) {
    const GlobalBaStats& g = gba_->stats();
    o << "; global BA: " << g.runs << " runs (failed " << g.failures << "), last " << g.keyframes
      << " keyframes (+" << g.fixed_keyframes << " held), " << g.points << " points, " << g.observations
      << " observations, " << g.odometry_factors << " odometry factors, " << g.loop_factors
      << " loop factors, " << g.outliers << " outliers, cost " << g.initial_cost << " -> " << g.final_cost
      << ", largest keyframe move " << g.max_keyframe_move_m << " m; followed " << g.followed_keyframes
      << " keyframes / " << g.followed_points << " points mapped during the solves, " << g.lost_keyframes
      << " culled; solve p50 " << 1e-6 * static_cast<double>(gba_latency_.percentile(50)) << " ms, max "
      << 1e-6 * static_cast<double>(gba_latency_.max()) << " ms";
  }
  if (reloc_) {
    const RelocStats& r = reloc_->stats();
    o << "; relocalisation: " << r.queries << " queries, " << r.candidates << " candidates, " << r.verified
      << " verified, rejected " << r.rejected_ambiguous << " ambiguous / " << r.rejected_consistency
      << " consistency, " << r.relocalisations << " relocalised";
  }
  return o.str();
}

}  // namespace kestrel::core

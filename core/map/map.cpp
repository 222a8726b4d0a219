#include "kestrel/core/map.hpp"

#include <algorithm>
#include <sstream>
#include <stdexcept>

namespace kestrel::core {

std::string MapOptions::validate() const {
  std::ostringstream e;
  if (max_keyframes < 2) e << "max_keyframes: at least 2\n";
  if (max_points < 16) e << "max_points: at least 16\n";
  if (ba_keyframes < 1) e << "ba_keyframes: at least 1\n";
  if (ba_fixed_keyframes < 0) e << "ba_fixed_keyframes: >= 0\n";
  if (ba_iterations < 1) e << "ba_iterations: at least 1\n";
  if (!(ba_huber > 0)) e << "ba_huber: > 0\n";
  if (!(ba_outlier_chi2 > 0)) e << "ba_outlier_chi2: > 0\n";
  if (!(ba_gravity_sigma_rad >= 0)) e << "ba_gravity_sigma_rad: >= 0 (0: no gravity prior)\n";
  if (!(fuse_radius_px > 0)) e << "fuse_radius_px: > 0\n";
  if (fuse_max_hamming < 0 || fuse_max_hamming > 256) e << "fuse_max_hamming: in 0..256\n";
  if (!(cull_keyframe_redundancy > 0 && cull_keyframe_redundancy <= 1))
    e << "cull_keyframe_redundancy: in (0, 1]\n";
  if (cull_point_min_keyframes < 1) e << "cull_point_min_keyframes: at least 1\n";
  if (!(cull_point_min_found_ratio >= 0 && cull_point_min_found_ratio <= 1))
    e << "cull_point_min_found_ratio: in [0, 1]\n";
  if (update_max_points < 0) e << "update_max_points: >= 0\n";
  if (!(neighbour_radius_m >= 0)) e << "neighbour_radius_m: >= 0\n";
  if (!(neighbour_max_angle_rad >= 0)) e << "neighbour_max_angle_rad: >= 0\n";
  if (!(point_sigma_floor_m > 0)) e << "point_sigma_floor_m: > 0\n";
  if (point_min_keyframes_for_prior < 1) e << "point_min_keyframes_for_prior: at least 1\n";
  if (!(min_keyframe_interval_s >= 0)) e << "min_keyframe_interval_s: >= 0\n";
  if (depth_grid_cols < 0 || depth_grid_cols > 640) e << "depth_grid_cols: in 0..640\n";
  if (!(depth_grid_edge_rel > 0)) e << "depth_grid_edge_rel: > 0\n";
  return e.str();
}

Map::Map(const MapOptions& opt, int features_per_keyframe, std::shared_ptr<const Vocabulary> vocabulary)
    : opt_(opt), fpk_(features_per_keyframe), vocab_(std::move(vocabulary)) {
  const std::string err = opt.validate();
  if (!err.empty()) throw std::invalid_argument("MapOptions:\n" + err);
  if (fpk_ < 1) throw std::invalid_argument("Map: features_per_keyframe must be >= 1");
  const size_t K = static_cast<size_t>(opt.max_keyframes), P = static_cast<size_t>(opt.max_points);
  kfs_.reset(new MapKeyframe[K]);
  features_.reset(new KeyframeFeature[K * static_cast<size_t>(fpk_)]);
  point_of_.reset(new int32_t[K * static_cast<size_t>(fpk_)]);
  std::fill(point_of_.get(), point_of_.get() + K * static_cast<size_t>(fpk_), -1);
  pts_.reset(new MapPoint[P]);
  free_kf_.reserve(K);
  for (int k = opt.max_keyframes - 1; k >= 0; --k) free_kf_.push_back(k);
  free_pt_.reserve(P);
  for (int p = opt.max_points - 1; p >= 0; --p) free_pt_.push_back(p);
  size_t n = 1;
  while (n < 2 * P) n <<= 1;
  idx_key_.reset(new uint32_t[n]);
  idx_val_.reset(new int32_t[n]);
  std::fill(idx_val_.get(), idx_val_.get() + n, -1);
  idx_mask_ = static_cast<uint32_t>(n - 1);
  covis_count_.reset(new int32_t[K]);
  std::fill(covis_count_.get(), covis_count_.get() + K, 0);
  covis_list_.reset(new int32_t[K]);
  if (vocab_ && !vocab_->empty()) {
    db_ = std::make_unique<KeyframeDatabase>(vocab_->words(), opt.max_keyframes, opt.max_keyframes * fpk_);
    bow_.reset(new BowEntry[K * static_cast<size_t>(fpk_)]);
    words_.reset(new uint32_t[K * static_cast<size_t>(fpk_)]);
    desc_scratch_.reset(new OrbDescriptor[static_cast<size_t>(fpk_)]);
  } else {
    vocab_.reset();
  }
}

Map::~Map() = default;

namespace {
uint32_t hash_id(uint32_t id) {
  id ^= id >> 16;
  id *= 0x7feb352dU;
  id ^= id >> 15;
  id *= 0x846ca68bU;
  id ^= id >> 16;
  return id;
}
}  // namespace

void Map::index_insert(uint32_t id, int32_t p) {
  uint32_t h = hash_id(id) & idx_mask_;
  while (idx_val_[h] >= 0 && idx_key_[h] != id) h = (h + 1) & idx_mask_;
  idx_key_[h] = id;
  idx_val_[h] = p;
}

int Map::find_point(uint32_t id) const {
  if (id == 0) return -1;
  uint32_t h = hash_id(id) & idx_mask_;
  while (idx_val_[h] >= 0) {
    if (idx_key_[h] == id) return idx_val_[h];
    h = (h + 1) & idx_mask_;
  }
  return -1;
}

void Map::index_erase(uint32_t id) {
  uint32_t h = hash_id(id) & idx_mask_;
  while (idx_val_[h] >= 0 && idx_key_[h] != id) h = (h + 1) & idx_mask_;
  if (idx_val_[h] < 0) return;
  // Backward-shift deletion keeps every probe chain unbroken.
  uint32_t hole = h;
  for (uint32_t j = (hole + 1) & idx_mask_; idx_val_[j] >= 0; j = (j + 1) & idx_mask_) {
    const uint32_t home = hash_id(idx_key_[j]) & idx_mask_;
    const bool movable = hole <= j ? (home <= hole || home > j) : (home <= hole && home > j);
    if (movable) {
      idx_key_[hole] = idx_key_[j];
      idx_val_[hole] = idx_val_[j];
      hole = j;
    }
  }
  idx_val_[hole] = -1;
}

int Map::add_keyframe(int64_t t_ns, const Eigen::Isometry3d& T_MC, const Eigen::Isometry3d& T_WC,
                      const KeyframeFeature* f, int n, int32_t parent, uint32_t session) {
  if (free_kf_.empty()) return -1;
  const int k = free_kf_.back();
  free_kf_.pop_back();
  MapKeyframe& K = kfs_[k];
  K = MapKeyframe{};
  K.id = next_kf_id_++;
  K.t_ns = t_ns;
  K.T_MC = T_MC;
  K.T_WC = T_WC;
  K.g_C = T_WC.linear().transpose() * Eigen::Vector3d(0, 0, -1);
  K.parent = keyframe_used(parent) ? parent : -1;
  K.session = session;
  K.n = std::min(n, fpk_);
  K.first_feature = k * fpk_;
  std::copy(f, f + K.n, features_.get() + K.first_feature);
  std::fill(point_of_.get() + K.first_feature, point_of_.get() + K.first_feature + fpk_, -1);
  ++n_kf_;
  if (newest_kf_ < 0 || kfs_[newest_kf_].id < K.id) newest_kf_ = k;
  if (vocab_) {
    for (int j = 0; j < K.n; ++j) desc_scratch_[j] = f[j].desc;
    BowEntry* b = bow_.get() + static_cast<size_t>(k) * fpk_;
    K.n_bow = vocab_->transform(desc_scratch_.get(), K.n, b, words_.get() + static_cast<size_t>(k) * fpk_);
    db_->add(k, b, K.n_bow);
  }
  return k;
}

void Map::enable_depth_grids(int cells) {
  if (cells <= 0 || grid_cells_ > 0) return;
  grid_cells_ = cells;
  grids_.reset(new uint16_t[static_cast<size_t>(opt_.max_keyframes) * cells]());
}

void Map::erase_keyframe(int kf) {
  if (!keyframe_used(kf)) return;
  MapKeyframe& K = kfs_[kf];
  for (int j = 0; j < K.n; ++j) {
    const int32_t p = point_of_[K.first_feature + j];
    if (p >= 0) erase_observation(p, kf);
  }
  for (int k = 0; k < opt_.max_keyframes; ++k)
    if (kfs_[k].id != 0 && kfs_[k].parent == kf) kfs_[k].parent = K.parent;
  if (db_) db_->erase(kf, bow(kf), K.n_bow);
  K.id = 0;
  --n_kf_;
  free_kf_.push_back(kf);
  if (newest_kf_ == kf) {
    newest_kf_ = -1;
    for (int k = 0; k < opt_.max_keyframes; ++k)
      if (kfs_[k].id != 0 && (newest_kf_ < 0 || kfs_[k].id > kfs_[newest_kf_].id)) newest_kf_ = k;
  }
}

int Map::add_point(uint32_t landmark_id, const Eigen::Vector3d& p_M, const OrbDescriptor& d, int level,
                   int kf, int feat) {
  if (free_pt_.empty() || landmark_id == 0 || find_point(landmark_id) >= 0) return -1;
  const int p = free_pt_.back();
  free_pt_.pop_back();
  MapPoint& P = pts_[p];
  P = MapPoint{};
  P.landmark_id = landmark_id;
  P.p_M = p_M;
  P.desc = d;
  P.level = static_cast<int16_t>(level);
  P.first_kf_id = keyframe_used(kf) ? kfs_[kf].id : 0;
  ++n_pt_;
  index_insert(landmark_id, p);
  if (keyframe_used(kf)) add_observation(p, kf, feat);
  return p;
}

bool Map::add_observation(int p, int kf, int feat) {
  if (!point_used(p) || !keyframe_used(kf) || feat < 0 || feat >= kfs_[kf].n) return false;
  MapPoint& P = pts_[p];
  int32_t& slot = point_of_[kfs_[kf].first_feature + feat];
  if (slot >= 0 || P.n_obs >= kMaxPointObservations) return false;
  for (int i = 0; i < P.n_obs; ++i)
    if (P.obs_kf[i] == kf) return false;
  P.obs_kf[P.n_obs] = kf;
  P.obs_feat[P.n_obs] = static_cast<int16_t>(feat);
  ++P.n_obs;
  slot = p;
  const float z = feature(kf, feat).depth_m;
  if (z > 0 && (P.min_depth_m <= 0 || z < P.min_depth_m)) P.min_depth_m = z;
  return true;
}

void Map::erase_observation(int p, int kf) {
  if (!point_used(p)) return;
  MapPoint& P = pts_[p];
  for (int i = 0; i < P.n_obs; ++i) {
    if (P.obs_kf[i] != kf) continue;
    point_of_[kfs_[kf].first_feature + P.obs_feat[i]] = -1;
    --P.n_obs;
    P.obs_kf[i] = P.obs_kf[P.n_obs];
    P.obs_feat[i] = P.obs_feat[P.n_obs];
    break;
  }
  if (P.n_obs == 0) erase_point(p);
}

void Map::erase_point(int p) {
  if (!point_used(p)) return;
  MapPoint& P = pts_[p];
  for (int i = 0; i < P.n_obs; ++i) point_of_[kfs_[P.obs_kf[i]].first_feature + P.obs_feat[i]] = -1;
  P.n_obs = 0;
  index_erase(P.landmark_id);
  P.landmark_id = 0;
  --n_pt_;
  free_pt_.push_back(p);
}

void Map::merge_point(int from, int into) {
  if (from == into || !point_used(from) || !point_used(into)) return;
  MapPoint& F = pts_[from];
  MapPoint& I = pts_[into];
  for (int i = 0; i < F.n_obs; ++i) {
    const int kf = F.obs_kf[i], feat = F.obs_feat[i];
    point_of_[kfs_[kf].first_feature + feat] = -1;
    add_observation(into, kf, feat);  // refused when `into` is seen by kf already or is full
  }
  I.visible += F.visible;
  I.found += F.found;
  F.n_obs = 0;
  erase_point(from);
}

uint32_t Map::fresh_landmark_id() {
  uint32_t id = next_fresh_id_++;
  if (next_fresh_id_ == 0) next_fresh_id_ = 0x80000000u;
  while (find_point(id) >= 0) id = next_fresh_id_++;
  return id;
}

void Map::set_next_ids(uint32_t kf_id, uint32_t fresh_id) {
  next_kf_id_ = std::max(next_kf_id_, kf_id);
  next_fresh_id_ = std::max(next_fresh_id_, fresh_id);
}

int Map::covisible(int kf, int min_shared, int max, int32_t* kf_out, int32_t* shared_out) const {
  if (!keyframe_used(kf)) return 0;
  const MapKeyframe& K = kfs_[kf];
  int n_list = 0;
  for (int j = 0; j < K.n; ++j) {
    const int32_t p = point_of_[K.first_feature + j];
    if (p < 0) continue;
    const MapPoint& P = pts_[p];
    for (int i = 0; i < P.n_obs; ++i) {
      const int o = P.obs_kf[i];
      if (o == kf) continue;
      if (covis_count_[o]++ == 0) covis_list_[n_list++] = o;
    }
  }
  int n = 0;
  for (int i = 0; i < n_list; ++i) {
    const int o = covis_list_[i];
    if (covis_count_[o] >= min_shared) {
      covis_list_[n++] = o;
    } else {
      covis_count_[o] = 0;
    }
  }
  std::sort(covis_list_.get(), covis_list_.get() + n, [&](int32_t a, int32_t b) {
    return covis_count_[a] != covis_count_[b] ? covis_count_[a] > covis_count_[b] : kfs_[a].id > kfs_[b].id;
  });
  const int out = std::min(n, max);
  for (int i = 0; i < n; ++i) {
    if (i < out) {
      kf_out[i] = covis_list_[i];
      if (shared_out != nullptr) shared_out[i] = covis_count_[covis_list_[i]];
    }
    covis_count_[covis_list_[i]] = 0;
  }
  return out;
}

}  // namespace kestrel::core

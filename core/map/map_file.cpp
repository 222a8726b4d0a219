#include "kestrel/core/map_file.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "kestrel/core/bytes.hpp"

namespace kestrel::core {

namespace {

void put_pose(ByteWriter& w, const Eigen::Isometry3d& T) {
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) w.f64(T.matrix()(r, c));
}

// A pose from the file: finite, and its rotation a rotation (a damaged file
// that still passed the CRC, or a writer's bug, must not reach the solver).
bool get_pose(ByteReader& r, Eigen::Isometry3d* T) {
  Eigen::Matrix<double, 3, 4> m;
  for (int i = 0; i < 3; ++i)
    for (int c = 0; c < 4; ++c) m(i, c) = r.f64();
  if (!r.ok() || !m.allFinite()) return false;
  const Eigen::Matrix3d R = m.leftCols<3>();
  if ((R.transpose() * R - Eigen::Matrix3d::Identity()).norm() > 1e-6 || R.determinant() < 0) return false;
  *T = Eigen::Isometry3d::Identity();
  T->linear() = R;
  T->translation() = m.col(3);
  return true;
}

void put_desc(ByteWriter& w, const OrbDescriptor& d) {
  for (uint64_t x : d) w.u64(x);
}
void get_desc(ByteReader& r, OrbDescriptor* d) {
  for (auto& x : *d) x = r.u64();
}

std::string at(const char* what, size_t i) { return std::string(what) + " " + std::to_string(i) + ": "; }

}  // namespace

std::vector<uint8_t> encode_map(const Map& map, const MapCamera& cam) {
  // Keyframes in id order (the spanning tree's parents come first); points
  // numbered in the order their first observer is written.
  std::vector<int> kfs;
  map.for_each_keyframe([&](int k) { kfs.push_back(k); });
  std::sort(kfs.begin(), kfs.end(), [&](int a, int b) { return map.keyframe(a).id < map.keyframe(b).id; });
  std::vector<int32_t> file_kf(static_cast<size_t>(map.max_keyframes()), -1);
  for (size_t i = 0; i < kfs.size(); ++i) file_kf[static_cast<size_t>(kfs[i])] = static_cast<int32_t>(i);
  std::vector<int32_t> file_pt(static_cast<size_t>(map.max_points()), -1);
  std::vector<int> pts;
  for (int k : kfs) {
    for (int j = 0; j < map.keyframe(k).n; ++j) {
      const int32_t p = map.point_of(k, j);
      if (p >= 0 && file_pt[static_cast<size_t>(p)] < 0) {
        file_pt[static_cast<size_t>(p)] = static_cast<int32_t>(pts.size());
        pts.push_back(p);
      }
    }
  }

  std::vector<uint8_t> payload;
  ByteWriter w(payload);
  w.u32(map.vocabulary() ? map.vocabulary()->checksum() : 0u);
  w.f64(cam.K.fx);
  w.f64(cam.K.fy);
  w.f64(cam.K.cx);
  w.f64(cam.K.cy);
  w.i32(cam.width);
  w.i32(cam.height);
  w.u32(static_cast<uint32_t>(kfs.size()));
  w.u32(static_cast<uint32_t>(pts.size()));
  for (int k : kfs) {
    const MapKeyframe& K = map.keyframe(k);
    w.i64(K.t_ns);
    put_pose(w, K.T_MC);
    put_pose(w, K.T_WC);
    w.i32(map.keyframe_used(K.parent) ? file_kf[static_cast<size_t>(K.parent)] : -1);
    w.f64(K.path_m);
    w.u32(static_cast<uint32_t>(K.n));
    for (int j = 0; j < K.n; ++j) {
      const KeyframeFeature& f = map.feature(k, j);
      w.f32(f.x_px);
      w.f32(f.y_px);
      w.f32(f.u_px);
      w.f32(f.v_px);
      w.f32(f.depth_m);
      w.u16(static_cast<uint16_t>(f.level));
      put_desc(w, f.desc);
      const int32_t p = map.point_of(k, j);
      w.i32(p >= 0 ? file_pt[static_cast<size_t>(p)] : -1);
    }
  }
  for (int p : pts) {
    const MapPoint& P = map.point(p);
    for (int i = 0; i < 3; ++i) w.f64(P.p_M[i]);
    put_desc(w, P.desc);
    w.u16(static_cast<uint16_t>(P.level));
    w.u32(P.visible);
    w.u32(P.found);
  }
  return seal(kMapMagic, kMapVersion, payload);
}

std::string decode_map(const uint8_t* data, size_t n, const MapCamera& cam, Map* map, MapFileInfo* info) {
  const uint8_t* payload = nullptr;
  size_t pn = 0;
  std::string err = open_sealed(data, n, kMapMagic, kMapVersion, &payload, &pn);
  if (!err.empty()) return err;
  if (map->num_keyframes() != 0 || map->num_points() != 0) return "the map to load into is not empty";
  ByteReader r(payload, pn);
  const uint32_t vocab = r.u32();
  PinholeK K;
  K.fx = r.f64();
  K.fy = r.f64();
  K.cx = r.f64();
  K.cy = r.f64();
  const int32_t width = r.i32(), height = r.i32();
  const uint32_t n_kf = r.u32(), n_pt = r.u32();
  if (!r.ok()) return "truncated header";
  if (vocab != 0 && map->vocabulary() != nullptr && vocab != map->vocabulary()->checksum()) {
    char b[160];
    std::snprintf(b, sizeof b,
                  "made with another place-recognition vocabulary (checksum %08x, this run uses %08x)", vocab,
                  map->vocabulary()->checksum());
    return b;
  }
  const auto close = [](double a, double b) { return std::abs(a - b) <= 1e-6 * std::max(1.0, std::abs(b)); };
  if (width != cam.width || height != cam.height || !close(K.fx, cam.K.fx) || !close(K.fy, cam.K.fy) ||
      !close(K.cx, cam.K.cx) || !close(K.cy, cam.K.cy)) {
    char b[320];
    std::snprintf(
        b, sizeof b,
        "made with another camera (%dx%d, fx %.3f fy %.3f cx %.3f cy %.3f; this rig: %dx%d, fx %.3f fy %.3f "
        "cx %.3f cy %.3f)",
        width, height, K.fx, K.fy, K.cx, K.cy, cam.width, cam.height, cam.K.fx, cam.K.fy, cam.K.cx, cam.K.cy);
    return b;
  }
  if (n_kf > static_cast<uint32_t>(map->max_keyframes()) || n_pt > static_cast<uint32_t>(map->max_points())) {
    return "holds " + std::to_string(n_kf) + " keyframes and " + std::to_string(n_pt) +
           " points, more than this map's capacity (map.max_keyframes " +
           std::to_string(map->max_keyframes()) + ", map.max_points " + std::to_string(map->max_points()) +
           ")";
  }
  // Read and check everything before the map is touched.
  struct Kf {
    int64_t t_ns = 0;
    Eigen::Isometry3d T_MC, T_WC;
    int32_t parent = -1;
    double path_m = 0;
    size_t first = 0;  // into feats / feat_pt
    int n = 0;
  };
  std::vector<Kf> kfs;
  std::vector<KeyframeFeature> feats;
  std::vector<int32_t> feat_pt;
  kfs.reserve(n_kf);
  for (uint32_t i = 0; i < n_kf; ++i) {
    Kf k;
    k.t_ns = r.i64();
    if (!get_pose(r, &k.T_MC) || !get_pose(r, &k.T_WC))
      return at("keyframe", i) + (r.ok() ? "its pose is not a rigid transform" : "truncated");
    k.parent = r.i32();
    k.path_m = r.f64();
    const uint32_t nf = r.u32();
    if (!r.ok()) return at("keyframe", i) + "truncated";
    if (k.parent < -1 || k.parent >= static_cast<int32_t>(i))
      return at("keyframe", i) + "parent out of range";
    if (!std::isfinite(k.path_m)) return at("keyframe", i) + "path length not finite";
    if (nf > static_cast<uint32_t>(map->features_per_keyframe())) {
      return at("keyframe", i) + std::to_string(nf) + " features, this tracker keeps " +
             std::to_string(map->features_per_keyframe());
    }
    // Each feature takes 58 bytes: a count larger than what is left is damage, not a reason to allocate.
    if (static_cast<size_t>(nf) * 58 > r.remaining()) return at("keyframe", i) + "truncated";
    k.first = feats.size();
    k.n = static_cast<int>(nf);
    for (uint32_t j = 0; j < nf; ++j) {
      KeyframeFeature f;
      f.x_px = r.f32();
      f.y_px = r.f32();
      f.u_px = r.f32();
      f.v_px = r.f32();
      f.depth_m = r.f32();
      f.level = static_cast<int16_t>(r.u16());
      get_desc(r, &f.desc);
      const int32_t p = r.i32();
      if (!r.ok()) return at("keyframe", i) + "truncated";
      if (!std::isfinite(f.x_px) || !std::isfinite(f.y_px) || !std::isfinite(f.u_px) ||
          !std::isfinite(f.v_px) || !std::isfinite(f.depth_m) || f.depth_m < 0 || f.level < 0 || f.level > 31)
        return at("keyframe", i) + "feature " + std::to_string(j) + " damaged";
      if (p < -1 || p >= static_cast<int64_t>(n_pt)) {
        return at("keyframe", i) + "feature " + std::to_string(j) + " observes point " + std::to_string(p) +
               " of " + std::to_string(n_pt);
      }
      feats.push_back(f);
      feat_pt.push_back(p);
    }
    kfs.push_back(k);
  }
  struct Pt {
    Eigen::Vector3d p_M;
    OrbDescriptor desc{};
    int level = 0;
    uint32_t visible = 0, found = 0;
  };
  if (static_cast<size_t>(n_pt) * 66 > r.remaining()) return "truncated in the points";
  std::vector<Pt> pts(n_pt);
  for (uint32_t i = 0; i < n_pt; ++i) {
    Pt& p = pts[i];
    for (int a = 0; a < 3; ++a) p.p_M[a] = r.f64();
    get_desc(r, &p.desc);
    p.level = r.u16();
    p.visible = r.u32();
    p.found = r.u32();
    if (!r.ok()) return at("point", i) + "truncated";
    if (!p.p_M.allFinite() || p.level > 31) return at("point", i) + "damaged";
  }
  if (r.remaining() != 0) return std::to_string(r.remaining()) + " bytes after the last point";
  // Each point's observers; a point nobody observes is damage.
  std::vector<int> n_obs(n_pt, 0);
  for (int32_t p : feat_pt)
    if (p >= 0) ++n_obs[static_cast<size_t>(p)];
  for (uint32_t i = 0; i < n_pt; ++i)
    if (n_obs[i] == 0) return at("point", i) + "observed by no keyframe";

  // Fill the map: keyframes as session 1, points with fresh ids.
  std::vector<int> slot_of_kf(n_kf, -1), slot_of_pt(n_pt, -1);
  std::vector<uint32_t> id_of_pt(n_pt, 0);
  for (uint32_t i = 0; i < n_pt; ++i) id_of_pt[i] = map->fresh_landmark_id();
  std::vector<KeyframeFeature> tmp;
  for (uint32_t i = 0; i < n_kf; ++i) {
    const Kf& k = kfs[i];
    tmp.assign(feats.begin() + static_cast<long>(k.first), feats.begin() + static_cast<long>(k.first) + k.n);
    for (int j = 0; j < k.n; ++j) {
      const int32_t p = feat_pt[k.first + static_cast<size_t>(j)];
      tmp[static_cast<size_t>(j)].landmark_id = p >= 0 ? id_of_pt[static_cast<size_t>(p)] : 0;
    }
    const int s = map->add_keyframe(k.t_ns, k.T_MC, k.T_WC, tmp.data(), k.n,
                                    k.parent >= 0 ? slot_of_kf[static_cast<size_t>(k.parent)] : -1, 1);
    if (s < 0) return at("keyframe", i) + "the map is full";
    map->keyframe(s).path_m = k.path_m;
    slot_of_kf[i] = s;
    for (int j = 0; j < k.n; ++j) {
      const int32_t p = feat_pt[k.first + static_cast<size_t>(j)];
      if (p < 0) continue;
      int& ps = slot_of_pt[static_cast<size_t>(p)];
      const Pt& P = pts[static_cast<size_t>(p)];
      if (ps < 0) {
        ps = map->add_point(id_of_pt[static_cast<size_t>(p)], P.p_M, P.desc, P.level, s, j);
        if (ps < 0) return at("point", static_cast<size_t>(p)) + "the map is full";
        map->point(ps).visible = P.visible;
        map->point(ps).found = P.found;
      } else {
        // Refused when the point is seen by this keyframe already or has all
        // its observations: the file's extra observation is dropped, as the map would.
        (void)map->add_observation(ps, s, j);
      }
    }
  }
  if (info != nullptr) {
    info->vocabulary_checksum = vocab;
    info->keyframes = static_cast<int>(n_kf);
    info->points = static_cast<int>(n_pt);
  }
  return "";
}

}  // namespace kestrel::core

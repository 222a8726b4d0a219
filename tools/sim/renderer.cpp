// CPU ray caster for the simulated RGB-D camera.
//
// Hot path: one ray per pixel, from a per-pixel table of undistorted
// directions (z = 1, so the hit parameter is the registered depth). The room
// is a box seen from inside (three divisions); clutter is culled per 16x16
// tile with bounding-sphere vs tile-cone tests, so a pixel usually tests zero
// to three objects. Pixel noise comes from a hash of (seed, frame, pixel)
// indexing a table of normals: independent of which thread renders the row.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <thread>

#include "kestrel/tools/sim_random.hpp"
#include "kestrel/tools/sim_render.hpp"

namespace kestrel::tools {
namespace {

constexpr int kTile = 16;
constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr int kRoomSurfaces = 6;
// 4096 normals (16 KiB, stays in L1); a 64-bit hash picks four of them.
constexpr uint32_t kGaussTableSize = 1u << 12;

// MurmurHash3's finaliser: two multiplies, enough to make cells look random.
inline uint32_t fmix32(uint32_t h) {
  h ^= h >> 16;
  h *= 0x85EBCA6Bu;
  h ^= h >> 13;
  h *= 0xC2B2AE35u;
  h ^= h >> 16;
  return h;
}

// floor() without a libm call (baseline x86-64 has no SSE4.1 round).
inline int32_t floor_int(float x) {
  const auto i = static_cast<int32_t>(x);
  return x < static_cast<float>(i) ? i - 1 : i;
}

struct Rgb {
  float r = 0.f, g = 0.f, b = 0.f;
};

struct Hit {
  float t = kInf;
  float nx = 0.f, ny = 0.f, nz = 1.f;  // unit normal facing the camera side
  uint32_t surface = 0;
  float u = 0.f, v = 0.f;  // surface coordinates, metres
};

// Clutter flattened to floats for the inner loop.
struct Obj {
  bool box = true;
  float cx = 0.f, cy = 0.f, cz = 0.f;              // box centre / cylinder axis point (cz unused)
  float hx = 0.f, hy = 0.f, hz = 0.f;              // box half sizes
  float c = 1.f, s = 0.f;                          // box yaw
  float r = 0.f, z0 = 0.f, z1 = 0.f;               // cylinder
  float bx = 0.f, by = 0.f, bz = 0.f, brad = 0.f;  // bounding sphere
};

struct Frame {
  float R[9]{};  // R_WC row-major
  float o[3]{};  // p_WC
  uint64_t key = 0;
};

struct Mip {
  int w = 0, h = 0;
  std::vector<uint8_t> rgb;
};

inline float guard(float d) { return std::abs(d) < 1e-12f ? (d < 0.f ? -1e-12f : 1e-12f) : d; }

}  // namespace

Eigen::Vector2d distort_normalized(const CameraIntrinsics& cam, const Eigen::Vector2d& p) {
  if (cam.distortion != DistortionModel::kRadTan) return p;
  const double k1 = cam.dist[0], k2 = cam.dist[1], p1 = cam.dist[2], p2 = cam.dist[3], k3 = cam.dist[4];
  const double x = p.x(), y = p.y(), r2 = x * x + y * y;
  const double radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
  return {x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
          y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y};
}

Eigen::Vector2d undistort_normalized(const CameraIntrinsics& cam, const Eigen::Vector2d& pd) {
  if (cam.distortion != DistortionModel::kRadTan) return pd;
  const double k1 = cam.dist[0], k2 = cam.dist[1], p1 = cam.dist[2], p2 = cam.dist[3], k3 = cam.dist[4];
  Eigen::Vector2d p = pd;
  for (int it = 0; it < 20; ++it) {
    const Eigen::Vector2d f = distort_normalized(cam, p) - pd;
    if (f.squaredNorm() < 1e-26) break;
    const double x = p.x(), y = p.y(), r2 = x * x + y * y;
    const double radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    const double dr = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2));  // d radial / d r2, times 2
    Eigen::Matrix2d J;
    J(0, 0) = radial + x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x;
    J(0, 1) = x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y;
    J(1, 0) = x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y;
    J(1, 1) = radial + y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x;
    p -= J.lu().solve(f);
  }
  return p;
}

Eigen::Vector2d project(const CameraIntrinsics& cam, const Eigen::Vector3d& p_C) {
  const Eigen::Vector2d d = distort_normalized(cam, p_C.head<2>() / p_C.z());
  return {cam.fx * d.x() + cam.cx, cam.fy * d.y() + cam.cy};
}

struct Renderer::Impl {
  Scene scene;
  CameraIntrinsics cam;
  DepthModel depth;
  RenderOptions opt;
  int W = 0, H = 0, tiles_x = 0, tiles_y = 0;
  std::vector<float> ray;        // (x, y, |(x, y, 1)|) per pixel; z = 1
  std::vector<float> tile_axis;  // unit cone axis per tile
  std::vector<double> tile_cos;  // cos and sin of each tile cone's half angle
  std::vector<double> tile_sin;
  std::vector<Obj> objs;
  std::vector<float> gauss;
  std::vector<Mip> mips;
  float lo[3]{}, hi[3]{};
  float light[3]{};
  float focal = 1.f;
  float cos_max_inc = 0.f;
  // Per-frame candidate lists, tile-major; render() is not re-entrant.
  mutable std::vector<uint16_t> cand;
  mutable std::vector<uint16_t> cand_n;

  void trace(const Frame& f, const float* d, const uint16_t* cands, int ncand, Hit& h) const;
  Rgb pattern(uint32_t surface, float u, float v, float footprint, bool aa) const;
  Rgb image_texture(float u, float v, float footprint) const;
  void render_rows(const Frame& f, int y0, int y1, uint8_t* rgb, uint16_t* dep) const;
};

Renderer::Renderer(const Scene& scene, const CameraIntrinsics& camera, const DepthModel& depth,
                   const RenderOptions& options)
    : impl_(std::make_unique<Impl>()) {
  Impl& m = *impl_;
  if (camera.width <= 0 || camera.height <= 0 || camera.fx <= 0 || camera.fy <= 0)
    throw std::invalid_argument("renderer: camera needs width, height, fx, fy > 0");
  if (camera.distortion == DistortionModel::kEquidistant)
    throw std::invalid_argument("renderer: equidistant distortion is not supported (use radtan or none)");
  if (scene.boxes.size() + scene.cylinders.size() > 60000)
    throw std::invalid_argument("renderer: too many objects");
  m.scene = scene;
  m.cam = camera;
  m.depth = depth;
  m.opt = options;
  m.W = camera.width;
  m.H = camera.height;
  m.focal = static_cast<float>(0.5 * (camera.fx + camera.fy));
  m.cos_max_inc = static_cast<float>(std::cos(options.max_incidence_deg * 3.14159265358979323846 / 180.0));
  for (int i = 0; i < 3; ++i) {
    m.lo[i] = static_cast<float>(scene.room.min()[i]);
    m.hi[i] = static_cast<float>(scene.room.max()[i]);
  }
  const Eigen::Vector3f L = Eigen::Vector3f(0.35f, 0.25f, 0.9f).normalized();
  m.light[0] = L.x();
  m.light[1] = L.y();
  m.light[2] = L.z();

  // Undistorted ray of every pixel, once.
  m.ray.resize(static_cast<size_t>(m.W) * m.H * 3);
  for (int v = 0; v < m.H; ++v) {
    for (int u = 0; u < m.W; ++u) {
      const Eigen::Vector2d xy =
          undistort_normalized(camera, {(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy});
      const size_t i = (static_cast<size_t>(v) * m.W + u) * 3;
      m.ray[i] = static_cast<float>(xy.x());
      m.ray[i + 1] = static_cast<float>(xy.y());
      m.ray[i + 2] = static_cast<float>(std::sqrt(xy.squaredNorm() + 1.0));
    }
  }
  // A cone per tile holding all its rays (pixel centres widened by half a
  // pixel so the cone covers whole pixels).
  m.tiles_x = (m.W + kTile - 1) / kTile;
  m.tiles_y = (m.H + kTile - 1) / kTile;
  m.tile_axis.resize(static_cast<size_t>(m.tiles_x) * m.tiles_y * 3);
  m.tile_cos.resize(static_cast<size_t>(m.tiles_x) * m.tiles_y);
  m.tile_sin.resize(m.tile_cos.size());
  const double pixel_angle = 1.0 / std::min(camera.fx, camera.fy);
  for (int ty = 0; ty < m.tiles_y; ++ty) {
    for (int tx = 0; tx < m.tiles_x; ++tx) {
      Eigen::Vector3d axis = Eigen::Vector3d::Zero();
      const int u1 = std::min(m.W, (tx + 1) * kTile), v1 = std::min(m.H, (ty + 1) * kTile);
      for (int v = ty * kTile; v < v1; ++v) {
        for (int u = tx * kTile; u < u1; ++u) {
          const size_t i = (static_cast<size_t>(v) * m.W + u) * 3;
          axis += Eigen::Vector3d(m.ray[i], m.ray[i + 1], 1.0).normalized();
        }
      }
      axis.normalize();
      double half = 0.0;
      for (int v = ty * kTile; v < v1; ++v) {
        for (int u = tx * kTile; u < u1; ++u) {
          const size_t i = (static_cast<size_t>(v) * m.W + u) * 3;
          const Eigen::Vector3d r = Eigen::Vector3d(m.ray[i], m.ray[i + 1], 1.0).normalized();
          half = std::max(half, std::acos(std::clamp(r.dot(axis), -1.0, 1.0)));
        }
      }
      const size_t t = static_cast<size_t>(ty) * m.tiles_x + tx;
      m.tile_axis[3 * t] = static_cast<float>(axis.x());
      m.tile_axis[3 * t + 1] = static_cast<float>(axis.y());
      m.tile_axis[3 * t + 2] = static_cast<float>(axis.z());
      m.tile_cos[t] = std::cos(half + 2.0 * pixel_angle);
      m.tile_sin[t] = std::sin(half + 2.0 * pixel_angle);
    }
  }

  for (const SceneBox& b : scene.boxes) {
    Obj o;
    o.box = true;
    o.cx = static_cast<float>(b.center_W.x());
    o.cy = static_cast<float>(b.center_W.y());
    o.cz = static_cast<float>(b.center_W.z());
    o.hx = static_cast<float>(b.half_m.x());
    o.hy = static_cast<float>(b.half_m.y());
    o.hz = static_cast<float>(b.half_m.z());
    o.c = static_cast<float>(std::cos(b.yaw_rad));
    o.s = static_cast<float>(std::sin(b.yaw_rad));
    o.bx = o.cx;
    o.by = o.cy;
    o.bz = o.cz;
    o.brad = static_cast<float>(b.half_m.norm()) * 1.001f;
    m.objs.push_back(o);
  }
  for (const SceneCylinder& c : scene.cylinders) {
    Obj o;
    o.box = false;
    o.cx = static_cast<float>(c.center_W.x());
    o.cy = static_cast<float>(c.center_W.y());
    o.r = static_cast<float>(c.radius_m);
    o.z0 = static_cast<float>(c.z0_m);
    o.z1 = static_cast<float>(c.z1_m);
    o.bx = o.cx;
    o.by = o.cy;
    o.bz = 0.5f * (o.z0 + o.z1);
    o.brad = std::hypot(o.r, 0.5f * (o.z1 - o.z0)) * 1.001f;
    m.objs.push_back(o);
  }
  m.cand.resize(m.tile_cos.size() * std::max<size_t>(1, m.objs.size()));
  m.cand_n.resize(m.tile_cos.size());

  // Normals for pixel noise, drawn once from the seed by Box-Muller.
  SimRng rng(options.seed, RngStream::kPixels);
  m.gauss.resize(kGaussTableSize);
  for (float& g : m.gauss) g = static_cast<float>(rng.normal());

  if (!options.texture_path.empty()) {
    cv::Mat img = cv::imread(options.texture_path, cv::IMREAD_COLOR);
    if (img.empty()) throw std::runtime_error(options.texture_path + ": cannot read texture image");
    cv::cvtColor(img, img, cv::COLOR_BGR2RGB);
    while (true) {
      Mip mip;
      mip.w = img.cols;
      mip.h = img.rows;
      mip.rgb.resize(static_cast<size_t>(img.cols) * img.rows * 3);
      for (int r = 0; r < img.rows; ++r)
        std::copy_n(img.ptr<uint8_t>(r), img.cols * 3, &mip.rgb[static_cast<size_t>(r) * img.cols * 3]);
      m.mips.push_back(std::move(mip));
      if (img.cols < 16 || img.rows < 16) break;
      cv::Mat down;
      cv::pyrDown(img, down);
      img = down;
    }
  }
}

Renderer::~Renderer() = default;

const CameraIntrinsics& Renderer::camera() const { return impl_->cam; }

Eigen::Vector3d Renderer::pixel_ray(int u, int v) const {
  const size_t i = (static_cast<size_t>(v) * impl_->W + u) * 3;
  return {impl_->ray[i], impl_->ray[i + 1], 1.0};
}

void Renderer::Impl::trace(const Frame& f, const float* d, const uint16_t* cands, int ncand, Hit& h) const {
  const float* o = f.o;
  // Leaving the room from inside: the nearest of three walls.
  int face = 0;
  for (int a = 0; a < 3; ++a) {
    float t;
    int fa;
    if (d[a] > 1e-12f) {
      t = (hi[a] - o[a]) / d[a];
      fa = 2 * a + 1;
    } else if (d[a] < -1e-12f) {
      t = (lo[a] - o[a]) / d[a];
      fa = 2 * a;
    } else {
      continue;
    }
    if (t < h.t) {
      h.t = t;
      face = fa;
    }
  }
  {
    const int a = face / 2;
    const float sgn = (face & 1) ? -1.f : 1.f;
    h.nx = a == 0 ? sgn : 0.f;
    h.ny = a == 1 ? sgn : 0.f;
    h.nz = a == 2 ? sgn : 0.f;
    h.surface = static_cast<uint32_t>(face);
    const float px = o[0] + h.t * d[0], py = o[1] + h.t * d[1], pz = o[2] + h.t * d[2];
    // Wall u runs to the right as seen from inside, so image textures read
    // the right way round on all four walls.
    if (a == 0) {
      h.u = (face & 1) ? -py : py;
      h.v = pz;
    } else if (a == 1) {
      h.u = (face & 1) ? px : -px;
      h.v = pz;
    } else {
      h.u = px;
      h.v = py;
    }
  }

  for (int k = 0; k < ncand; ++k) {
    const int idx = cands[k];
    const Obj& b = objs[static_cast<size_t>(idx)];
    const uint32_t surf_base = kRoomSurfaces + 8u * static_cast<uint32_t>(idx);
    if (b.box) {
      const float ox = o[0] - b.cx, oy = o[1] - b.cy, oz = o[2] - b.cz;
      const float lo_[3] = {b.c * ox + b.s * oy, -b.s * ox + b.c * oy, oz};
      const float ld[3] = {guard(b.c * d[0] + b.s * d[1]), guard(-b.s * d[0] + b.c * d[1]), guard(d[2])};
      const float hh[3] = {b.hx, b.hy, b.hz};
      float tn = -kInf, tf = kInf;
      int axis = 0;
      for (int a = 0; a < 3; ++a) {
        const float inv = 1.f / ld[a];
        float t1 = (-hh[a] - lo_[a]) * inv, t2 = (hh[a] - lo_[a]) * inv;
        if (t1 > t2) std::swap(t1, t2);
        if (t1 > tn) {
          tn = t1;
          axis = a;
        }
        tf = std::min(tf, t2);
      }
      if (tn <= tf && tn > 1e-4f && tn < h.t) {
        h.t = tn;
        float nl[3] = {0.f, 0.f, 0.f};
        nl[axis] = ld[axis] > 0.f ? -1.f : 1.f;
        h.nx = b.c * nl[0] - b.s * nl[1];
        h.ny = b.s * nl[0] + b.c * nl[1];
        h.nz = nl[2];
        h.surface = surf_base + static_cast<uint32_t>(2 * axis + (nl[axis] > 0.f ? 1 : 0));
        const float p[3] = {lo_[0] + tn * ld[0], lo_[1] + tn * ld[1], lo_[2] + tn * ld[2]};
        const int a1 = axis == 0 ? 1 : 0, a2 = axis == 2 ? 1 : 2;
        h.u = p[a1] + hh[a1];
        h.v = p[a2] + hh[a2];
      }
    } else {
      const float ox = o[0] - b.cx, oy = o[1] - b.cy;
      const float A = d[0] * d[0] + d[1] * d[1];
      if (A > 1e-12f) {
        const float B = ox * d[0] + oy * d[1];
        const float C = ox * ox + oy * oy - b.r * b.r;
        const float disc = B * B - A * C;
        if (disc >= 0.f) {
          const float t = (-B - std::sqrt(disc)) / A;
          const float z = o[2] + t * d[2];
          if (t > 1e-4f && t < h.t && z >= b.z0 && z <= b.z1) {
            h.t = t;
            const float px = ox + t * d[0], py = oy + t * d[1];
            h.nx = px / b.r;
            h.ny = py / b.r;
            h.nz = 0.f;
            h.surface = surf_base;
            h.u = (std::atan2(py, px) + 3.14159265f) * b.r;
            h.v = z;
          }
        }
      }
      if (o[2] > b.z1 && d[2] < 0.f) {  // top cap
        const float t = (b.z1 - o[2]) / d[2];
        const float px = ox + t * d[0], py = oy + t * d[1];
        if (t > 1e-4f && t < h.t && px * px + py * py <= b.r * b.r) {
          h.t = t;
          h.nx = 0.f;
          h.ny = 0.f;
          h.nz = 1.f;
          h.surface = surf_base + 1;
          h.u = px;
          h.v = py;
        }
      }
    }
  }
}

// Multi-scale random blocks: from the finest level (5 cm) to the coarsest
// (80 cm) each cell flips a biased coin for "a block of its own here"; the
// first level that says yes gives the colour, so big blocks carry smaller
// ones at all scales and every block corner is a high-contrast corner. Levels
// finer than three pixels are skipped (no aliasing of fine blocks far away),
// and pixels within half a pixel of their block's edge are blended with the
// colour across it: a 1-D box filter that keeps edges sharp, not jagged.
Rgb Renderer::Impl::pattern(uint32_t surface, float u, float v, float footprint, bool aa) const {
  static constexpr float kCell[5] = {0.8f, 0.4f, 0.2f, 0.1f, 0.05f};
  static constexpr float kInvCell[5] = {1.25f, 2.5f, 5.f, 10.f, 20.f};
  static constexpr uint32_t kKeep[5] = {256u, 128u, 102u, 77u, 56u};  // out of 256
  int level = 4;
  while (level > 0 && kCell[level] < 3.f * footprint) --level;
  const uint32_t sbase = surface * 0x9E3779B1u;
  int32_t ix = 0, iy = 0;
  uint32_t h = 0;
  for (;; --level) {
    ix = floor_int(u * kInvCell[level]);
    iy = floor_int(v * kInvCell[level]);
    h = fmix32(sbase ^ (static_cast<uint32_t>(ix) * 0x85EBCA77u) ^ (static_cast<uint32_t>(iy) * 0xC2B2AE3Du) ^
               (static_cast<uint32_t>(level) * 0x27D4EB2Fu));
    if (level == 0 || (h & 0xFFu) < kKeep[level]) break;
  }
  // Dark or bright at random (strong contrast between neighbours half the
  // time), tinted by the surface's hue and a little per block.
  const float r1 = static_cast<float>((h >> 9) & 0xFFu) * (1.f / 255.f);
  const float lum = (h & 0x100u) ? 0.62f + 0.33f * r1 : 0.06f + 0.26f * r1;
  const uint32_t hs = fmix32(surface + 0x632BE5ABu);
  const float tr = 0.55f + 0.45f * static_cast<float>((hs ^ (h >> 17)) & 0xFFu) * (1.f / 255.f);
  const float tg = 0.55f + 0.45f * static_cast<float>((hs >> 8) & 0xFFu) * (1.f / 255.f);
  const float tb = 0.55f + 0.45f * static_cast<float>(((hs >> 16) ^ (h >> 24)) & 0xFFu) * (1.f / 255.f);
  const Rgb c{lum * tr, lum * tg, lum * tb};
  if (!aa) return c;

  const float cell = kCell[level];
  const float fu = u * kInvCell[level] - static_cast<float>(ix),
              fv = v * kInvCell[level] - static_cast<float>(iy);
  const float du = std::min(fu, 1.f - fu) * cell, dv = std::min(fv, 1.f - fv) * cell;
  const float dist_px = std::min(du, dv) / footprint;
  if (dist_px >= 0.5f) return c;
  float u2 = u, v2 = v;
  if (du <= dv) {
    u2 = fu < 0.5f ? u - du - 0.01f * footprint : u + du + 0.01f * footprint;
  } else {
    v2 = fv < 0.5f ? v - dv - 0.01f * footprint : v + dv + 0.01f * footprint;
  }
  const Rgb o = pattern(surface, u2, v2, footprint, false);
  const float w = 0.5f + dist_px;
  return {w * c.r + (1.f - w) * o.r, w * c.g + (1.f - w) * o.g, w * c.b + (1.f - w) * o.b};
}

Rgb Renderer::Impl::image_texture(float u, float v, float footprint) const {
  const Mip& base = mips.front();
  const float scale = static_cast<float>(base.w) / static_cast<float>(opt.texture_size_m);
  const float texels = footprint * scale;
  int level = texels > 1.f ? static_cast<int>(std::log2(texels)) : 0;
  level = std::min(level, static_cast<int>(mips.size()) - 1);
  const Mip& m = mips[static_cast<size_t>(level)];
  const float x = u * scale * static_cast<float>(m.w) / static_cast<float>(base.w) - 0.5f;
  const float y =
      -v * scale * static_cast<float>(m.w) / static_cast<float>(base.w) - 0.5f;  // image rows go down
  const float fx = std::floor(x), fy = std::floor(y);
  const float ax = x - fx, ay = y - fy;
  auto wrap = [](long i, int n) { return static_cast<int>(((i % n) + n) % n); };
  const int x0 = wrap(static_cast<long>(fx), m.w), x1 = wrap(static_cast<long>(fx) + 1, m.w);
  const int y0 = wrap(static_cast<long>(fy), m.h), y1 = wrap(static_cast<long>(fy) + 1, m.h);
  float out[3];
  for (int c = 0; c < 3; ++c) {
    auto at = [&](int xx, int yy) {
      return static_cast<float>(m.rgb[(static_cast<size_t>(yy) * m.w + xx) * 3 + c]);
    };
    out[c] = ((1.f - ax) * (1.f - ay) * at(x0, y0) + ax * (1.f - ay) * at(x1, y0) +
              (1.f - ax) * ay * at(x0, y1) + ax * ay * at(x1, y1)) *
             (1.f / 255.f);
  }
  return {out[0], out[1], out[2]};
}

void Renderer::Impl::render_rows(const Frame& f, int y0, int y1, uint8_t* rgb, uint16_t* dep) const {
  const float* R = f.R;
  const float k_sigma = opt.depth_noise ? static_cast<float>(depth.sigma_coeff_per_m) : 0.f;
  const float img_sigma = static_cast<float>(opt.image_noise_sigma);
  const float zmin = static_cast<float>(depth.min_range_m), zmax = static_cast<float>(depth.max_range_m);
  const double inv_scale = 1.0 / depth.scale_m_per_unit;
  const size_t n_obj = objs.size();
  for (int v = y0; v < y1; ++v) {
    const int ty = v / kTile;
    for (int u = 0; u < W; ++u) {
      const size_t idx = static_cast<size_t>(v) * W + u;
      const float xn = ray[3 * idx], yn = ray[3 * idx + 1], len = ray[3 * idx + 2];
      const float d[3] = {R[0] * xn + R[1] * yn + R[2], R[3] * xn + R[4] * yn + R[5],
                          R[6] * xn + R[7] * yn + R[8]};
      const size_t tile = static_cast<size_t>(ty) * tiles_x + static_cast<size_t>(u / kTile);
      Hit h;
      trace(f, d, &cand[tile * n_obj], cand_n[tile], h);

      const float ndot = h.nx * d[0] + h.ny * d[1] + h.nz * d[2];
      const float cos_inc = std::abs(ndot) / len;
      const float footprint = h.t * len / (focal * std::max(cos_inc, 0.15f));
      Rgb tex;
      if (opt.bare_surface >= 0 && h.surface == static_cast<uint32_t>(opt.bare_surface)) {
        // Paint with a faint large-scale shading: nothing a corner detector can hold on to.
        const float g = 0.62f + 0.03f * std::sin(0.7f * h.u) * std::sin(0.5f * h.v);
        tex = Rgb{g, g, 0.97f * g};
      } else {
        tex = (h.surface < kRoomSurfaces && !mips.empty()) ? image_texture(h.u, h.v, footprint)
                                                           : pattern(h.surface, h.u, h.v, footprint, true);
      }
      const float lambert = std::max(0.f, h.nx * light[0] + h.ny * light[1] + h.nz * light[2]);
      const float shade = 255.f * (0.55f + 0.45f * lambert);

      const uint64_t noise = splitmix64(f.key + idx);
      const float n0 = gauss[noise & 0xFFFu], n1 = gauss[(noise >> 16) & 0xFFFu];
      const float n2 = gauss[(noise >> 32) & 0xFFFu], n3 = gauss[(noise >> 48) & 0xFFFu];
      uint8_t* px = rgb + 3 * idx;
      px[0] = static_cast<uint8_t>(std::clamp(tex.r * shade + img_sigma * n0 + 0.5f, 0.f, 255.f));
      px[1] = static_cast<uint8_t>(std::clamp(tex.g * shade + img_sigma * n1 + 0.5f, 0.f, 255.f));
      px[2] = static_cast<uint8_t>(std::clamp(tex.b * shade + img_sigma * n2 + 0.5f, 0.f, 255.f));

      // Registered depth is the hit's z in the camera frame, which is t
      // because the ray has z = 1.
      uint16_t out = 0;
      if (cos_inc >= cos_max_inc && h.t >= zmin && h.t <= zmax) {
        const double z = static_cast<double>(h.t) + static_cast<double>(k_sigma * h.t * h.t * n3);
        const double q = z * inv_scale + 0.5;  // round to the nearest unit
        if (q >= 1.0 && q < 65536.0) out = static_cast<uint16_t>(q);
      }
      dep[idx] = out;
    }
  }
}

void Renderer::render(const Eigen::Isometry3d& T_WC, uint64_t frame_index, uint8_t* rgb,
                      uint16_t* depth) const {
  const Impl& m = *impl_;
  Frame f;
  const Eigen::Matrix3d R = T_WC.rotation();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) f.R[3 * r + c] = static_cast<float>(R(r, c));
  for (int i = 0; i < 3; ++i) f.o[i] = static_cast<float>(T_WC.translation()[i]);
  f.key = hash_combine(m.opt.seed, frame_index);

  // Which objects each tile's cone can see.
  const size_t n_obj = m.objs.size();
  const Eigen::Matrix3d R_CW = R.transpose();
  std::fill(m.cand_n.begin(), m.cand_n.end(), 0);
  for (size_t k = 0; k < n_obj; ++k) {
    const Obj& o = m.objs[k];
    const Eigen::Vector3d c_C = R_CW * (Eigen::Vector3d(o.bx, o.by, o.bz) - T_WC.translation());
    const double dist = c_C.norm();
    const bool around = dist <= o.brad;
    // angle(c, axis) <= half + asin(r / dist), compared as cosines: both
    // angles stay below pi/2 + a tile's few degrees.
    const double sin_r = around ? 1.0 : o.brad / dist, cos_r = std::sqrt(1.0 - sin_r * sin_r);
    for (size_t t = 0; t < m.cand_n.size(); ++t) {
      bool hit = around;
      if (!hit) {
        const double cosang = (c_C.x() * m.tile_axis[3 * t] + c_C.y() * m.tile_axis[3 * t + 1] +
                               c_C.z() * m.tile_axis[3 * t + 2]) /
                              dist;
        hit = cosang >= m.tile_cos[t] * cos_r - m.tile_sin[t] * sin_r;
      }
      if (hit) m.cand[t * n_obj + m.cand_n[t]++] = static_cast<uint16_t>(k);
    }
  }

  // Bands of tile rows handed out to the threads.
  std::atomic<int> next{0};
  const int bands = m.tiles_y;
  auto work = [&]() {
    for (int b = next.fetch_add(1); b < bands; b = next.fetch_add(1))
      m.render_rows(f, b * kTile, std::min(m.H, (b + 1) * kTile), rgb, depth);
  };
  const int extra = std::max(0, m.opt.threads - 1);
  std::vector<std::thread> pool;
  pool.reserve(static_cast<size_t>(extra));
  for (int i = 0; i < extra; ++i) pool.emplace_back(work);
  work();
  for (auto& t : pool) t.join();

  // Dropouts: small discs of missing depth, drawn per frame from the seed.
  if (m.opt.dropout_fraction > 0.0) {
    SimRng rng(f.key, RngStream::kCamera);
    const double scale = m.W / 640.0;
    const double r_lo = 1.0 * scale, r_hi = 4.0 * scale;
    const double mean_area = 3.14159265358979323846 * (r_lo * r_lo + r_lo * r_hi + r_hi * r_hi) / 3.0;
    const double expected = m.opt.dropout_fraction * m.W * m.H / mean_area;
    const int n = static_cast<int>(expected + rng.uniform());
    for (int i = 0; i < n; ++i) {
      const double cx = rng.uniform(0.0, m.W), cy = rng.uniform(0.0, m.H), r = rng.uniform(r_lo, r_hi);
      const int x0 = std::max(0, static_cast<int>(cx - r)), x1 = std::min(m.W - 1, static_cast<int>(cx + r));
      const int y0 = std::max(0, static_cast<int>(cy - r)), y1 = std::min(m.H - 1, static_cast<int>(cy + r));
      for (int y = y0; y <= y1; ++y) {
        for (int x = x0; x <= x1; ++x) {
          if ((x + 0.5 - cx) * (x + 0.5 - cx) + (y + 0.5 - cy) * (y + 0.5 - cy) <= r * r)
            depth[static_cast<size_t>(y) * m.W + x] = 0;
        }
      }
    }
  }
}

double Renderer::cast(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir) const {
  const Impl& m = *impl_;
  Frame f;
  for (int i = 0; i < 3; ++i) f.o[i] = static_cast<float>(origin[i]);
  const Eigen::Vector3d u = dir.normalized();
  const float d[3] = {static_cast<float>(u.x()), static_cast<float>(u.y()), static_cast<float>(u.z())};
  std::vector<uint16_t> all(m.objs.size());
  for (size_t k = 0; k < all.size(); ++k) all[k] = static_cast<uint16_t>(k);
  Hit h;
  m.trace(f, d, all.data(), static_cast<int>(all.size()), h);
  return h.t;
}

}  // namespace kestrel::tools

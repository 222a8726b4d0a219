// One keyframe feature as a bundle adjustment observation, with the map's
// noise model (pixel sigma by pyramid level, depth sigma by range): the local
// and the global bundle adjustment must weigh the same feature alike.
// Private to core/map.
#pragma once

#include "kestrel/core/bundle_adjustment.hpp"
#include "kestrel/core/local_mapper.hpp"

namespace kestrel::core {

inline BaObservation ba_observation(const MapCamera& cam, const KeyframeFeature& f, int32_t pose,
                                    int32_t point) {
  BaObservation ob;
  ob.pose = pose;
  ob.point = point;
  ob.u_px = f.u_px;
  ob.v_px = f.v_px;
  ob.depth_m = f.depth_m > 0 ? f.depth_m : 0.0;
  ob.inv_sigma_px = 1.0 / cam.sigma_px(f.level);
  ob.inv_sigma_z = f.depth_m > 0 ? 1.0 / cam.sigma_depth_m(f.depth_m) : 0.0;
  return ob;
}

}  // namespace kestrel::core

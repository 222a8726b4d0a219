#!/usr/bin/env python3
"""The cost of driving a backend from Python instead of C++ (docs/python.md, "Overhead").

Preloads every record of LOG (reading is not the binding's cost), then feeds them through kestrel.Estimator as
docs/api.md's C++ loop does, and splits the wall time into the time spent inside the C++ estimator calls
(Estimator.counters["native_s"]) and the rest: argument conversion, array checks and the Python loop itself.

usage: PYTHONPATH=build/release/python python3 tools/python/bench/overhead.py LOG [BACKEND ...]
"""
import sys
import time

import kestrel


def run(recs, rig, backend):
    est = kestrel.Estimator(rig, backend)
    frames = imu = 0
    rgb = None
    t0 = time.perf_counter()
    for r in recs:
        if r.type == "imu":
            est.add_imu(r.t_ns, r.gyro_rps, r.acc_mps2)
            imu += 1
        elif r.type == "rgb":
            rgb = r
        elif r.type == "depth" and rgb is not None and r.t_ns == rgb.t_ns:
            est.add_frame(rgb.t_ns, rgb.image, r.image, rgb_format=rgb.format)
            frames += 1
    wall = time.perf_counter() - t0
    native = est.counters["native_s"]
    return frames, imu, wall, native


def main():
    if len(sys.argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    log = kestrel.open_log(sys.argv[1])
    recs = list(log)
    backends = sys.argv[2:] or ["imu", "vo"]
    print(f"log {sys.argv[1]}: {log.rig.width}x{log.rig.height}, {len(recs)} records")
    print("backend  frames  imu  wall_ms/frame  native_ms/frame  python_overhead_us/frame  overhead_share")
    for b in backends:
        frames, imu, wall, native = run(recs, log.rig, b)
        over = wall - native
        print(f"{b:8s} {frames:6d} {imu:5d} {wall / frames * 1e3:13.3f} {native / frames * 1e3:16.3f} "
              f"{over / frames * 1e6:25.1f} {over / wall:14.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

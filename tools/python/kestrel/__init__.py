"""Kestrel from Python: read any supported log, run any backend, replay, score trajectories.

Trajectories are (N, 8) float64 arrays of TUM rows ``t[s] x y z qx qy qz qw`` (body B = IMU in the world W,
gravity along -z; docs/frames.md). docs/python.md has a worked example.
"""

import os as _os

from . import _kestrel
from ._kestrel import Estimator, Log, Record, Rig, State, backends, evaluate  # noqa: F401  (the public API)

__all__ = [
    "Estimator", "Log", "Record", "Rig", "State", "ate", "backends", "evaluate", "load_rig", "load_trajectory",
    "open_log", "replay", "rpe", "write_tum",
]


def open_log(path, **options):
    """Open a .klog, rosbag2 folder / .mcap, ROS 1 bag, EuRoC, TUM RGB-D, ETH3D, OpenLORIS or 7-Scenes log.

    Options: format, rig (a rig YAML for datasets without calibration), fps (7-Scenes), rgb_topic,
    depth_topic, imu_topic, camera_info_topic, gt_topic, topics (rosbag2: read only these; a list or "a,b").
    Iterate it for its records.
    """
    return Log(_os.fspath(path), **options)


def ate(gt, est, align="posyaw", max_gap_ms=20.0):
    """Absolute trajectory error in metres after alignment: a dict of rmse, mean, median, std, min, max, count."""
    return evaluate(gt, est, align=align, max_gap_ms=max_gap_ms)["ate_m"]


def rpe(gt, est, delta_s=1.0, align="posyaw", max_gap_ms=20.0):
    """Relative pose error over delta_s seconds: a dict of pairs, trans_rmse_m, rot_rmse_deg, ..."""
    return evaluate(gt, est, align=align, max_gap_ms=max_gap_ms, rpe_delta_s=delta_s)["rpe"]


def replay(path, **options):
    """Run `kestrel replay` on a log and return its trajectory as an (N, 8) array of TUM rows.

    Options (all keywords; an unknown one is a TypeError naming it): estimator (a backend name, see backends()),
    config (a config YAML, docs/config.md), pace (lockstep, the default and deterministic; fast; realtime),
    mapping / loop ("on" / "off"), warmup_s, trajectory ("odometry", "map", "map_final"), report (True: return
    (rows, dict) with the run's figures), and the open_log options.
    """
    return _kestrel.replay(_os.fspath(path), **options)


def load_rig(path):
    """Read a rig YAML (configs/*.yaml) as a Rig for Estimator."""
    return _kestrel.load_rig(_os.fspath(path))


def load_trajectory(path):
    """TUM text, EuRoC CSV or a log's ground truth as an (N, 8) array of TUM rows."""
    return _kestrel.load_trajectory(_os.fspath(path))


def write_tum(path, rows):
    """Write (N, 8) TUM rows as a TUM text file."""
    _kestrel.write_tum(_os.fspath(path), rows)

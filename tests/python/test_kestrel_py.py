"""`import kestrel`: logs, backends, replay and metrics from Python (docs/python.md)."""
import math
import os
import subprocess

import numpy as np
import pytest

import kestrel
from conftest import bin_dir


def records_of(path):
    return list(kestrel.open_log(path))


# ---- logs ---------------------------------------------------------------------------------------------------

def test_open_log_yields_every_record_with_numpy_payloads(hover_log):
    log = kestrel.open_log(hover_log)
    assert log.format == "klog"
    assert (log.rig.width, log.rig.height) == (160, 120)
    assert log.rig.K.shape == (3, 3) and log.rig.T_BC.shape == (4, 4)
    recs = list(log)
    kinds = {k: sum(r.type == k for r in recs) for k in ("imu", "rgb", "depth", "ground_truth")}
    # 8 s at the rig's rates (a sample may fall either side of the ends).
    assert abs(kinds["imu"] - 8 * log.rig.imu_rate_hz) <= 2, (kinds, log.rig.imu_rate_hz)
    assert abs(kinds["rgb"] - 8 * log.rig.camera_rate_hz) <= 2 and kinds["depth"] == kinds["rgb"], kinds
    assert kinds["ground_truth"] > 0
    imu = next(r for r in recs if r.type == "imu")
    assert imu.gyro_rps.shape == (3,) and imu.acc_mps2.shape == (3,) and imu.image is None
    # Hovering: the accelerometer reads about +g.
    assert 9.0 < np.linalg.norm(imu.acc_mps2) < 10.6
    rgb = next(r for r in recs if r.type == "rgb")
    assert rgb.image.shape == (120, 160, 3) and rgb.image.dtype == np.uint8 and rgb.format in ("rgb8", "bgr8")
    assert rgb.image.std() > 5  # a textured room, not a blank buffer
    depth = next(r for r in recs if r.type == "depth")
    assert depth.image.shape == (120, 160) and depth.image.dtype == np.uint16 and depth.image.max() > 0
    gt = next(r for r in recs if r.type == "ground_truth")
    assert gt.p_WB.shape == (3,) and abs(np.linalg.norm(gt.q_WB_wxyz) - 1) < 1e-9
    times = [r.t_ns for r in recs if r.type == "imu"]
    assert all(b > a for a, b in zip(times, times[1:]))
    assert log.problems == []
    # Arrays are copies: the next record does not overwrite them.
    first = recs[0]
    log.rewind()
    again = next(iter(log))
    assert again.type == first.type and again.t_ns == first.t_ns


def test_open_log_names_what_is_wrong(tmp_path, hover_log):
    with pytest.raises(RuntimeError, match="nothing-here"):
        kestrel.open_log(tmp_path / "nothing-here")
    with pytest.raises(TypeError, match="colour_topic"):
        kestrel.open_log(hover_log, colour_topic="/x")
    with pytest.raises(ValueError, match="nosuchformat"):
        kestrel.open_log(hover_log, format="nosuchformat")


def test_a_truncated_log_reads_up_to_the_damage(tmp_path, hover_log):
    data = hover_log.read_bytes()
    cut = tmp_path / "cut.klog"
    cut.write_bytes(data[: len(data) // 2])
    log = kestrel.open_log(cut)
    recs = list(log)
    assert len(recs) > 100
    assert any(kind == "truncated" for _, kind, _ in log.problems), log.problems
    assert all("cut.klog" in where for where, _, _ in log.problems)


# ---- replay -------------------------------------------------------------------------------------------------

def test_replay_returns_tum_rows_that_follow_the_ground_truth(hover_log):
    rows = kestrel.replay(hover_log)
    assert rows.dtype == np.float64 and rows.ndim == 2 and rows.shape[1] == 8
    assert rows.shape[0] > 180, rows.shape
    assert np.all(np.diff(rows[:, 0]) > 0)
    assert np.allclose(np.linalg.norm(rows[:, 4:], axis=1), 1.0, atol=1e-9)
    gt = kestrel.load_trajectory(hover_log)
    assert kestrel.ate(gt, rows)["rmse"] < 0.05
    # Lockstep is deterministic: the same log gives the same array.
    assert np.array_equal(rows, kestrel.replay(hover_log))


def test_replay_matches_the_command_line(tmp_path, hover_log):
    out = tmp_path / "cli.txt"
    subprocess.run([os.path.join(bin_dir(), "kestrel"), "replay", str(hover_log), "--estimator", "vo", "--quiet",
                    "--traj-out", str(out)], check=True)
    cli = np.loadtxt(out, ndmin=2)
    py = kestrel.replay(hover_log, estimator="vo")
    assert py.shape == cli.shape
    # The file prints times exactly and poses to its own precision.
    assert np.allclose(py, cli, atol=1e-6, rtol=0)


def test_replay_options_and_report(hover_log):
    rows, report = kestrel.replay(hover_log, estimator="imu", report=True)
    assert report["estimator"] == "imu-dead-reckoning"
    assert report["frames_pushed"] > 200 and report["problems"] == []
    assert report["alloc_counting"] is False  # the counting hook is not in the module (docs/python.md)
    # The run's perf registry by path, the same numbers as the report's own keys.
    assert report["counters"]["estimator.frames_in"] == report["frames_pushed"]
    assert report["counters"]["output.lost_poses_withheld"] == report["lost_poses_withheld"]
    assert rows.shape[1] == 8 and rows.shape[0] > 0
    with pytest.raises(ValueError, match="nosuch"):
        kestrel.replay(hover_log, estimator="nosuch")
    with pytest.raises(TypeError, match="estimater"):
        kestrel.replay(hover_log, estimater="vo")
    with pytest.raises(ValueError, match="trajectory"):
        kestrel.replay(hover_log, trajectory="sideways")


# ---- the estimator from numpy -------------------------------------------------------------------------------

def feed(est, recs, until_s=None, depth_in_metres=False, scale=0.001):
    """The docs/api.md loop in Python: IMU in order, each colour image with the depth that follows it."""
    rgb = None
    t0 = recs[0].t_ns
    for r in recs:
        if until_s is not None and r.t_ns - t0 > until_s * 1e9:
            break
        if r.type == "imu":
            est.add_imu(r.t_ns, r.gyro_rps, r.acc_mps2)
        elif r.type == "rgb":
            rgb = r
        elif r.type == "depth" and rgb is not None and r.t_ns == rgb.t_ns:
            depth = r.image.astype(np.float32) * scale if depth_in_metres else r.image
            est.add_frame(rgb.t_ns, rgb.image, depth, rgb_format=rgb.format)


def test_estimator_from_python_is_the_cpp_api_bit_for_bit(hover_log):
    recs = records_of(hover_log)
    est = kestrel.Estimator(kestrel.open_log(hover_log).rig, "vo")
    feed(est, recs)
    rows = est.trajectory()
    # docs/api.md's C++ program (built by tests/pipeline) on the same log and backend.
    out = subprocess.run([os.path.join(bin_dir(), "api_example"), str(hover_log), "vo"], check=True,
                         capture_output=True, text=True).stdout
    cpp = np.loadtxt(out.splitlines(), ndmin=2)
    # The C++ example prints every pose past initialisation, lost ones too; the Python trajectory leaves lost
    # poses out, as `kestrel replay` does. This flight never loses track, so the two are the same poses.
    assert rows.shape == cpp.shape, (rows.shape, cpp.shape)
    assert np.allclose(rows[:, 0], cpp[:, 0], atol=1e-6, rtol=0)
    assert np.allclose(rows[:, 1:], cpp[:, 1:], atol=1e-5, rtol=0)
    assert est.counters["frames_rejected"] == 0 and est.counters["frames_in"] >= rows.shape[0]
    s = est.state
    assert s.quality == "tracking" and s.p_WB.shape == (3,) and abs(np.linalg.norm(s.q_WB_wxyz) - 1) < 1e-9
    gt = kestrel.load_trajectory(hover_log)
    assert kestrel.ate(gt, rows)["rmse"] < 0.05


@pytest.mark.parametrize("backend", kestrel.backends().split(", "))
def test_every_backend_runs_from_python(hover_log, backend):
    recs = records_of(hover_log)
    est = kestrel.Estimator(kestrel.open_log(hover_log).rig, backend)
    states = []
    # IMU dead reckoning takes nothing from the camera: its poses come at IMU rate only.
    imu_only = backend == "imu"
    est.on_state(states.append, imu_rate=imu_only)
    feed(est, recs, until_s=4.0)
    c = est.counters
    assert c["frames_in"] > 100 and c["imu_in"] > 700, c
    if imu_only:
        assert len(states) > 700 and not any(s.from_frame for s in states), (len(states), c)
    else:
        # on_state once per frame that changed the state, and only then.
        assert 60 < len(states) <= c["frames_in"] and all(s.from_frame for s in states), (len(states), c)
        assert est.trajectory().shape[0] > 60
    assert states[-1].quality != "uninitialized"


def test_depth_in_metres_is_the_same_as_depth_units(hover_log):
    recs = records_of(hover_log)
    rig = kestrel.open_log(hover_log).rig
    a, b = kestrel.Estimator(rig, "vo"), kestrel.Estimator(rig, "vo")
    feed(a, recs, until_s=3.0)
    feed(b, recs, until_s=3.0, depth_in_metres=True, scale=rig.depth_scale_m_per_unit)
    assert np.array_equal(a.trajectory(), b.trajectory())


def test_bad_frames_are_refused_with_the_expected_shape(hover_log):
    rig = kestrel.open_log(hover_log).rig
    est = kestrel.Estimator(rig, "vo")
    with pytest.raises(ValueError, match=r"\(120, 160, 3\) uint8"):
        est.add_frame(1, np.zeros((100, 160, 3), np.uint8))
    with pytest.raises(ValueError, match="dtype"):
        est.add_frame(1, np.zeros((120, 160, 3), np.float32))
    with pytest.raises(ValueError, match="depth"):
        est.add_frame(1, np.zeros((120, 160, 3), np.uint8), np.zeros((120, 161), np.uint16))
    with pytest.raises(ValueError, match="packed"):
        est.add_frame(1, np.zeros((120, 320, 3), np.uint8)[:, ::2])
    with pytest.raises(ValueError, match="backend"):
        kestrel.Estimator(rig, "nosuch")
    # Out of order: refused and counted, not an exception (the C++ contract).
    img = np.zeros((120, 160, 3), np.uint8)
    est.add_frame(2_000_000_000, img, np.zeros((120, 160), np.uint16))
    est.add_frame(1_000_000_000, img, np.zeros((120, 160), np.uint16))
    assert est.counters["frames_rejected"] == 1


def test_imu_batch_is_the_same_as_one_by_one(hover_log):
    imu = [r for r in records_of(hover_log) if r.type == "imu"][:400]
    rig = kestrel.open_log(hover_log).rig
    a, b = kestrel.Estimator(rig, "imu"), kestrel.Estimator(rig, "imu")
    for r in imu:
        a.add_imu(r.t_ns, r.gyro_rps, r.acc_mps2)
    b.add_imu_batch(np.array([r.t_ns for r in imu]), np.array([r.gyro_rps for r in imu]),
                    np.array([r.acc_mps2 for r in imu]))
    assert a.counters["imu_in"] == b.counters["imu_in"] == 400
    assert np.array_equal(a.state.p_WB, b.state.p_WB) and np.array_equal(a.state.q_WB_wxyz, b.state.q_WB_wxyz)
    with pytest.raises(ValueError, match="gyro_rps"):
        b.add_imu_batch(np.zeros(3, np.int64), np.zeros((2, 3)), np.zeros((3, 3)))


# ---- ATE / RPE on arrays, against numpy written from the definitions ----------------------------------------

def quat_to_R(q_xyzw):
    x, y, z, w = q_xyzw / np.linalg.norm(q_xyzw)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def R_to_quat_xyzw(R):
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    return np.array([(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w), w])


def umeyama_se3(est, gt):
    """Umeyama 1991 without scale: R, t minimising sum |gt - (R est + t)|^2."""
    mu_e, mu_g = est.mean(0), gt.mean(0)
    H = (gt - mu_g).T @ (est - mu_e) / len(est)
    U, _, Vt = np.linalg.svd(H)
    S = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    return R, mu_g - R @ mu_e


def synthetic_pair(seed=3):
    rng = np.random.default_rng(seed)
    n = 600
    t = np.arange(n) * 0.01
    p = np.stack([np.sin(t), np.cos(0.7 * t), 0.2 * t], 1)
    yaw = 0.3 * t
    q = np.stack([np.zeros(n), np.zeros(n), np.sin(yaw / 2), np.cos(yaw / 2)], 1)
    gt = np.column_stack([t, p, q])
    # The estimate: the same motion in another world frame, with noise on position and heading.
    Rw = quat_to_R(np.array([0.1, -0.2, 0.3, 0.9]))
    tw = np.array([1.0, -2.0, 0.5])
    est = gt.copy()
    for i in range(n):
        R_noise = quat_to_R(np.array([*rng.normal(0, 0.01, 3), 1.0]))
        est[i, 1:4] = Rw @ (p[i] + rng.normal(0, 0.02, 3)) + tw
        est[i, 4:8] = R_to_quat_xyzw(Rw @ quat_to_R(q[i]) @ R_noise)
    return gt, est


def test_ate_matches_umeyama_in_numpy():
    gt, est = synthetic_pair()
    R, t = umeyama_se3(est[:, 1:4], gt[:, 1:4])
    err = np.linalg.norm(gt[:, 1:4] - (est[:, 1:4] @ R.T + t), axis=1)
    ate = kestrel.ate(gt, est, align="se3")
    assert ate["count"] == len(gt)
    assert ate["rmse"] == pytest.approx(math.sqrt(np.mean(err ** 2)), rel=1e-9)
    assert ate["max"] == pytest.approx(err.max(), rel=1e-9)
    assert ate["median"] == pytest.approx(np.median(err), rel=1e-9)
    # Without alignment the world offset is the error.
    assert kestrel.ate(gt, est, align="none")["rmse"] > 1.0


def test_rpe_matches_the_definition_in_numpy():
    gt, est = synthetic_pair()
    delta = 0.5
    step = 50  # poses every 10 ms: the pair of i is i + 50, exactly delta later

    def T(row):
        M = np.eye(4)
        M[:3, :3] = quat_to_R(row[4:8])
        M[:3, 3] = row[1:4]
        return M

    trans, rot = [], []
    for i in range(len(gt) - step):
        dg = np.linalg.inv(T(gt[i])) @ T(gt[i + step])
        de = np.linalg.inv(T(est[i])) @ T(est[i + step])
        E = np.linalg.inv(dg) @ de
        trans.append(np.linalg.norm(E[:3, 3]))
        rot.append(math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(E[:3, :3]) - 1) / 2)))))
    rpe = kestrel.rpe(gt, est, delta_s=delta, align="se3")
    assert rpe["pairs"] == len(trans)
    assert rpe["trans_rmse_m"] == pytest.approx(math.sqrt(np.mean(np.square(trans))), rel=1e-9)
    assert rpe["rot_rmse_deg"] == pytest.approx(math.sqrt(np.mean(np.square(rot))), rel=1e-6)


def test_metrics_refuse_malformed_arrays():
    gt, est = synthetic_pair()
    with pytest.raises(ValueError, match=r"est: expected an \(N, 8\)"):
        kestrel.evaluate(gt, est[:, :7])
    bad = est.copy()
    bad[10, 0] = bad[5, 0]
    with pytest.raises(ValueError, match="est: row 10"):
        kestrel.evaluate(gt, bad)
    bad = est.copy()
    bad[3, 2] = np.nan
    with pytest.raises(ValueError, match="est: row 3 column 2 is not finite"):
        kestrel.evaluate(gt, bad)


def test_tum_files_round_trip(tmp_path):
    gt, _ = synthetic_pair()
    path = tmp_path / "gt.txt"
    kestrel.write_tum(path, gt)
    back = kestrel.load_trajectory(path)
    assert back.shape == gt.shape
    assert np.allclose(back, gt, atol=1e-6, rtol=0)


# ---- docs/python.md's worked example ------------------------------------------------------------------------

def test_the_docs_example_runs_and_tracks(tmp_path, hover_log):
    import re
    import sys
    page = os.path.join(os.path.dirname(__file__), "..", "..", "docs", "python.md")
    with open(page) as f:
        blocks = re.findall(r"```python\n(.*?)```", f.read(), re.S)
    assert len(blocks) == 1, "docs/python.md should hold exactly one python example"
    script = tmp_path / "example.py"
    script.write_text(blocks[0])
    out = subprocess.run([sys.executable, str(script), str(hover_log)], check=True, capture_output=True,
                         text=True).stdout
    ates = [float(a) for a in re.findall(r"ATE ([0-9.]+) m", out)]
    assert len(ates) == 2, out
    assert max(ates) < 0.05, out
    assert "final quality tracking" in out, out

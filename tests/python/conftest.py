"""Fixtures for the `import kestrel` tests: the built module (PYTHONPATH set by ctest) and a simulated log
made by this build's `kestrel sim` (KESTREL_BIN_DIR set by ctest)."""
import os
import subprocess

import pytest


def bin_dir():
    d = os.environ.get("KESTREL_BIN_DIR")
    if not d:
        raise RuntimeError("KESTREL_BIN_DIR is not set: run these tests through ctest (tests/python/CMakeLists.txt)")
    return d


@pytest.fixture(scope="session")
def hover_log(tmp_path_factory):
    """An 8 s simulated hover, 160x120 RGB-D at 30 Hz with a 200 Hz IMU and ground truth."""
    path = tmp_path_factory.mktemp("sim") / "hover.klog"
    subprocess.run([os.path.join(bin_dir(), "kestrel"), "sim", "--scenario", "hover", "--duration", "8", "--seed", "5",
                    "--width", "160", "--height", "120", "--out", str(path)], check=True, stdout=subprocess.DEVNULL)
    return path

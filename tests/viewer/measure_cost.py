#!/usr/bin/env python3
"""The viewer's cost figures in docs/viewer.md, reproducibly.

Replays one log in realtime pace three times, alternating RUNS times:
  off     without --view
  idle    with --view and no browser
  socket  with --view and one bare WebSocket reader that drains the stream and
          draws nothing: the vehicle's side of a browser on a laptop
  client  with --view and one headless chromium watching (browser_check.Browser);
          here the browser's own rendering (WebGL on the CPU) shares the
          machine with the estimator, which a laptop would not
and prints, per run, tracking p50/p99, IMU->pose p99, the estimator thread's
steady-state allocations and, with --view, the viewer thread's CPU (ms per
second of streaming) and the stream's kB/s. Not a ctest: it takes minutes and
its figures depend on the machine; the browser test checks the contracts.

  python3 tests/viewer/measure_cost.py --kestrel build/release/bin/kestrel \
      --log /tmp/fig8_vga.klog --out-dir /tmp/viewer_cost [--runs 2] [--modes off,idle,socket,client]
"""
import argparse
import json
import os
import re
import subprocess
import socket
import sys
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from browser_check import Browser, CheckFailed, websocket_handshake  # noqa: E402


def drain(url, stop):
    """A WebSocket client that reads and discards everything until stop is set."""
    port = int(re.search(r":(\d+)/", url).group(1))
    s, status = websocket_handshake(port)
    if "101" not in status:
        raise CheckFailed(f"WebSocket handshake refused: {status}")
    s.settimeout(0.2)
    while not stop.is_set():
        try:
            if not s.recv(1 << 20):
                break
        except socket.timeout:
            pass
        except OSError:
            break
    s.close()


def replay(args, mode, i, browser):
    metrics = os.path.join(args.out_dir, f"{mode}_{i}.json")
    cmd = [args.kestrel, "replay", args.log, "--pace", "realtime", "--status", "off", "--metrics-out", metrics]
    if mode != "off":
        cmd += ["--view", "127.0.0.1:0"]
    if mode in ("socket", "client"):
        cmd += ["--view-wait", "60"]  # the log starts once the reader is connected
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    stop = threading.Event()
    reader = None
    if mode in ("socket", "client"):
        line = p.stdout.readline()
        m = re.search(r"viewer: (http://\S+)", line)
        if not m:
            p.kill()
            raise CheckFailed(f"no viewer URL from kestrel replay: {line!r}")
        if mode == "client":
            browser.go(m.group(1))
        else:
            reader = threading.Thread(target=drain, args=(m.group(1), stop), daemon=True)
            reader.start()
    rest = p.communicate(timeout=600)[0]
    stop.set()
    if reader:
        reader.join(5)
    if p.returncode != 0:
        raise CheckFailed(f"{' '.join(cmd)} exited with {p.returncode}: {rest[-500:]}")
    with open(metrics) as f:
        return json.load(f)


def row(mode, m):
    lat = m["latency"]
    out = (f"{mode:7s} tracking p50 {lat['tracking']['p50_ms']:6.2f} ms  p99 {lat['tracking']['p99_ms']:6.2f} ms  "
           f"IMU->pose p99 {lat['imu_to_output']['p99_ms']:6.2f} ms  "
           f"estimator-thread allocs {m['allocations']['estimator_thread_steady']}  "
           f"process CPU {m['cpu_s']:.1f} s")
    v = m.get("viewer")
    if v:
        out += (f"  | viewer {v['cpu_ms_per_s']:.1f} ms CPU/s, {v['kbytes_per_s']:.0f} kB/s, "
                f"{v['frames_sent']} frames sent, {v['frames_skipped_budget']} skipped (cap), "
                f"{v['snapshots_skipped']} snapshots skipped")
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--kestrel", required=True)
    ap.add_argument("--log", required=True)
    ap.add_argument("--out-dir", required=True)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--modes", default="off,idle,socket,client")
    args = ap.parse_args()
    os.makedirs(args.out_dir, exist_ok=True)
    browser = Browser(args.out_dir)
    try:
        for i in range(args.runs):
            for mode in args.modes.split(","):
                print(row(mode, replay(args, mode, i, browser)), flush=True)
                if mode == "client":
                    browser.go("about:blank")
                time.sleep(1)
    except CheckFailed as e:
        print("FAILED:", e)
        return 1
    finally:
        browser.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())

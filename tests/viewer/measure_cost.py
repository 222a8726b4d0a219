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
      [--fifo] [--browser-nice 19]
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


def renice_tree(root_pid, nice):
    """Every process below root_pid (chromedriver -> chromium and its renderers) to `nice`."""
    children = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(d))
    todo = list(children.get(root_pid, []))
    while todo:
        pid = todo.pop()
        # Linux applies a nice value per thread: every thread of the process.
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        except OSError:
            tids = []
        for tid in tids:
            try:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
            except OSError:
                pass
        todo.extend(children.get(pid, []))


def replay(args, mode, i, browser):
    metrics = os.path.join(args.out_dir, f"{mode}_{i}.json")
    cmd = [args.kestrel, "replay", args.log, "--pace", "realtime", "--status", "off", "--metrics-out", metrics]
    if args.config:
        cmd += ["--config", args.config]
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
            if args.browser_nice:
                renice_tree(browser.driver.pid, args.browser_nice)
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
    ap.add_argument("--config", default="", help="passed to kestrel replay --config")
    ap.add_argument("--fifo", action="store_true",
                    help="tracking at SCHED_FIFO 50 and kst-propagate at 60, unpinned (as it flies; docs/threads.md): "
                         "writes that threads: table to OUT_DIR/fifo.yaml and replays with it")
    ap.add_argument("--browser-nice", type=int, default=0,
                    help="client mode: renice chromium to this after it loads the page (does its CPU move p99?)")
    args = ap.parse_args()
    os.makedirs(args.out_dir, exist_ok=True)
    if args.fifo:
        if args.config:
            ap.error("--fifo writes its own config: not with --config")
        args.config = os.path.join(args.out_dir, "fifo.yaml")
        with open(args.config, "w") as f:
            f.write("threads:\n"
                    "  kst-propagate: {cpu: -1, policy: fifo, priority: 60}\n"
                    "  kst-estimator: {cpu: -1, policy: fifo, priority: 50}\n")
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

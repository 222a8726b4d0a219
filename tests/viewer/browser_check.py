#!/usr/bin/env python3
"""Checks the live viewer and the HTML evaluation report in a real browser.

Debian's chromium, headless, driven by chromedriver over the W3C WebDriver
protocol (plain HTTP + JSON: no client library needed). Two modes:

  viewer  replays LOG with `kestrel replay --pace lockstep --view`, loads the
          page with ?paused (the replay holds from the moment it connects, so
          no check races a replay faster than real time), steps through the
          first second of flight one frame at a time and checks what a person
          would see (image updating, trajectory drawn in the 3-D view, the
          estimator's name in the state panel, pause / step), throws bad
          requests at the server meanwhile, then resumes, lets the replay
          finish and checks its metrics (no estimator-thread allocation with
          a browser connected).
  report  runs `kestrel eval --report` and checks the page opens with no
          network and shows its plots.

Each saves a screenshot into --out-dir. Exit 0: passed; 1: a check failed
(the message says which); 77: cannot run here (printed as SKIPPED).
"""
import argparse
import base64
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request

CHROME_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--window-size=1600,1000", "--disable-dev-shm-usage",
                # WebGL on the CPU (SwiftShader): headless has no GPU, and chromium no longer falls back silently.
                "--enable-unsafe-swiftshader"]


class CheckFailed(Exception):
    pass


def check(cond, what):
    if not cond:
        raise CheckFailed(what)
    print("ok:", what, flush=True)


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Browser:
    """A chromium session through chromedriver (W3C WebDriver over HTTP)."""

    def __init__(self, workdir):
        self.port = free_port()
        self.log = open(os.path.join(workdir, "chromedriver.log"), "w")
        self.driver = subprocess.Popen(["chromedriver", f"--port={self.port}"], stdout=self.log, stderr=self.log)
        self.base = f"http://127.0.0.1:{self.port}"
        deadline = time.time() + 20
        while True:
            try:
                self._req("GET", "/status")
                break
            except (urllib.error.URLError, ConnectionError):
                if time.time() > deadline:
                    raise CheckFailed("chromedriver did not start (see chromedriver.log)")
                time.sleep(0.2)
        profile = tempfile.mkdtemp(prefix="kestrel_chromium_", dir=workdir)
        caps = {"capabilities": {"alwaysMatch": {"browserName": "chrome", "goog:chromeOptions": {
            "binary": shutil.which("chromium") or "/usr/bin/chromium",
            "args": CHROME_FLAGS + [f"--user-data-dir={profile}"]},
            "goog:loggingPrefs": {"browser": "ALL"}}}}
        self.session = self._req("POST", "/session", caps)["sessionId"]

    def _req(self, method, path, body=None, timeout=60):
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(self.base + path, data=data, method=method,
                                     headers={"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(req, timeout=timeout) as r:
                return json.loads(r.read() or b"{}").get("value")
        except urllib.error.HTTPError as e:
            raise CheckFailed(f"WebDriver {method} {path}: {e.code} {e.read()[:400]!r}")

    def s(self, method, path, body=None):
        return self._req(method, f"/session/{self.session}{path}", body)

    def go(self, url):
        self.s("POST", "/url", {"url": url})

    def js(self, script, *args):
        return self.s("POST", "/execute/sync", {"script": script, "args": list(args)})

    def js_async(self, script, timeout_s):
        """A script that ends by calling its last argument with the result."""
        self.s("POST", "/timeouts", {"script": int(timeout_s * 1000)})
        return self.s("POST", "/execute/async", {"script": script, "args": []})

    def click(self, css):
        el = self.s("POST", "/element", {"using": "css selector", "value": css})
        eid = next(iter(el.values()))
        self.s("POST", f"/element/{eid}/click", {})

    def screenshot(self, path):
        with open(path, "wb") as f:
            f.write(base64.b64decode(self.s("GET", "/screenshot")))

    def wait(self, script, what, timeout_s=30):
        deadline = time.time() + timeout_s
        last = None
        while time.time() < deadline:
            last = self.js(script)
            if last:
                return last
            time.sleep(0.2)
        raise CheckFailed(f"{what} (waited {timeout_s} s; last value {last!r})")

    def console(self):
        """The page's console since the last call (errors explain a failure)."""
        try:
            return self.s("POST", "/se/log", {"type": "browser"}) or []
        except CheckFailed:
            return []

    def close(self):
        try:
            self._req("DELETE", f"/session/{self.session}", timeout=10)
        except Exception:
            pass
        self.driver.terminate()
        try:
            self.driver.wait(10)
        except subprocess.TimeoutExpired:
            self.driver.kill()
        self.log.close()


# ---------------------------------------------------------------- bad requests
def http_status(port, path):
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(f"GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n".encode())
        head = s.recv(4096).decode(errors="replace")
    m = re.match(r"HTTP/1\.[01] (\d+)", head)
    return int(m.group(1)) if m else None


def websocket_handshake(port, path="/ws"):
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET {path} HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = s.recv(4096)
        if not chunk:
            break
        head += chunk
    return s, head.decode(errors="replace").split("\r\n")[0]


def malformed_frame_closes(port):
    """A frame with reserved bits and opcode set: the server must fail the connection."""
    s, status = websocket_handshake(port)
    if "101" not in status:
        s.close()
        return f"handshake refused: {status}"
    s.sendall(bytes([0x7F, 0xFF]) + os.urandom(64))
    s.settimeout(5)
    deadline = time.time() + 5
    try:
        while time.time() < deadline:
            if not s.recv(65536):
                return "closed"
    except (ConnectionResetError, BrokenPipeError):
        return "closed"
    except socket.timeout:
        return "still open after 5 s"
    finally:
        s.close()
    return "still open"


def flood(port, n):
    socks = []
    for _ in range(n):
        try:
            socks.append(socket.create_connection(("127.0.0.1", port), timeout=2))
        except OSError:
            break
    return socks


# ---------------------------------------------------------------- viewer mode
def run_viewer(args, b):
    cmd = [args.kestrel, "replay", args.log, "--pace", "lockstep", "--view", "127.0.0.1:0", "--view-wait", "60",
           "--metrics-out", os.path.join(args.out_dir, "viewer_metrics.json"), "--status", "off",
           # The dense map on: its blocks must reach the page too (docs/dense.md, "The viewer stream").
           "--dense-out", os.path.join(args.out_dir, "viewer_dense.ply")]
    print("running:", " ".join(cmd), flush=True)
    out_path = os.path.join(args.out_dir, "viewer_replay.log")
    out = open(out_path, "w+")
    replay = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
    try:
        url = None
        deadline = time.time() + 30
        while url is None and time.time() < deadline:
            out.flush()
            with open(out_path) as f:
                m = re.search(r"viewer: (http://\S+)", f.read())
            if m:
                url = m.group(1)
            elif replay.poll() is not None:
                raise CheckFailed(f"kestrel replay exited with {replay.returncode} before serving: {open(out_path).read()}")
            else:
                time.sleep(0.1)
        check(url is not None, "kestrel replay --view printed the viewer's URL")
        port = int(re.search(r":(\d+)/", url).group(1))

        # ?paused: the page holds the lockstep replay as soon as it connects, so
        # nothing below races a replay that runs faster than real time.
        b.go(url + "?paused")
        b.wait("return window.kestrelViewer && window.kestrelViewer.connected", "the page connected its WebSocket")
        b.wait("return document.getElementById('estimator').textContent === 'window'",
               "the header names the estimator (window)")
        b.wait("const v = window.kestrelViewer; return v.paused && v.heldFrame > 0 && !!v.state && "
               "v.state.frames === v.heldFrame", "?paused held the replay and the page shows the frame it holds at")
        f0 = b.js("return window.kestrelViewer.state.frames")
        # Step through the first second or so of flight, one frame at a time:
        # each step lets exactly one frame through and the page shows it.
        r = b.js_async("""
          const done = arguments[arguments.length - 1];
          const v = window.kestrelViewer;
          const enough = () => v.framesShown >= 3 && v.trajectoryPoints >= 30 && v.keyframes >= 1 && v.mapPoints > 0;
          let steps = 0;
          function next() {
            if (enough() || steps >= 300) { done({steps: steps, frames: v.state.frames}); return; }
            const f = v.state.frames;
            document.getElementById('btn-step').click();
            ++steps;
            const t0 = performance.now();
            (function poll() {
              if (v.paused && v.heldFrame === f + 1 && v.state.frames === f + 1) next();
              else if (v.state.frames > f + 1) done({error: `step ${steps} let ${v.state.frames - f} frames through`});
              else if (performance.now() - t0 > 15000)
                done({error: `step ${steps} from frame ${f}: frame ${f + 1} not shown in 15 s (held ${v.heldFrame}, shown ${v.state.frames})`});
              else setTimeout(poll, 10);
            })();
          }
          next();""", 240)
        check("error" not in r, f"every step let exactly one frame through and showed it ({r})")
        check(r["frames"] == f0 + r["steps"], f"{r['steps']} steps from frame {f0} reached frame {r['frames']}")
        check(b.js("const v = window.kestrelViewer; return v.framesShown >= 3 && v.trajectoryPoints >= 30"),
              "camera frames shown and >= 30 trajectory points in the 3-D view")
        check(b.js("return document.getElementById('rgb').naturalWidth > 0"), "the camera image is shown")
        check(b.js("return document.getElementById('state-table').textContent.includes('window')"),
              "the state panel shows the estimator name")
        check(b.js("return document.getElementById('features').width > 0"), "the feature overlay is drawn")
        # The pipeline's perf registry reaches the page: every counter by path, in a table opened on demand.
        check(b.js("const p = window.kestrelViewer.state.perf; return !!p && 'input.frames_missing' in p && "
                   "'window.solves_ok' in p && p['estimator.frames_in'] > 0"),
              "the state carries the pipeline's counters by path")
        b.js("const d = document.getElementById('perf-box'); d.open = true; return d.hidden")
        b.wait("return document.getElementById('perf-table').textContent.includes('rings.imu_drops')",
               "the opened 'every counter' table lists the registry")
        check(b.js("return document.getElementById('depth').naturalWidth > 0"), "the depth colour map is shown")
        b.wait("const v = window.kestrelViewer; return v.keyframes >= 1 && v.mapPoints > 0 && v.groundTruthPoints > 0 && v.aligned",
               "keyframes, map points and the aligned ground truth reached the 3-D view")
        check(b.js("return window.kestrelViewer.webgl && window.kestrelViewer.renders > 5"), "WebGL renders the 3-D view")
        time.sleep(0.5)  # a few more renders with everything in the scene
        lit = b.js("""
          const c = document.querySelector('#three canvas');
          const t = document.createElement('canvas'); t.width = c.width; t.height = c.height;
          const g = t.getContext('2d'); g.drawImage(c, 0, 0);
          const d = g.getImageData(0, 0, t.width, t.height).data;
          let n = 0;
          for (let i = 0; i < d.length; i += 4) if (Math.abs(d[i] - 16) + Math.abs(d[i+1] - 19) + Math.abs(d[i+2] - 23) > 60) n++;
          return n;""")
        check(lit > 500, f"the 3-D canvas shows drawn geometry ({lit} bright pixels)")

        # Paused holds the replay; a step lets exactly one frame through, and the image element follows.
        f1 = b.js("return window.kestrelViewer.state.frames")
        time.sleep(1.5)
        f2 = b.js("return window.kestrelViewer.state.frames")
        check(f1 == f2, f"paused: the frame count holds ({f1} -> {f2})")
        src0 = b.js("return document.getElementById('rgb').src")
        b.click("#btn-step")
        b.wait(f"const v = window.kestrelViewer; return v.state.frames === {f1 + 1} && v.heldFrame === {f1 + 1}",
               "step: exactly one more frame, shown", 15)
        b.wait(f"return document.getElementById('rgb').src !== {json.dumps(src0)} && "
               "document.getElementById('rgb').naturalWidth > 0", "the camera image element updates")
        time.sleep(1.0)
        check(b.js("return window.kestrelViewer.state.frames") == f1 + 1, "after the step the replay holds again")
        b.screenshot(os.path.join(args.out_dir, "viewer.png"))
        print("screenshot:", os.path.join(args.out_dir, "viewer.png"), flush=True)

        # Bad requests while a browser watches: none may crash or stall anything.
        check(http_status(port, "/no/such/page") == 404, "an unknown path gets 404")
        check(http_status(port, "/../../etc/passwd") == 404, "a path outside the page gets 404")
        s, status = websocket_handshake(port, "/elsewhere")
        s.close()
        check("404" in status, f"a WebSocket on another path is refused ({status})")
        check(malformed_frame_closes(port) == "closed", "a malformed WebSocket frame closes that connection")
        socks = flood(port, 200)
        time.sleep(0.5)
        served = http_status(port, "/viewer.css")
        for s in socks:
            s.close()
        check(served == 200 or served is None, f"during a flood of {len(socks)} connections the server stays up")
        b.click("#btn-resume")
        b.wait("return !window.kestrelViewer.paused", "resume reached the replay")
        n0 = b.js("return window.kestrelViewer.statesReceived")
        b.wait(f"return window.kestrelViewer.statesReceived > {n0} + 3 || window.kestrelViewer.ended",
               "the page keeps updating after the bad requests")
        code = replay.wait(timeout=120)
        check(code == 0, f"the replay finished normally (exit {code})")
        b.wait("const v = window.kestrelViewer; return v.denseMessages > 0 && v.densePoints > 1000 && v.denseBlocks > 10",
               "the dense map's blocks reached the page and were drawn")
        print("dense map on the page: %d points in %d blocks from %d messages" % tuple(
            b.js("const v = window.kestrelViewer; return [v.densePoints, v.denseBlocks, v.denseMessages]")), flush=True)
    finally:
        if replay.poll() is None:
            replay.kill()
            replay.wait()
        else:
            print(f"kestrel replay exited with {replay.returncode}", flush=True)
        out.close()
    with open(os.path.join(args.out_dir, "viewer_metrics.json")) as f:
        m = json.load(f)
    steady = m["allocations"]["estimator_thread_steady"]
    check(steady == 0, f"no estimator-thread allocation after warm-up with a browser connected ({steady})")
    d = m["dense"]
    check(d is not None and d["view_messages"] > 0, "kst-dense encoded the dense map for the viewer")
    v = m["viewer"]
    check(v["browsers"] >= 1 and v["frames_sent"] > 0, f"the viewer streamed frames ({v['frames_sent']})")
    check(v["protocol_errors"] >= 1, f"the malformed frame was counted ({v['protocol_errors']})")
    check(v["connections_refused"] > 0, f"the flood was capped ({v['connections_refused']} refused)")
    print(f"viewer cost: {v['kbytes_per_s']:.1f} kB/s, {v['cpu_ms_per_s']:.1f} ms CPU per s over "
          f"{v['streaming_s']:.1f} s", flush=True)


# ---------------------------------------------------------------- report mode
def run_report(args, b):
    est = os.path.join(args.out_dir, "report_est.txt")
    metrics = os.path.join(args.out_dir, "report_metrics.json")
    html = os.path.join(args.out_dir, "report.html")
    r = subprocess.run([args.kestrel, "replay", args.log, "--traj-out", est, "--metrics-out", metrics, "-q"],
                       capture_output=True, text=True)
    check(r.returncode == 0, f"replay for the report ({r.stderr.strip()[:300]})")
    r = subprocess.run([args.kestrel, "eval", "--gt", args.log, "--est", est, "--report", html, "--metrics", metrics],
                       capture_output=True, text=True)
    check(r.returncode == 0, f"kestrel eval --report ({r.stderr.strip()[:300]})")
    text = open(html, encoding="utf-8").read()
    external = re.findall(r"""(?:src|href)\s*=\s*["'](?:https?:)?//[^"']*""", text)
    check(not external, f"the report loads nothing from the network ({external[:3]})")
    b.go("file://" + os.path.abspath(html))
    b.wait("return document.readyState === 'complete'", "the report loads")
    check("ATE" in b.js("return document.body.textContent"), "the report shows the ATE")
    for pid in ["top-view", "side-view", "error-time", "error-axes", "rpe"]:
        check(b.js(f"return !!document.getElementById('{pid}')"), f"the report has the {pid} plot")
    n = b.js("return Array.from(document.querySelectorAll('#top-view polyline')).map(p => p.points.numberOfItems).reduce((a, b) => a + b, 0)")
    check(n >= 100, f"the top view draws the trajectories ({n} points)")
    rows = b.js("return document.querySelectorAll('#rpe-table tbody tr').length")
    check(rows >= 3, f"RPE over several deltas ({rows} rows)")
    bars = b.js("return document.querySelectorAll('#latency rect.bar').length")
    check(bars > 5, f"the run's latency histograms are drawn ({bars} bars)")
    b.screenshot(os.path.join(args.out_dir, "report.png"))
    print("screenshot:", os.path.join(args.out_dir, "report.png"), flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", choices=["viewer", "report"])
    ap.add_argument("--kestrel", required=True)
    ap.add_argument("--log", required=True)
    ap.add_argument("--out-dir", required=True)
    args = ap.parse_args()
    os.makedirs(args.out_dir, exist_ok=True)
    b = Browser(args.out_dir)
    try:
        (run_viewer if args.mode == "viewer" else run_report)(args, b)
    except CheckFailed as e:
        print("FAILED:", e, flush=True)
        try:
            print("page state:", json.dumps(b.js("const v = Object.assign({}, window.kestrelViewer); delete v.hello; delete v.state; return v;")), flush=True)
        except Exception:
            pass
        try:
            b.screenshot(os.path.join(args.out_dir, f"{args.mode}_failed.png"))
        except Exception:
            pass
        for entry in b.console():
            if entry.get("level") in ("SEVERE", "WARNING"):
                print("console:", entry.get("level"), entry.get("message"), flush=True)
        return 1
    finally:
        b.close()
    print("PASSED", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

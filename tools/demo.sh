#!/usr/bin/env bash
# The README's main job: installs what is missing, builds `release`, simulates a
# 30 s RGB-D + IMU hover flight, replays it through the estimator in lockstep and
# scores the trajectory against the simulator's ground truth.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
bash tools/install-deps.sh
bash tools/build.sh release --target kestrel
k=build/release/bin/kestrel
out=build/demo
mkdir -p "$out"
echo "== kestrel sim: 30 s hover, VGA RGB-D at 30 Hz, BMX055-model IMU at 400 Hz =="
"$k" sim --scenario hover --duration 30 --seed 1 --out "$out/hover.klog"
echo "== kestrel replay (lockstep) =="
"$k" replay "$out/hover.klog" --pace lockstep --traj-out "$out/est.txt" --metrics-out "$out/metrics.json"
echo "== kestrel eval: estimate vs ground truth =="
"$k" eval --gt "$out/hover.klog" --est "$out/est.txt" --plot "$out/trajectory.svg"
echo "demo: outputs in $out/ (trajectory est.txt, metrics.json, trajectory.svg)"

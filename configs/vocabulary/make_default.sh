#!/usr/bin/env bash
# How configs/vocabulary/kestrel_orb_k10l4.kvoc was made (docs/map.md).
set -euo pipefail
K=build/release/bin/kestrel
E=../shared/data/euroc
W=${1:-/tmp/kestrel-vocab}  # scratch for the renders (about 7 GB while it runs)
mkdir -p "$W"
$K sim --scenario figure8 --duration 40 --seed 7 --out "$W/figure8.klog"
$K sim --scenario hover --duration 20 --seed 7 --out "$W/hover.klog"
$K sim --trajectory $E/V1_01_easy/gt_body_20hz.csv --imu $E/V1_01_easy/imu0.csv --duration 30 --seed 7 --out "$W/v101.klog"
$K sim --trajectory $E/MH_01_easy/gt_body_20hz.csv --imu $E/MH_01_easy/imu0.csv --start 60 --duration 30 --seed 7 --out "$W/mh01.klog"
$K vocab --out configs/vocabulary/kestrel_orb_k10l4.kvoc --k 10 --levels 4 --seed 1 --features 500 --every 10 \
  "$W/figure8.klog" "$W/hover.klog" "$W/v101.klog" "$W/mh01.klog" \
  ../shared/data/real-rgbd/7scenes_first500 $E/V1_01_easy_first95
rm -rf "$W"

#!/bin/bash
# The speed goals (docs/results/benchmarks.md) in one sitting, beside the references (run from the repository's
# root after `cargo build --release`; needs python3 with opencv-python for the reference):
#   benches/speed_sitting.sh SESSION_1280x960 SESSION_16BIT
# left01 detection + single-view calibration, Glint and OpenCV alternated five times; then
# `glint validate` on SESSION_1280x960 (e.g. `glint run --rig rigs/mock.toml --out s1`) and
# `glint fit` on SESSION_16BIT (the same rig with camera.bit_depth = 16: a polynomial
# response, whose 40 draws the fit re-merges), three runs each.
set -u
G=./target/release/glint
IMG=../shared/data/opencv_stereo_chessboard_9x6/images/left01.jpg
if [ $# -ne 2 ]; then
  echo "usage: $0 SESSION_1280x960 SESSION_16BIT" >&2
  exit 2
fi
uptime
lscpu | grep "Model name"
if [ -f "$IMG" ]; then
  for i in 1 2 3 4 5; do
    $G bench calib --image "$IMG" --repeats 101 2>&1 | tail -1
    python3 benches/opencv_calib_timing.py "$IMG" 2>&1 | tail -1
  done
else
  echo "skipped left01: $IMG is absent (it comes with ../shared/data)"
fi
for i in 1 2 3; do /usr/bin/time -f "validate: %e s wall, %U s user, %S s sys" $G validate "$1" 2>&1 >/dev/null | tail -1; done
for i in 1 2 3; do /usr/bin/time -f "fit: %e s wall, %U s user" $G fit "$2" 2>&1 >/dev/null | tail -1; done
uptime

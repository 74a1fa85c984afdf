#!/usr/bin/env bash
# The main job, from a fresh clone: native setup if needed, release build, then
#  1. a rendered view of the scene: every camera's RGB, depth and point cloud under out/demo/;
#  2. a closed-loop run of keyframes through IK -> ruckig -> OSC at 1 kHz (log: out/demo/track.csv)
#     and a 10 cm step response of the controller (plot: out/demo/step.png);
#  3. an expert episode of a task, as an animated GIF (out/demo/push_buttons.gif);
#  4. the simulator, renderer and controller benchmarks.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
scripts/setup.sh
cargo build --release --locked
bin=target/release/flowram
"$bin" render --scene default --camera all --size 128 --out out/demo
echo "open out/demo/<camera>/rgb.png, or out/demo/merged.ply in MeshLab / Open3D"
"$bin" track --keyframes scripts/demo_keyframes.json --log out/demo/track.csv
"$bin" tune --step 0.1,0,0 --plot out/demo/step.png
"$bin" run --task push_buttons --seed 21 --video out/demo/push_buttons.gif
"$bin" bench sim
"$bin" bench render
"$bin" bench control

#!/usr/bin/env bash
# The main job, from a fresh clone: native setup if needed, release build, then a rendered
# simulation of the scene (every camera's RGB, depth and point cloud under out/demo/) and the
# simulator and renderer benchmarks.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
scripts/setup.sh
cargo build --release --locked
bin=target/release/flowram
"$bin" render --scene default --camera all --size 128 --out out/demo
echo "open out/demo/<camera>/rgb.png, or out/demo/merged.ply in MeshLab / Open3D"
"$bin" bench sim
"$bin" bench render

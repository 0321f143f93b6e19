#!/usr/bin/env bash
# Install volcap (editable, with test extras) and make sure an OpenCL device can build kernels.
# The pip PoCL (LLVM 14) cannot compile for CPUs newer than that LLVM knows ("unknown target CPU
# 'generic'"); then the distribution's PoCL is installed with apt (needs root or sudo).
set -euo pipefail
cd "$(dirname "$0")"
python3 -m pip install --quiet --disable-pip-version-check -e ".[test]"
if ! python3 -m nodegraph.clrt 2>/dev/null; then
    echo "setup: the pip PoCL cannot build kernels on this CPU; installing the distribution's PoCL" >&2
    SUDO=""
    [ "$(id -u)" = 0 ] || SUDO="sudo"
    if command -v apt-get >/dev/null; then
        $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq pocl-opencl-icd >/dev/null
    fi
    python3 -m nodegraph.clrt  # fails with a clear message if there is still no working device
fi

#!/usr/bin/env bash
# Install volcap (editable, with test extras), make sure an OpenCL device can build kernels, and install
# headless Chromium for the report test.
# - The pip PoCL (LLVM 14) cannot compile for CPUs newer than that LLVM knows ("unknown target CPU
#   'generic'"); then the distribution's PoCL is installed with apt (needs root or sudo).
# - tests/test_report.py opens the HTML report in Debian's `chromium`.
set -euo pipefail
cd "$(dirname "$0")"
python3 -m pip install --quiet --disable-pip-version-check -e ".[test]"
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
apt_install() {
    if command -v apt-get >/dev/null; then
        $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$@" >/dev/null
    else
        echo "setup: no apt-get here; install $* with your package manager" >&2
    fi
}
if ! python3 -m nodegraph.clrt 2>/dev/null; then
    echo "setup: the pip PoCL cannot build kernels on this CPU; installing the distribution's PoCL" >&2
    apt_install pocl-opencl-icd
    python3 -m nodegraph.clrt  # fails with a clear message if there is still no working device
fi
if ! command -v chromium >/dev/null 2>&1; then
    echo "setup: installing headless Chromium (used by the report test)" >&2
    apt_install chromium
fi

"""OpenCL device choice: devices that fail their probe are never used; among the others the documented first
choice (GPU, then PoCL >= 3.1, then Intel's CPU runtime, then older PoCL) wins unless the probes measured
another a quarter faster. The probes run in a child process with a time limit, and the ranking is kept."""
from __future__ import annotations

import json
import subprocess
import sys
from types import SimpleNamespace

from nodegraph import clrt


def fake(kind: str, version: str, name: str = "dev"):
    import pyopencl as cl

    t = cl.device_type.GPU if kind == "gpu" else cl.device_type.CPU
    return SimpleNamespace(type=t, name=name, platform=SimpleNamespace(version=version, name="p"), driver_version="1")


POCL31 = "OpenCL 3.0 PoCL 3.1+debian  Linux"
POCL30 = "OpenCL 3.0 PoCL 3.0-rc2  Linux"
INTEL = "OpenCL 3.1 LINUX"


def test_documented_order_wins_within_a_quarter():
    rows = [(66.0, 1, 0, fake("cpu", INTEL)), (78.0, 0, 0, fake("cpu", POCL31)), (60.0, 2, 0, fake("cpu", POCL30))]
    assert clrt.pick(rows)[3].platform.version == POCL31        # 60 ms is not a quarter faster than 78
    rows.append((30.0, 3, 0, fake("cpu", INTEL)))
    assert clrt.pick(rows)[0] == 30.0                            # a much faster device wins


def test_gpus_come_first():
    rows = [(50.0, 0, 0, fake("cpu", POCL31)), (55.0, 1, 0, fake("gpu", "OpenCL 3.0 CUDA"))]
    assert clrt.pick(rows)[3].type == fake("gpu", "").type


def test_probe_child_reports_milliseconds_for_the_device_in_use():
    res = subprocess.run([sys.executable, "-m", "nodegraph.clrt", "--probe"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout.strip().splitlines()[-1])["ms"] > 0


def test_a_device_that_fails_its_probe_is_unusable(monkeypatch):
    def broken(*a, **kw):
        raise subprocess.TimeoutExpired("probe", 1)

    monkeypatch.setattr(subprocess, "run", broken)
    assert clrt.probe_ms(0, 0) is None

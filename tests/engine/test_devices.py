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
    """The child runs the probes the stages register (the key kernels against their NumPy reference): it runs as
    __main__, and until stop 46 it read its own empty probe list, so the generic kernel alone ranked devices."""
    from nodegraph.node import registry

    registry()
    res = subprocess.run([sys.executable, "-m", "nodegraph.clrt", "--probe"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["ms"] > 0 and out["probes"] == len(clrt._PROBES) >= 1


def test_a_device_that_fails_its_probe_is_unusable(monkeypatch):
    def broken(*a, **kw):
        raise subprocess.TimeoutExpired("probe", 1)

    monkeypatch.setattr(subprocess, "run", broken)
    assert clrt.probe_ms(0, 0) is None


def test_the_probe_runs_the_project_from_any_folder(tmp_path, monkeypatch):
    """The child runs ``-m nodegraph.clrt`` from the project with it on the path: started from another folder
    (no PYTHONPATH), it found no module, and that failure was kept as 'this device is unusable' for every later
    run on the machine."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("PYTHONPATH", raising=False)
    ms = clrt.probe_ms(0, 0)
    assert ms is not None and ms > 0


def test_a_probe_that_cannot_start_ranks_nothing_and_says_why(tmp_path, monkeypatch):
    """A probe child that fails before it reaches the device (no module to run) or that ran other probes than this
    process has gives no verdict: the device is unusable for this run (the error names the child's message) and
    nothing is kept, so the next run probes again."""
    import pytest

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(clrt, "_NOT_RANKED", {})
    monkeypatch.setattr(subprocess, "run", lambda *a, **kw: subprocess.CompletedProcess(
        a, 1, "", "/usr/bin/python3: No module named nodegraph.clrt"))
    assert all(r[0] is None for r in clrt.ranking(refresh=True))
    assert not (tmp_path / "volcap" / "opencl-devices.json").exists()
    assert all("not probed: " in row and "No module named" in row for row in clrt.devices_table())
    monkeypatch.delenv("VOLCAP_CL_DEVICE", raising=False)
    with pytest.raises(clrt.OpenCLUnavailable, match="No module named nodegraph.clrt"):
        clrt._choose_device()
    monkeypatch.setattr(subprocess, "run", lambda *a, **kw: subprocess.CompletedProcess(a, 0, '{"ms": 5.0, "probes": -1}', ""))
    with pytest.raises(clrt.ProbeNotRun, match="ran -1 probes"):
        clrt.probe_ms(0, 0)
    # the device's own failure (the child's PROBE_FAILED, or a crash) is a verdict: kept as unusable
    for code in (clrt.PROBE_FAILED, -11):
        monkeypatch.setattr(subprocess, "run", lambda *a, code=code, **kw: subprocess.CompletedProcess(a, code, "", ""))
        assert clrt.probe_ms(0, 0) is None


def test_setup_ranks_the_devices_with_the_stages_probes(tmp_path):
    """setup.sh runs ``python -m nodegraph.clrt --rank``: there this file is __main__ too, so it must rank with the
    probes the stages register in the module (it compared the child's count with its own empty list and ranked
    nothing), and keep the verdict where a run finds it."""
    import os

    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path))
    env.pop("VOLCAP_CL_DEVICE", None)
    res = subprocess.run([sys.executable, "-m", "nodegraph.clrt", "--rank"], capture_output=True, text=True, timeout=300,
                         env=env)
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[0].startswith("* ") and " ms " in res.stdout.splitlines()[0]
    kept = json.loads((tmp_path / "volcap" / "opencl-devices.json").read_text())
    version = clrt._probes_version()
    assert any(k.endswith(f"probes {version}") and v is not None for k, v in kept.items())

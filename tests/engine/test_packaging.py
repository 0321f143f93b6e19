"""`pip install .` (not editable) works: the wheel carries the engine, the stages, their data files and the
OpenCL sources, and `volcap run` of the demo graph succeeds from another folder with that install alone.

The wheel is built without build isolation and installed with --no-deps into a virtual environment that sees
this interpreter's site-packages (numpy, pyopencl, ... are not downloaded again); the test checks that the
modules the run imports are the installed ones, not this checkout."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def run(cmd, **kw):
    res = subprocess.run(cmd, capture_output=True, text=True, **kw)
    assert res.returncode == 0, f"{' '.join(map(str, cmd))} failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    return res


def test_wheel_installs_and_runs_the_demo_from_another_folder(tmp_path):
    dist = tmp_path / "dist"
    run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "-w", str(dist), str(ROOT)],
        cwd=tmp_path)
    wheels = list(dist.glob("volcap-*.whl"))
    assert len(wheels) == 1
    import zipfile

    names = set(zipfile.ZipFile(wheels[0]).namelist())
    assert {"kernels/camera.h", "kernels/hull.cl", "kernels/silhouette.h", "nodes/capture/layouts.yaml"} <= names
    assert not any(n.startswith("tests/") for n in names)

    venv = tmp_path / "venv"
    run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)])
    py = venv / "bin" / "python"
    run([str(py), "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", str(wheels[0])])
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VOLCAP_CACHE")}
    where = run([str(py), "-c", "import json, kernels, nodes, nodegraph; print(json.dumps([kernels.__file__, nodes.__file__, nodegraph.__file__]))"],
                cwd=elsewhere, env=env)
    for f in json.loads(where.stdout):
        assert str(venv) in f, f"{f} is not the installed copy"
    small = ["--set", "stage.width=160", "--set", "stage.height=120", "--set", "stage.cameras=6",
             "--set", "hull.resolution=32", "--frames", "0:2"]
    volcap = venv / "bin" / "volcap"
    run([str(volcap), "--cache", str(elsewhere / "cache"), "run", str(ROOT / "graphs" / "demo.yaml"), "--out", "out", "-q", "-j", "1", *small],
        cwd=elsewhere, env=env)
    doc = json.loads((elsewhere / "out" / "run.json").read_text())
    assert doc["counts"].get("failed", 0) == 0 and doc["counts"].get("done", 0) >= 8, doc["counts"]
    assert (elsewhere / "out" / "demo_0000.ply").stat().st_size > 1000

"""`pip install .` (not editable) works: the wheel carries exactly the engine's and the stages' tracked modules,
their data files and the OpenCL sources, and `volcap run` of the demo graph succeeds from another folder with
that install alone.

The wheel is built from a clean copy of the git-tracked files, not in the checkout: setuptools reuses a stale
build/ folder there and would ship modules deleted since (pypa/setuptools#1871), or untracked ones. It is built
without build isolation and installed with --no-deps into a virtual environment that sees this interpreter's
site-packages (numpy, pyopencl, ... are not downloaded again); the test checks that the modules the run imports
are the installed ones, not this checkout."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("nodegraph", "nodes", "kernels")  # pyproject.toml: [tool.setuptools.packages.find], and py-modules app


BUILD_OUTPUTS = {"build", "dist", "__pycache__", ".git", ".volcap-cache", "out", ".pytest_cache", ".hypothesis"}


def source_files() -> set[str]:
    """The tree's source files: git's tracked ones (as they are in the working tree, uncommitted edits included;
    files deleted there left out), or outside a git checkout (an unpacked archive) every file except build
    outputs (build/, dist/, *.egg-info, caches)."""
    try:
        res = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z"], capture_output=True, check=True)
        return {f for f in res.stdout.decode().split("\0") if f and (ROOT / f).is_file()}
    except (OSError, subprocess.CalledProcessError):
        return {p.relative_to(ROOT).as_posix() for p in ROOT.rglob("*") if p.is_file()
                and not any(part in BUILD_OUTPUTS or part.endswith(".egg-info") for part in p.relative_to(ROOT).parts)}


def tracked_copy(dest: Path) -> set[str]:
    """Copy the tree's source files (``source_files``) to ``dest``; return their relative paths."""
    files = source_files()
    for f in files:
        (dest / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / f, dest / f)
    return files


def run(cmd, **kw):
    res = subprocess.run(cmd, capture_output=True, text=True, **kw)
    assert res.returncode == 0, f"{' '.join(map(str, cmd))} failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    return res


@pytest.mark.slow
def test_wheel_installs_and_runs_the_demo_from_another_folder(tmp_path):
    src = tmp_path / "src"
    tracked = tracked_copy(src)
    dist = tmp_path / "dist"
    run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "-w", str(dist), str(src)],
        cwd=tmp_path)
    wheels = list(dist.glob("volcap-*.whl"))
    assert len(wheels) == 1
    import zipfile

    names = {n for n in zipfile.ZipFile(wheels[0]).namelist() if ".dist-info/" not in n}
    modules = {n for n in names if n.endswith(".py")}
    want = {f for f in tracked if f == "app.py" or (f.endswith(".py") and f.split("/")[0] in PACKAGES)}
    assert modules == want, f"shipped but not tracked: {sorted(modules - want)}; tracked but not shipped: {sorted(want - modules)}"
    assert names <= tracked, f"shipped but not tracked: {sorted(names - tracked)}"
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

"""Start-up stays light: the engine and every node module import without the heavy libraries (they are
imported inside the functions that use them), so `volcap --help`, `validate` and `explain` start fast. Checked
in a fresh interpreter: after discovering every node type and validating the demo graph, none is loaded."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("trimesh", "scipy", "cv2", "pyopencl", "pyvista", "vtk", "matplotlib", "networkx", "OpenEXR", "distributed",
         "dask", "skimage", "open3d", "pymeshlab", "xatlas", "pxr", "pygltflib", "DracoPy")


def test_discovery_and_validation_import_no_heavy_library():
    code = ("import json, sys; from nodegraph.node import registry; from nodegraph.graphfile import load_graph; "
            f"registry(); load_graph(r'{ROOT / 'graphs' / 'demo.yaml'}'); "
            f"print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    loaded = json.loads(res.stdout)
    assert loaded == [], f"imported at start-up (import them inside the functions that use them): {loaded}"


def test_help_imports_nothing_of_the_stages():
    code = ("import json, sys; from nodegraph.cli import build_parser; build_parser().format_help(); "
            "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in ('nodes', 'numpy', 'yaml'))))")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout) == []

"""The implementation fingerprint follows the code by itself (nodegraph/fingerprint.py): edit a module and
exactly the nodes that import it, directly or not, get new cache keys. Each case edits a copy of the packages
and computes every node type's fingerprint in a fresh interpreter that imports that copy."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CODE = ("import json; from nodegraph.node import registry, discovery_problems; "
        "from nodegraph.fingerprint import implementation_fingerprint as fp; "
        "assert not discovery_problems(), discovery_problems(); "
        "print(json.dumps({t: fp(c) for t, c in registry().items()}))")


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    """A copy of the packages, and fingerprints(): every node type's fingerprint computed from that copy."""
    root = tmp_path_factory.mktemp("tree")
    for pkg in ("nodegraph", "nodes", "kernels"):
        shutil.copytree(ROOT / pkg, root / pkg, ignore=shutil.ignore_patterns("__pycache__"))

    def fingerprints() -> dict:
        env = dict(os.environ, PYTHONPATH=str(root))
        res = subprocess.run([sys.executable, "-c", CODE], cwd=root, env=env, capture_output=True, text=True)
        assert res.returncode == 0, res.stderr[-2000:]
        return json.loads(res.stdout)

    return root, fingerprints


def edit(path: Path, text: str):
    path.write_text(path.read_text() + text)


def changed(before: dict, after: dict) -> set:
    assert before.keys() == after.keys()
    return {t for t in before if before[t] != after[t]}


@pytest.mark.slow
def test_fingerprints_follow_imports_kernels_and_data(tree):
    root, fingerprints = tree
    base = fingerprints()
    assert fingerprints() == base  # stable

    # a calibration reader (imported by the capture stage's two nodes, which read dataset folders, and by
    # calibrate, which writes the formats) -> those re-run, nothing else
    edit(root / "nodes/common/calibration.py", "\n# edited: a reader's fix\n")
    after = fingerprints()
    assert changed(base, after) == {"capture", "capture.background", "calibrate"}
    base = after

    # the key stage's work module -> the key nodes, no other stage
    edit(root / "nodes/key/keying.py", "\n# edited\n")
    after = fingerprints()
    assert changed(base, after) == {t for t in base if t.startswith("key.")}
    base = after

    # the rasterizer -> the nodes that render (synth, the silhouette score, texturing and its export), not the
    # stages that never render; the report's drawings use it too, but they declare that they change no result
    edit(root / "nodes/common/raster.py", "\n# edited\n")
    after = fingerprints()
    assert {"synth", "eval.silhouette", "texture", "export.textured"} <= changed(base, after)
    assert not changed(base, after) & {"capture", "key.chroma", "hull", "mc", "refine", "export.mesh", "export.masks"}
    base = after

    # a shared OpenCL header: every node whose kernels include it (hull.cl, refine.cl include silhouette.h), not mc
    edit(root / "kernels/silhouette.h", "\n// edited\n")
    after = fingerprints()
    assert {"hull", "refine", "relax"} <= changed(base, after) and "mc" not in changed(base, after)
    base = after

    # a data file beside a module (the dataset layouts) -> capture and capture.background (both read folders)
    edit(root / "nodes/capture/layouts.yaml", "\n# edited\n")
    assert changed(base, fingerprints()) == {"capture", "capture.background"}

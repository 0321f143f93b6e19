"""Evaluation results reach the user (issue 12, item 12): eval tables are published to the output folder
(JSON per frame, CSV per node), each eval node prints a one-line summary after the run, and a reference
mesh is read from disk by the load.mesh node (eval.surface had no way to get one)."""
from __future__ import annotations

import csv
import json
import os

import numpy as np
import pytest
import trimesh

from nodegraph.cli import main as cli
from nodegraph.errors import DataError
from nodegraph.testing import run_node
from nodes.io.mesh import load_mesh


def write_meshes(tmp_path):
    ref = trimesh.creation.icosphere(3, radius=0.5)
    ref.export(tmp_path / "reference.ply")
    moved = ref.copy()
    moved.apply_translation([0.01, 0, 0])
    moved.export(tmp_path / "result.obj")
    return ref


def test_load_mesh_reads_common_formats(tmp_path):
    ref = write_meshes(tmp_path)
    for name in ("reference.ply", "result.obj"):
        m = run_node("load.mesh", params={"path": str(tmp_path / name)}, roundtrip=True)["mesh"]
        assert len(m.faces) == len(ref.faces) and m.is_watertight
    glb = trimesh.Scene([ref, ref.copy().apply_translation([2, 0, 0])])
    glb.export(tmp_path / "two.glb")
    two = run_node("load.mesh", params={"path": str(tmp_path / "two.glb")})["mesh"]
    assert len(two.faces) == 2 * len(ref.faces)


@pytest.mark.parametrize("content, needle", [
    (b"", "empty"),
    (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
     b"0 0 0\n1 0 0\n0 1 0\n", "no faces"),
    (b"not a mesh at all", "cannot be read"),
    (b"v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "NaN"),
])
def test_load_mesh_refuses_what_is_not_a_mesh(tmp_path, content, needle):
    p = tmp_path / ("bad.obj" if content.startswith(b"v ") else "bad.ply")
    p.write_bytes(content)
    with pytest.raises(DataError, match=needle):
        run_node("load.mesh", params={"path": str(p)})
    os.mkfifo(tmp_path / "pipe.ply")
    with pytest.raises(ValueError, match="not a regular file"):   # as a graph's parameter: refused before the node
        run_node("load.mesh", params={"path": str(tmp_path / "pipe.ply")})
    with pytest.raises(DataError, match="not a regular file"):    # and by the reader itself
        load_mesh(tmp_path / "pipe.ply")


def test_eval_tables_are_published_with_a_summary_line(tmp_path, capsys):
    write_meshes(tmp_path)
    g = tmp_path / "g.yaml"
    g.write_text("frames: 0:2\nnodes:\n"
                 "  ref:    {type: load.mesh, params: {path: reference.ply}}\n"
                 "  result: {type: load.mesh, params: {path: result.obj}}\n"
                 "  score:  {type: eval.surface, in: {mesh: result.mesh, reference: ref.mesh}, params: {samples: 5000}}\n")
    out = tmp_path / "out"
    assert cli(["--cache", str(tmp_path / "cache"), "run", str(g), "--out", str(out), "-q", "-j", "1"]) == 0
    stdout = capsys.readouterr().out
    lines = [ln for ln in stdout.splitlines() if ln.startswith("score (eval.surface)")]
    assert len(lines) == 1, stdout
    assert "chamfer" in lines[0] and "hausdorff" in lines[0] and "2 frames" in lines[0], lines[0]
    table = json.loads((out / "tables" / "score" / "0.json").read_text())
    assert 0.003 < table["chamfer"] < 0.012 and table["samples"] == 5000
    with open(out / "tables" / "score.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["frame"] for r in rows] == ["0", "1"]
    assert float(rows[0]["chamfer"]) == pytest.approx(table["chamfer"])
    doc = json.loads((out / "run.json").read_text())
    score = [r for r in doc["items"] if r["node"] == "score"]
    assert any(p.endswith("tables/score/0.json") for p in score[0]["published"])
    # a cached rerun publishes and summarises the same
    assert cli(["--cache", str(tmp_path / "cache"), "run", str(g), "--out", str(out), "-q", "-j", "1"]) == 0
    assert lines[0] in capsys.readouterr().out


def test_silhouette_tables_have_a_per_view_csv(tmp_path, capsys):
    from nodes.common import raster
    from nodes.common.types import MaskSet
    from nodes.synth import render as synth

    sphere = trimesh.creation.icosphere(2, radius=0.5)
    sphere.apply_translation([0, 0, 0.6])
    cams = synth.ring_rig(3, [0, 0, 0.6], 0.5, 50.0, 64, 48)
    rep = run_node("eval.silhouette", {"mesh": sphere, "cameras": cams,
                                       "masks": MaskSet(raster.silhouette(sphere.vertices, sphere.faces, cams))})["report"]
    from nodegraph.run import table_rows

    rows = table_rows(rep)
    assert [r["name"] for r in rows["views"]] == cams.names and rows["views"][0]["iou"] == 1.0
    assert rows[""]["mean_iou"] == 1.0 and "views" not in rows[""]
    assert np.isclose(rep["mean_iou"], 1.0)

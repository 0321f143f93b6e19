"""Every graph in graphs/ validates; every dataset graph runs on the real data (coarse, to stay quick)
and produces watertight one-piece meshes, with silhouette scores where the graph computes them."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import trimesh

from nodegraph.cache import Cache
from nodegraph.executors import LocalExecutor
from nodegraph.graphfile import load_graph
from nodegraph.run import run_graph

ROOT = Path(__file__).resolve().parent.parent
DATASET_GRAPHS = sorted((ROOT / "graphs/datasets").glob("*.yaml")) + [ROOT / "graphs/hull.yaml"]
SYNTHETIC_GRAPHS = [ROOT / "graphs/demo.yaml"]


@pytest.mark.parametrize("path", SYNTHETIC_GRAPHS, ids=lambda p: p.name)
def test_synthetic_graphs_validate(path):
    g = load_graph(path)
    assert g.nodes


@pytest.mark.realdata
@pytest.mark.parametrize("path", DATASET_GRAPHS, ids=lambda p: p.stem)
def test_dataset_graph_runs(path, tmp_path, data_dir, monkeypatch):
    monkeypatch.setenv("VOLCAP_DATA", str(data_dir))
    g = load_graph(path)
    coarse = [f"{n}.resolution=64" for n, s in g.nodes.items() if s.type_name == "hull"]
    g = load_graph(path, overrides=coarse, frames=str(g.frames[0]))
    res = run_graph(g, Cache(tmp_path / "cache"), tmp_path / "out", LocalExecutor(1), progress=False)
    assert res.ok, res.failures
    meshes = [Path(p) for r in res.records if r["type"] == "export.mesh" for p in r["published"]]
    assert meshes, "a dataset graph should export a mesh"
    for p in meshes:
        m = trimesh.load(p, process=False)
        assert m.is_watertight and m.body_count == 1 and m.volume > 0, p.name
    for p in [Path(p) for r in res.records if r["type"] == "export.textured" for p in r["published"]]:
        if p.suffix == ".glb":                          # textured: the texture travels inside the GLB
            m = trimesh.load(p, force="mesh")
            assert m.visual.kind == "texture" and m.visual.material.baseColorTexture is not None, p.name
    for r in res.records:
        if r["type"] == "eval.silhouette":
            table = json.loads((Path(r["cache_dir"]) / "report/table.json").read_text())
            assert table["mean_iou"] >= 0.85, (path.stem, table["mean_iou"])

"""End to end: the demo graph (synth -> key -> cleanup -> hull -> mc -> refine -> relax -> skeleton; track -> one
atlas per segment -> texture, rig: skeleton from the motion + skin; the hull carved beside it; exports and
evaluations), shrunk."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from nodegraph.cli import main as cli

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_demo_graph_end_to_end(tmp_path):
    small = ["--set", "stage.width=240", "--set", "stage.height=180", "--set", "stage.cameras=8",
             "--set", "hull.resolution=64", "--set", "skeleton.resolution=64", "--set", "texture.size=256", "--frames", "0:2"]
    args = ["--cache", str(tmp_path / "cache"), "run", str(ROOT / "graphs/demo.yaml"), "--out", str(tmp_path / "out"), "-q", "-j", "1"]
    assert cli(args + small) == 0
    doc = json.loads((tmp_path / "out/run.json").read_text())
    assert doc["counts"] == {"done": 55}
    items = {(r["node"], r["frame"]): r for r in doc["items"]}
    for f in (0, 1):
        mesh = trimesh.load(tmp_path / f"out/demo_{f:04d}.ply", process=False)
        assert mesh.is_watertight and mesh.body_count == 1 and mesh.volume > 0
        sil = json.loads((Path(items[("silhouettes", f)]["cache_dir"]) / "report/table.json").read_text())
        assert sil["mean_iou"] > 0.9, sil["mean_iou"]
        surf = json.loads((Path(items[("surface", f)]["cache_dir"]) / "report/table.json").read_text())
        assert surf["chamfer_rel"] < 0.01, surf["chamfer_rel"]
        assert len(list((tmp_path / "out/masks").glob(f"*/{f:04d}.png"))) == 8
        glb = trimesh.load(tmp_path / f"out/demo_{f:04d}.glb", force="mesh")     # the textured mesh, texture embedded
        assert glb.visual.kind == "texture" and glb.visual.material.baseColorTexture.size == (256, 256)
        tex = np.asarray(glb.visual.material.baseColorTexture.convert("RGB")).astype(int)
        uv = np.asarray(glb.visual.uv)[np.asarray(glb.faces)].mean(axis=1)      # each face's texel
        px = tex[np.clip(((1 - uv[:, 1]) * 256).astype(int), 0, 255), np.clip((uv[:, 0] * 256).astype(int), 0, 255)]
        green = px[:, 1] - np.maximum(px[:, 0], px[:, 2])
        assert np.mean(green > 10) < 0.002, np.mean(green > 10)   # painted from the despilled photos: no green cast
        health = json.loads((tmp_path / f"out/tables/health/{f}.json").read_text())
        assert health["folded_edges"] == 0 and health["watertight"], health
        assert health["normal_error_mean_deg"] < 15, health["normal_error_mean_deg"]
        skel = json.loads((Path(items[("skeleton", f)]["cache_dir"]) / "report/table.json").read_text())
        assert sorted(skel["names"]) == ["foot_0", "foot_1", "hand_0", "hand_1", "head"], skel
        carved = trimesh.load(tmp_path / f"out/demo_carved_{f:04d}.ply", process=False)
        assert carved.visual.kind == "vertex" and carved.volume < mesh.volume * 1.05
    # the tracked frames: one segment, one connectivity, one atlas (the texture stays in place)
    glbs = [trimesh.load(tmp_path / f"out/demo_{f:04d}.glb", force="mesh") for f in (0, 1)]
    assert np.array_equal(glbs[0].faces, glbs[1].faces) and np.array_equal(glbs[0].visual.uv, glbs[1].visual.uv)
    assert not np.allclose(glbs[0].vertices, glbs[1].vertices)
    for name in ("demo_dynamic.usdc", "demo_dynamic.glb", "demo_rig.usd", "demo_rig.glb", "demo_character.bvh",
                 "demo_character.glb", "demo_character.usd", "demo_volumetric.usdc",
                 "demo_volumetric_0000.mp4", "demo_volumetric_tex/00001.png"):
        assert (tmp_path / "out" / name).stat().st_size > 1000, name
    # the deliverable: one textured animated GLB for the segment, upright (+Y) and to scale as a glTF reader sees it
    import pygltflib as G

    from nodegraph.testing import run_node
    from nodes.common.gltf import read_accessor

    g = G.GLTF2.load(str(tmp_path / "out/demo_volumetric_0000.glb"))
    prim = g.meshes[0].primitives[0]
    y = read_accessor(g, g.binary_blob(), prim.attributes.POSITION)[:, 1]
    truth = np.asarray(run_node("synth", params={"scene": "figure", "rig": "ring", "cameras": 2, "width": 64,
                                                  "height": 48})["mesh"].vertices)[:, 2]
    assert abs(y.min()) < 0.02 and abs(np.ptp(y) - np.ptp(truth)) < 0.03 * np.ptp(truth), (y.min(), np.ptp(y))
    assert len(prim.targets) == 1 and prim.attributes.TEXCOORD_0 is not None and g.extras["frames"] == [0, 1]
    # the character: the humanoid template's names, as a BVH reader sees them
    from nodes.skeleton.formats import read_bvh

    bvh = read_bvh((tmp_path / "out/demo_character.bvh").read_text())
    assert {"pelvis", "elbow_l", "knee_r", "head"} <= set(bvh["names"]) and bvh["positions"].shape[0] == 2
    # the stream ladder decodes: two rungs, the lower with about a quarter of the faces
    from nodes.export.stream import read_stream

    full, low = (read_stream(tmp_path / "out/demo_stream", r) for r in ("full", "quarter"))
    assert [f["frame"] for f in full] == [f["frame"] for f in low] == [0, 1]
    assert 0.2 < len(low[0]["faces"]) / len(full[0]["faces"]) < 0.3 and low[0]["atlas"].shape == (512, 512, 3)
    assert json.loads((tmp_path / "out/demo_stream/rungs.json").read_text()) == ["full", "quarter"]      # the player
    assert (tmp_path / "out/demo_stream/lib/three.module.min.js").stat().st_size > 100_000
    # a second run is all cache hits and rewrites identical files
    before = (tmp_path / "out/demo_0000.ply").read_bytes()
    assert cli(args + small) == 0
    doc = json.loads((tmp_path / "out/run.json").read_text())
    assert doc["counts"] == {"cached": 55}
    assert (tmp_path / "out/demo_0000.ply").read_bytes() == before


@pytest.mark.slow
def test_demo_graph_with_track_in_windows(tmp_path):
    """`--set track.window=2` over 4 frames: two track items (run side by side with -j 2), a segment per window,
    each frame's texture on its own window's segment, and the sequence nodes after track on the joined windows."""
    small = ["--set", "stage.width=240", "--set", "stage.height=180", "--set", "stage.cameras=8",
             "--set", "hull.resolution=64", "--set", "skeleton.resolution=64", "--set", "texture.size=256",
             "--frames", "0:4", "--set", "track.window=2"]
    args = ["--cache", str(tmp_path / "cache"), "run", str(ROOT / "graphs/demo.yaml"), "--out", str(tmp_path / "out"), "-q", "-j", "2"]
    assert cli(args + small) == 0
    doc = json.loads((tmp_path / "out/run.json").read_text())
    assert sorted(r["frames"] for r in doc["items"] if r["node"] == "track") == [[0, 1], [2, 3]]
    dynamic = json.loads((tmp_path / "out/tables/dynamic/all.json").read_text())
    assert dynamic["segments"] == 2 and dynamic["segments_frames"] == [2, 2], dynamic
    glbs = [trimesh.load(tmp_path / f"out/demo_{f:04d}.glb", force="mesh") for f in range(4)]
    assert np.array_equal(glbs[0].faces, glbs[1].faces) and np.array_equal(glbs[2].faces, glbs[3].faces)
    assert len(glbs[1].faces) != len(glbs[2].faces) or not np.array_equal(glbs[1].faces, glbs[2].faces)
    assert all((tmp_path / f"out/demo_volumetric_{s:04d}.glb").is_file() for s in (0, 1))
    from nodes.export.stream import read_stream

    assert [f["frame"] for f in read_stream(tmp_path / "out/demo_stream", "full")] == [0, 1, 2, 3]


def test_the_bench_chain_graph_is_the_demos_chain():
    """graphs/bench/chain.yaml (bench/chain.py --graph) is graphs/demo.yaml's chain, node for node."""
    from nodegraph.graphfile import load_graph

    demo, chain = load_graph(ROOT / "graphs/demo.yaml"), load_graph(ROOT / "graphs/bench/chain.yaml")
    assert {"stage", "key", "hull", "track", "texture", "volumetric", "stream_low"} <= set(chain.nodes)
    for name, spec in chain.nodes.items():
        other = demo.nodes[name]
        assert (spec.type_name, spec.params, spec.inputs) == (other.type_name, other.params, other.inputs), name
    assert chain.frames == demo.frames

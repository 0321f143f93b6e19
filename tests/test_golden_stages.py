"""Golden files for the nodes not covered by their own test modules: bounds, key.grabcut and the exports.
Inputs come from a small synthetic capture (8 cameras, 160x120) rendered by the synth node."""
from __future__ import annotations

import io
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from nodes.common.types import Masks, MaskSet, Mesh, Volume, VoxelGrid
from nodegraph.testing import run_node


@pytest.fixture(scope="module")
def stage():
    return run_node("synth", params={"scene": "figure", "cameras": 8, "width": 160, "height": 120, "background": "green"})


def test_bounds_golden(stage, golden):
    out = run_node("bounds", {"masks": stage["masks"], "cameras": stage["cameras"]}, {"resolution": 32})
    box = out["bounds"]
    # the automatic box must contain the true mesh and stay reasonably tight (8 views: a loose hull)
    lo, hi = stage["mesh"].bounds
    assert np.all(box[0] <= lo) and np.all(box[1] >= hi)
    assert np.prod(box[1] - box[0]) < 4 * np.prod(hi - lo)
    from nodegraph import Array

    golden.check("bounds_figure_8cams", box, Array, atol=1e-6)


def test_grabcut_golden(stage, golden):
    # start from a dilated (too fat) silhouette: GrabCut must pull it back towards the truth
    fat = [cv2.dilate(m, np.ones((5, 5), np.uint8)) for m in stage["masks"].masks]
    out = run_node("key.grabcut", {"images": stage["images"], "masks": MaskSet(fat)})
    def iou(a, b):
        return np.logical_and(a > 127, b > 127).sum() / np.logical_or(a > 127, b > 127).sum()
    before = np.mean([iou(f, t) for f, t in zip(fat, stage["masks"].masks)])
    after = np.mean([iou(m, t) for m, t in zip(out["masks"].masks, stage["masks"].masks)])
    assert before < 0.75 and after > 0.95, (before, after)
    golden.check("key_grabcut_figure", out["masks"], Masks, iou=0.99)


def test_export_nodes_golden(stage, golden):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    files = run_node("export.mesh", {"mesh": mesh}, {"path": "m_{frame:03d}.ply"}, frame=7)["files"]
    assert list(files) == ["m_007.ply"]
    golden.check("export_mesh_icosphere", trimesh.load(io.BytesIO(files["m_007.ply"]), file_type="ply", process=False), Mesh)

    files = run_node("export.masks", {"masks": stage["masks"]}, {"path": "{camera}/{frame:04d}.png", "alpha": False}, frame=3)["files"]
    assert sorted(files) == sorted(f"{n}/0003.png" for n in stage["masks"].names)
    decoded = MaskSet([cv2.imdecode(np.frombuffer(files[f"{n}/0003.png"], np.uint8), cv2.IMREAD_GRAYSCALE) for n in stage["masks"].names])
    assert all(np.array_equal(a, b) for a, b in zip(decoded.masks, stage["masks"].masks))
    golden.check("export_masks_figure", decoded, Masks)

    occ = np.zeros((6, 5, 4), np.uint8)
    occ[1:4, 1:3, 1:3] = 1
    vol = VoxelGrid(occ, [0, 0, 0], [1.2, 1.0, 0.8])
    files = run_node("export.volume", {"volume": vol}, {"path": "v.npz"}, frame=0)["files"]
    with tempfile.TemporaryDirectory() as d:
        Path(d, "volume.npz").write_bytes(files["v.npz"])
        back = Volume.load(Path(d))
    golden.check("export_volume_block", back, Volume)


def test_export_mesh_rejects_unknown_format():
    from nodegraph import NodeError

    with pytest.raises(NodeError, match=r"unknown mesh format '\.xyz'"):
        run_node("export.mesh", {"mesh": trimesh.creation.box()}, {"path": "a.xyz"})

"""Golden files of the export nodes; masks from the small synthetic capture (conftest.small_stage)."""
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


def test_export_nodes_golden(small_stage, golden):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    files = run_node("export.mesh", {"mesh": mesh}, {"path": "m_{frame:03d}.ply"}, frame=7)["files"]
    assert list(files) == ["m_007.ply"]
    golden.check("export_mesh_icosphere", trimesh.load(io.BytesIO(files["m_007.ply"]), file_type="ply", process=False), Mesh)

    files = run_node("export.masks", {"masks": small_stage["masks"]}, {"path": "{camera}/{frame:04d}.png", "alpha": False}, frame=3)["files"]
    assert sorted(files) == sorted(f"{n}/0003.png" for n in small_stage["masks"].names)
    decoded = MaskSet([cv2.imdecode(np.frombuffer(files[f"{n}/0003.png"], np.uint8), cv2.IMREAD_GRAYSCALE) for n in small_stage["masks"].names])
    assert all(np.array_equal(a, b) for a, b in zip(decoded.masks, small_stage["masks"].masks))
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

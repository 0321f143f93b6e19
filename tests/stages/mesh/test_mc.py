"""Marching cubes: OpenCL == NumPy reference (same triangles), watertight outward meshes, skimage vertices."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nodes.common.types import Mesh
from nodegraph import NodeError
from nodegraph.testing import run_node
from nodes.common.types import VoxelGrid
from nodes.mesh.mc import case_table, marching_cubes, marching_cubes_reference

VS = 0.1


def ball(shape=(20, 22, 18), centre=(9.3, 10.1, 8.7), radius=6.5, soft=False) -> VoxelGrid:
    g = np.indices(shape).transpose(1, 2, 3, 0) + 0.5  # voxel centres in voxel units
    d = np.linalg.norm(g - np.asarray(centre) - 0.5, axis=-1)
    occ = np.clip(0.5 + (radius - d), 0, 1).astype(np.float32) if soft else (d < radius).astype(np.uint8)
    return VoxelGrid(occ, [-1.0, 0.5, 2.0], np.array([-1.0, 0.5, 2.0]) + np.array(shape) * VS)


def triangles(v, f) -> list:
    """Triangles as vertex coordinates, each rotated to start at its smallest vertex (winding kept), sorted."""
    out = []
    for tri in v[f]:
        t = [tuple(p) for p in tri]
        r = min(range(3), key=lambda i: t[i])
        out.append(tuple(t[r:] + t[:r]))
    return sorted(out)


def mesh(v, f) -> trimesh.Trimesh:
    return trimesh.Trimesh(v.astype(np.float64), f, process=False)


def test_case_table_is_complementary_in_count():
    ntri, table = case_table()
    assert ntri[0] == ntri[255] == 0 and ntri.min() == 0 and (ntri > 0).sum() == 254
    assert table.shape[1] == ntri.max()
    for case in (1, 2, 4, 8, 16, 32, 64, 128):  # one corner in: one triangle
        assert ntri[case] == 1 and ntri[255 - case] == 1


def test_case_table_is_the_one_the_meshes_were_made_with():
    """The table is derived at start-up (mc.case_table); its bytes are pinned, so a faster derivation (plain floats
    instead of numpy, 0.14 -> 0.03 s) cannot change a single triangle of any mesh."""
    import hashlib

    ntri, table = case_table()
    assert table.shape == (256, 5, 3) and table.dtype == np.int8 and ntri.dtype == np.int32
    assert hashlib.sha256(ntri.tobytes() + table.tobytes()).hexdigest() == \
        "cb30c46fb631b512c1c26b56aec1ae66d1edd7d1de80a1a1c3a1b8e2c9283589"


@pytest.mark.parametrize("kind", ["ball", "noise", "soft", "long_rows", "soft_below_zero"])
def test_kernel_equals_reference(kind):
    rng = np.random.default_rng(3)
    level = 0.5
    if kind == "ball":
        vol = ball()
    elif kind == "noise":
        vol = VoxelGrid((rng.random((12, 13, 11)) < 0.4).astype(np.uint8), [0, 0, 0], [1.2, 1.3, 1.1])
    elif kind == "soft":
        vol = VoxelGrid(rng.random((10, 11, 12)).astype(np.float32), [0, 0, 0], [1.0, 1.1, 1.2])
    elif kind == "long_rows":  # rows of 16-sample chunks and a tail, values 0..3 against level 2
        occ = (rng.random((9, 8, 45)) < 0.3).astype(np.uint8) * 3
        occ[:, :, :20] = 0  # empty leading chunk
        vol, level = VoxelGrid(occ, [0, 0, 0], [0.9, 0.8, 4.5]), 2.0
    else:  # negative level: the zero border counts as inside
        vol, level = VoxelGrid(rng.random((7, 9, 35)).astype(np.float32) - 0.5, [0, 0, 0], [0.7, 0.9, 3.5]), -0.2
    v1, f1 = marching_cubes(vol, level)
    v2, f2 = marching_cubes_reference(vol, level)
    assert len(v1) == len(v2) and len(f1) == len(f2) and len(f1) > 500
    assert np.array_equal(v1, v2) and np.array_equal(f1, f2)  # same vertices and triangles, same order
    assert len(np.unique(v1, axis=0)) == len(v1)  # one vertex per crossing edge, shared
    m = mesh(v1, f1)
    assert m.is_watertight and m.is_winding_consistent
    assert (m.volume > 0) == (level > 0)  # below zero the solid is the outside (with the border): inward normals


@pytest.mark.parametrize("level", [-0.5, 1.0, 255.0])
def test_uniform_side_gives_an_empty_mesh(level):
    """uint8 volumes with every sample (the zero border too) on one side of the level have no surface."""
    vol = ball()
    v, f = marching_cubes(vol, level)
    v2, f2 = marching_cubes_reference(vol, level)
    assert v.shape == v2.shape == (0, 3) and f.shape == f2.shape == (0, 3)


def test_ball_is_closed_outward_and_one_piece():
    vol = ball()
    m = mesh(*marching_cubes(vol))
    assert m.is_watertight and m.is_winding_consistent
    assert len(m.split(only_watertight=False)) == 1
    voxels = vol.occupancy.sum() * VS**3
    assert 0.9 * voxels < m.volume < 1.02 * voxels
    # outward: normals point away from the centre
    c = vol.bbox_min + (np.array([9.3, 10.1, 8.7]) + 0.5) * VS
    assert np.mean(np.einsum("ij,ij->i", m.face_normals, m.triangles_center - c) > 0) > 0.99


def test_full_box_closes_at_the_bounds():
    vol = VoxelGrid(np.ones((5, 6, 7), np.uint8), [0, 0, 0], [0.5, 0.6, 0.7])
    m = mesh(*marching_cubes(vol))
    assert m.is_watertight and m.volume > 0
    np.testing.assert_allclose(m.bounds, [[0, 0, 0], [0.5, 0.6, 0.7]], atol=1e-6)


def test_same_vertices_as_skimage():
    from skimage.measure import marching_cubes as sk_mc

    vol = ball((16, 15, 17), (7.2, 6.9, 8.1), 5.2)
    v, f = marching_cubes(vol)
    sv, sf, _, _ = sk_mc(np.pad(vol.occupancy, 1).astype(np.float32), 0.5, spacing=(VS,) * 3, gradient_direction="ascent")
    sv = sv + vol.bbox_min - 0.5 * VS
    assert len(sv) == len(v)
    np.testing.assert_allclose(np.unique(np.round(v, 5), axis=0), np.unique(np.round(sv, 5), axis=0), atol=2e-5)
    assert abs(mesh(sv, sf).volume - mesh(v, f).volume) < 0.02 * mesh(v, f).volume


def test_soft_occupancy_places_vertices_between_voxels():
    radius = 6.5
    centre = np.array([-1.0, 0.5, 2.0]) + (np.array([9.3, 10.1, 8.7]) + 0.5) * VS
    r_soft = np.linalg.norm(marching_cubes(ball(radius=radius, soft=True))[0] - centre, axis=1) / VS
    r_hard = np.linalg.norm(marching_cubes(ball(radius=radius))[0] - centre, axis=1) / VS
    assert np.abs(r_soft - radius).max() < 0.15
    assert np.abs(r_hard - radius).max() > 0.3


def test_node_golden_and_largest_component(golden):
    out = run_node("mc", {"volume": ball((12, 12, 12), (5.5, 5.5, 5.5), 4.0)}, roundtrip=True)["mesh"]
    assert out.is_watertight and out.volume > 0
    golden.check("mc_ball", out, Mesh)
    occ = np.zeros((20, 12, 12), np.uint8)
    occ[2:9, 2:9, 2:9] = 1   # the bigger block
    occ[12:16, 4:8, 4:8] = 1
    two = VoxelGrid(occ, [0, 0, 0], [2.0, 1.2, 1.2])
    both = run_node("mc", {"volume": two})["mesh"]
    one = run_node("mc", {"volume": two}, {"largest": True, "min_part": 1.0})["mesh"]
    assert len(both.split(only_watertight=False)) == 2
    assert one.is_watertight and len(one.split(only_watertight=False)) == 1
    assert one.bounds[1][0] < 1.0 and len(one.faces) < len(both.faces)


def test_node_rejects_a_flat_volume():
    with pytest.raises(NodeError, match="3-D"):
        run_node("mc", {"volume": VoxelGrid(np.ones((4, 4), np.uint8).reshape(4, 4), [0, 0, 0], [1, 1, 1])})

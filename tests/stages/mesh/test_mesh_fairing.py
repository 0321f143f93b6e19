"""Fairing kernels (kernels/fairing.cl) vs their NumPy references, the vertex -> face table, and free fairing
against Taubin smoothing (trimesh, the baseline a user would pick) on a noisy sphere."""
from __future__ import annotations

import numpy as np
import trimesh

from nodes.eval.health import mesh_health
from nodes.mesh.fairing import (CLOps, NumPyOps, face_filter_reference, face_normals_reference, fair,
                                fair_step_reference, shell_clamp_reference, vertex_faces, vertex_normals_reference)


def noisy_sphere(seed=0, level=3):
    m = trimesh.creation.icosphere(level)
    rng = np.random.default_rng(seed)
    return trimesh.Trimesh(m.vertices * (1 + 0.03 * rng.standard_normal((len(m.vertices), 1))), m.faces, process=False)


def test_vertex_faces_lists_each_vertex_faces():
    m = noisy_sphere()
    off, idx = vertex_faces(m.faces, len(m.vertices))
    assert off[-1] == 3 * len(m.faces)
    for i in (0, 17, 300):
        assert sorted(idx[off[i]:off[i + 1]]) == sorted(np.flatnonzero((m.faces == i).any(axis=1)))


def test_kernels_match_reference():
    m = noisy_sphere()
    v = m.vertices.astype(np.float32)
    f = m.faces.astype(np.int32)
    ops = CLOps(v, f)
    off, idx = vertex_faces(f, len(v))
    fn = face_normals_reference(v, f)
    np.testing.assert_allclose(ops.k.read(ops.face_normals(ops.v, "t_fn"), (len(f), 3), np.float32), fn, atol=1e-7)
    vn = vertex_normals_reference(fn, off, idx)
    np.testing.assert_allclose(ops.read(ops.vertex_normals(ops.face_normals(ops.v, "t_fn"), "t_vn")), vn, atol=1e-6)
    area_weighted = np.zeros_like(m.vertices)
    for k in range(3):
        np.add.at(area_weighted, m.faces[:, k], m.face_normals * m.area_faces[:, None])
    np.testing.assert_allclose(vn, area_weighted / np.linalg.norm(area_weighted, axis=1, keepdims=True), atol=1e-5)
    mf = face_filter_reference(vn, f)
    d_vn = ops.vertex_normals(ops.face_normals(ops.v, "t_fn"), "t_vn")
    np.testing.assert_allclose(ops.k.read(ops.face_filter(d_vn, "t_m"), (len(f), 3), np.float32), mf, atol=1e-6)
    want = fair_step_reference(v, f, off, idx, mf, vn, 0.5)
    got = ops.read(ops.fair_step(ops.v, ops.face_filter(d_vn, "t_m"), d_vn, 0.5, "t_out"))
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert np.abs(want - v).max() > 1e-3  # it moved
    # clamp: along the normals through the vertices, offsets limited to [0.3, 0.6] of the line and 0.01 across
    shell = np.tile(np.float32([0.1, 0.3, 0.6, 0.7]), (len(v), 1))
    moved = v + 0.05 * np.random.default_rng(3).standard_normal(v.shape).astype(np.float32)
    want = shell_clamp_reference(moved, v, vn, shell, 0.1, 0.01)
    d_sh = ops.k.upload("t_sh", shell)
    got = ops.read(ops.clamp(ops.k.upload("t_mv", moved), ops.v, d_vn, d_sh, 0.1, 0.01, "t_cl"))
    np.testing.assert_allclose(got, want, atol=1e-6)
    s = np.einsum("ij,ij->i", want - (v - 0.1 * vn), vn) / 0.2
    assert s.min() >= 0.3 - 1e-5 and s.max() <= 0.6 + 1e-5


def test_free_fairing_smooths_like_taubin_without_slivers():
    """Free fairing (no shell) on a noisy sphere: roughness at least halved, volume within 3 % (no Laplacian
    shrinkage), no sliver; Taubin lambda|mu (trimesh) for comparison. NumPy and OpenCL agree."""
    m = noisy_sphere()
    ops = CLOps(m.vertices, m.faces)
    out = trimesh.Trimesh(ops.read(fair(ops, rounds=1, iterations=8)[0]), m.faces, process=False)
    ref = NumPyOps(m.vertices, m.faces)
    np.testing.assert_allclose(out.vertices, ref.read(fair(ref, rounds=1, iterations=8)[0]), atol=1e-5)
    taubin = trimesh.smoothing.filter_taubin(m.copy(), lamb=0.6307, nu=0.6732, iterations=16)
    h0, h1, ht = mesh_health(m), mesh_health(out), mesh_health(taubin)
    print(f"roughness {h0['roughness_deg']:.2f} -> fairing {h1['roughness_deg']:.2f}, taubin {ht['roughness_deg']:.2f}; "
          f"volume {out.volume / m.volume:.4f} vs {taubin.volume / m.volume:.4f}")
    assert h1["roughness_deg"] <= 0.5 * h0["roughness_deg"]
    assert abs(out.volume / m.volume - 1) < 0.03
    assert h1["min_angle_below_10"] == 0 and h1["folded_edges"] == 0


def test_unfold_step_matches_reference_and_opens_a_fold():
    """A vertex of a sphere pushed past one of its neighbours: the vertices at the fold move (kernel == NumPy),
    the others stay, and the repair loop leaves no folded edge."""
    from nodes.mesh.fairing import unfold_step_reference

    m = trimesh.creation.icosphere(2)
    v = m.vertices.astype(np.float32).copy()
    ring = m.vertex_neighbors[0]
    v[0] = v[ring[0]] + (v[ring[0]] - v[0])  # across its neighbour: two of its faces turn over
    f = m.faces.astype(np.int32)
    assert mesh_health(trimesh.Trimesh(v, f, process=False))["folded_edges"] > 0
    off, idx = vertex_faces(f, len(v))
    want, moved = unfold_step_reference(v, f, off, idx)
    ops = CLOps(v, f)
    d_out, count = ops.unfold(ops.v, "t_unfold")
    np.testing.assert_allclose(ops.read(d_out), want, atol=1e-6)
    assert count == moved > 0 and (np.abs(want - v).max(axis=1) > 0).sum() == moved
    for _ in range(12):
        v, moved = unfold_step_reference(v, f, off, idx)
    assert mesh_health(trimesh.Trimesh(v, f, process=False))["folded_edges"] == 0

"""track: topology and the Table 8.1 classes, the deformation graph fit, keyframe tracking on the synthetic
figure with known correspondences, segments at a topology change, silhouettes, the exports, the sequence type."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from rig import ring_rig, two_segments

from nodegraph import DataError, NodeError, Table
from nodegraph.graphfile import load_graph
from nodegraph.testing import run_node
from nodes.common import closest
from nodes.common.meshops import edge_face_pairs, folded_edges, ring_operator, split_edges, unique_edges
from nodes.common.types import Mesh, MeshSequence, MaskSet, sequence_segments
from nodes.synth import scenes
from nodes.track import deform, formats
from nodes.track.topology import DYNAMIC, STABLE, UNCONSTRAINED, classify_sequence, mesh_topology

ROOT = Path(__file__).resolve().parents[3]
VOXEL = 0.03                 # the coarse figure is meshed on a 3 cm grid: distances below are in these voxels


# ---------------------------------------------------------------- a figure with known correspondences
def figure_frame(frame: int, seed: int):
    """The coarse walking figure at ``frame`` remeshed differently per ``seed`` (vertices shuffled, a fifth of
    the edges split), and the sparse map M from the rest mesh's vertices: true positions = M @ posed vertices."""
    from scipy.sparse import coo_matrix, identity, vstack

    rest, weights, _ = scenes.figure_rest(VOXEL)
    rots, pos = scenes.figure_pose(frame)
    posed = scenes.skin(rest.vertices, weights, rots, pos)
    rng = np.random.default_rng(seed)
    edges, face_edges = unique_edges(rest.faces)
    split = rng.random(len(edges)) < 0.2
    v, f = split_edges(posed, rest.faces, edges, face_edges, split, posed[edges].mean(axis=1))
    n0 = len(rest.vertices)
    mids = edges[split]
    M = vstack([identity(n0, format="csr"),
                coo_matrix((np.full(2 * len(mids), 0.5), (np.repeat(np.arange(len(mids)), 2), mids.ravel())),
                           shape=(len(mids), n0)).tocsr()]).tocsr()
    perm = rng.permutation(len(v))               # new vertex i is old vertex perm[i]
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    return trimesh.Trimesh(v[perm], inv[f], process=False), M[perm]


def truth(frame: int) -> np.ndarray:
    rest, weights, _ = scenes.figure_rest(VOXEL)
    return scenes.skin(rest.vertices, weights, *scenes.figure_pose(frame))


@pytest.fixture(scope="module")
def walk():
    frames = [0, 2, 4, 6, 8]
    return frames, [figure_frame(f, seed=10 + f) for f in frames]


# ---------------------------------------------------------------- topology and classes
def test_topology_counts():
    sphere, torus = trimesh.creation.icosphere(2), trimesh.creation.torus(1.0, 0.3)
    two = trimesh.util.concatenate([sphere, sphere.copy().apply_translation([3, 0, 0])])
    opened = trimesh.Trimesh(sphere.vertices, sphere.faces[:-3], process=False)
    t = [mesh_topology(m.vertices, m.faces) for m in (sphere, torus, two, opened)]
    assert [(x["components"], x["genus"], x["boundary_loops"], x["closed"]) for x in t] == [
        (1, 0, 0, True), (1, 1, 0, True), (2, 0, 0, True), (1, 0, 1, False)]
    assert t[0]["euler"] == 2 and t[1]["euler"] == 0


def test_classify_ranges_follow_table_8_1():
    s, b, t = trimesh.creation.icosphere(2), trimesh.creation.box(), trimesh.creation.torus(1.0, 0.3)
    moved = lambda m, k: trimesh.Trimesh(m.vertices * (1 + 0.1 * k), m.faces, process=False)  # noqa: E731
    seq = [moved(s, 0), moved(s, 1), moved(s, 2), b, t, moved(s, 3), moved(b, 1), moved(b, 2)]
    ranges = classify_sequence([(m.vertices, m.faces) for m in seq])
    assert [(r["start"], r["stop"], r["class"]) for r in ranges] == [
        (0, 2, DYNAMIC), (3, 3, STABLE), (4, 4, UNCONSTRAINED), (5, 5, STABLE), (6, 7, DYNAMIC)]
    out = run_node("track.classify", {"meshes": seq}, frames=list(range(100, 108)))["report"]
    assert out["class"] == UNCONSTRAINED and out["ranges"][0] == {"start": 100, "stop": 102, "class": DYNAMIC, "frames": 3}
    assert out["topology"]["genus"] == [0, 0, 0, 0, 1, 0, 0, 0]
    assert run_node("track.classify", {"meshes": seq[:3]}, frames=[0, 1, 2])["report"]["class"] == DYNAMIC
    assert run_node("track.classify", {"meshes": seq[:4]}, frames=[0, 1, 2, 3])["report"]["class"] == STABLE
    with pytest.raises(NodeError, match="exactly one"):
        run_node("track.classify", {})


def test_classify_golden(walk, golden):
    frames, data = walk
    out = run_node("track.classify", {"meshes": [m for m, _ in data]}, frames=frames)["report"]
    assert out["class"] == STABLE            # remeshed every frame: one topology, changing connectivity
    golden.check("track_classify_walk", out, Table)


# ---------------------------------------------------------------- geometry pieces
def test_closest_point_matches_brute_force():
    rng = np.random.default_rng(1)
    m = trimesh.creation.icosphere(2)
    m = trimesh.Trimesh(m.vertices * (1 + 0.1 * rng.standard_normal((len(m.vertices), 1))), m.faces, process=False)
    p = rng.normal(size=(300, 3)) * 0.6
    q, d = closest.SurfaceQuery(m.vertices, m.faces).closest(p)
    tri = m.triangles
    brute = closest.closest_on_triangles(p[:, None, :], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    bd = np.linalg.norm(brute - p[:, None, :], axis=2).min(axis=1)
    assert np.allclose(np.linalg.norm(q - p, axis=1), d)
    # nearest-vertex one-ring search is exact here except where a farther vertex's face is closer
    assert np.mean(np.isclose(d, bd, atol=1e-9)) > 0.97 and np.all(d >= bd - 1e-12) and np.max(d - bd) < 0.05


def test_closest_point_kernel_matches_its_numpy_reference():
    # kernels/closest.cl against SurfaceQuery.closest_reference: points near and far, on a vertex, on an edge
    rng = np.random.default_rng(2)
    m = trimesh.creation.icosphere(3)
    m = trimesh.Trimesh(m.vertices * (1 + 0.05 * rng.standard_normal((len(m.vertices), 1))), m.faces, process=False)
    e = m.edges_unique[:20]
    p = np.r_[rng.normal(size=(500, 3)) * 0.8, m.vertices[:20], m.vertices[e].mean(axis=1) * 1.01]
    query = closest.SurfaceQuery(m.vertices, m.faces)
    q, d, f = query.closest(p, with_faces=True)
    rq, rd, rf = query.closest_reference(p, with_faces=True)
    assert np.allclose(q, rq, rtol=0, atol=1e-12) and np.allclose(d, rd, rtol=0, atol=1e-12)
    # a face chosen otherwise only where two faces are equally close (a shared edge or vertex)
    other = f != rf
    assert other.mean() < 0.05
    assert np.allclose(np.linalg.norm(query.closest_reference(p[other])[0] - rq[other], axis=1), 0, atol=1e-12)
    assert len(query.closest(p[:0])[0]) == 0


def test_point_grid_matches_a_kd_tree():
    # kernels/closest.cl nearest_in_grid against cKDTree: near and far points, bounded and not, a flat point set
    # (the sphere pressed flat: every point twice, where either index is right)
    rng = np.random.default_rng(3)
    m = trimesh.creation.icosphere(4)
    v = np.asarray(m.vertices) * [3.0, 2.0, 7.0]
    for pts in (v, v * [1, 1, 0], v[:1]):
        grid = closest.PointGrid(pts)
        for scale, upper in ((0.05, np.inf), (0.5, 0.3), (3.0, 2.0), (40.0, np.inf)):
            q = pts[rng.integers(0, len(pts), 400)] + rng.normal(0, scale, (400, 3))
            d, j = grid.nearest(q, upper)
            rd, rj = grid.nearest_reference(q, upper)
            assert np.array_equal(d, rd) and np.array_equal(j >= 0, rj >= 0), (len(pts), scale, upper)
            assert np.array_equal(pts[j[j >= 0]], pts[rj[rj >= 0]])
            if pts is v:
                assert np.array_equal(j, rj)
    assert len(closest.PointGrid(v).nearest(v[:0])[0]) == 0
    # exact ties (points and queries on lattices, duplicated points) with coarse and fine grids: the search leaves
    # out a ring only when its bound exceeds the best distance, so the distances are cKDTree's and another index
    # only where two points are equally near
    lattice = rng.integers(0, 12, (3000, 3)) * 0.5
    for pts, q in ((lattice, rng.integers(0, 24, (4000, 3)) * 0.25), (np.vstack([v, v]), v[::7] + rng.normal(0, 0.3, (len(v[::7]), 3)))):
        for cells in (1.0, 8.0, 30.0):
            grid = closest.PointGrid(pts, cells_per_point=cells)
            for upper in (np.inf, 0.6):
                d, j = grid.nearest(q, upper)
                rd, rj = grid.nearest_reference(q, upper)
                assert np.array_equal(d, rd) and np.array_equal(j >= 0, rj >= 0), (cells, upper)
                ok = j >= 0
                assert np.array_equal(np.linalg.norm(pts[j[ok]] - q[ok], axis=1), np.linalg.norm(pts[rj[ok]] - q[ok], axis=1))


def test_closest_point_queries_refuse_points_that_are_not_finite():
    """NaN or infinite points (grid points, queries) and a surface without faces are a ValueError naming them, not
    cell indices made from NaN that send the kernels outside their buffers (a worker's segmentation fault)."""
    m = trimesh.creation.icosphere(2)
    query = closest.SurfaceQuery(m.vertices, m.faces)
    p = np.array(m.vertices[:10]) * 1.1
    for bad in (np.nan, np.inf, -np.inf):
        q = p.copy()
        q[4, 2] = bad
        with pytest.raises(ValueError, match="1 of 10 of the query points are not finite.*row 4"):
            query.closest(q)
        with pytest.raises(ValueError, match="grid's points are not finite"):
            closest.PointGrid(q)
    v = np.array(m.vertices)
    v[3] = np.nan
    with pytest.raises(ValueError, match="not finite"):
        closest.SurfaceQuery(v, m.faces)
    with pytest.raises(ValueError, match="without faces"):
        closest.SurfaceQuery(m.vertices, np.zeros((0, 3), np.int64)).closest(p)
    assert np.isfinite(query.closest(p)[1]).all()


def test_rotation_kernel_matches_its_svd_reference():
    # kernels/rotations.cl (one-sided Jacobi) against LAPACK's SVD: general matrices, near rotations, near
    # reflections (det < 0: the rotation, not the reflection), rank 2 (coplanar edges), and every result a rotation
    rng = np.random.default_rng(5)
    n = 300
    low = np.einsum("nik,njk->nij", rng.normal(size=(n, 3, 2)), rng.normal(size=(n, 3, 2)))
    for S in (rng.normal(size=(n, 3, 3)), 16 * np.eye(3) + rng.normal(size=(n, 3, 3)),
              16 * np.diag([1.0, 1.0, -1.0]) + rng.normal(size=(n, 3, 3)), low, low + 1e-9 * np.eye(3)):
        R = deform.nearest_rotations(S)
        assert np.abs(R - deform.nearest_rotations_reference(S)).max() < 1e-12
        assert np.allclose(np.einsum("nab,nac->nbc", R, R), np.eye(3), atol=1e-13) and np.allclose(np.linalg.det(R), 1)
    # rank 1 (a node with one neighbour): the rotation about the edge is not unique; still the best trace
    S = np.einsum("ni,nj->nij", rng.normal(size=(n, 3)), rng.normal(size=(n, 3)))
    R, ref = deform.nearest_rotations(S), deform.nearest_rotations_reference(S)
    assert np.allclose(np.einsum("nab,nba->n", R, S), np.einsum("nab,nba->n", ref, S), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1)
    assert len(deform.nearest_rotations(S[:0])) == 0


def test_silhouette_term_kernel_matches_its_numpy_reference():
    # kernels/outline.cl against silhouette_rows_reference, bit for bit: binary masks (the distance outline) and
    # soft alpha, lens distortion, a camera that sees the points from behind and points off the image; rows
    # outside every silhouette are found and point inwards
    from nodes.common import raster
    from nodes.common.silhouettes import Silhouettes

    cams = ring_rig(5, 160, 120, radius=3.0, z=0.5, target=(0, 0, 0.5),
                    dist=lambda i: [0.0, 0.0, 0.0, 0.0, 0.0] if i % 2 else [-0.2, 0.05, 0.001, -0.002, 0.01])
    cams[4].Rt = cams[4].Rt.copy()
    cams[4].Rt[:, 3] += [0.0, 0.0, -3.5]               # camera 4 moved forward past the points: some behind it
    sphere = trimesh.creation.icosphere(3, radius=0.4).apply_translation([0, 0, 0.5])
    sil = raster.silhouette(sphere.vertices, sphere.faces, cams)
    binary = MaskSet([np.where(s > 0, 255, 0).astype(np.uint8) for s in sil])
    rng = np.random.default_rng(3)
    soft = MaskSet(binary.masks, alpha=[np.clip(s.astype(np.float32) + rng.normal(0, 0.1, s.shape).astype(np.float32), 0, 1)
                                        for s in sil])
    voxel = 0.02
    x = (sphere.vertices[rng.integers(0, len(sphere.vertices), 3000)] * rng.uniform(0.8, 2.5, (3000, 1))
         + rng.normal(0, 0.05, (3000, 3)) - [0.0, 0.0, 0.5]) / voxel
    for masks in (binary, soft):
        views = Silhouettes.from_inputs(masks, cams, node="track").distance_outline()
        target = deform.Target(sphere.vertices, sphere.faces, np.array([0.0, 0.0, 0.5]), voxel, views)
        got, ref = deform.silhouette_rows(x, target), deform.silhouette_rows_reference(x, target)
        assert len(got[0]) > 1000 and all(np.array_equal(a, b) for a, b in zip(got, ref))
        i, g, d = got
        assert np.all(d > 0) and np.allclose(np.linalg.norm(g, axis=1), 1)
        if masks is binary:          # the distance outline rises towards the sphere (soft alpha: flat, noise)
            inward = np.einsum("ij,ij->i", g, -x[i] / np.linalg.norm(x[i], axis=1, keepdims=True))
            assert np.percentile(inward, 10) > 0.5          # 0.66 / 0.91 / 0.99 at the 10th / 50th / 90th
    empty = deform.silhouette_rows(x[:0], target)
    assert [len(a) for a in empty] == [0, 0, 0]
    # a view with an empty mask, cropped by track.crop to 1 x 1 pixel, pulls nothing (it read past its field)
    blind = binary.masks[:4] + [np.zeros((120, 160), np.uint8)]
    crop = run_node("track.crop", {"masks": MaskSet(blind), "cameras": cams}, {"margin": 4})
    assert crop["masks"].masks[4].shape == (1, 1)
    views = Silhouettes.from_inputs(crop["masks"], crop["cameras"], node="track").distance_outline()
    target = deform.Target(sphere.vertices, sphere.faces, np.array([0.0, 0.0, 0.5]), voxel, views)
    got, ref = deform.silhouette_rows(x, target), deform.silhouette_rows_reference(x, target)
    assert len(got[0]) > 1000 and all(np.array_equal(a, b) for a, b in zip(got, ref))


def test_graph_nodes_are_the_sequential_greedy_picks():
    # sample_nodes searches 16 candidates per Dijkstra call: the picks are those of the greedy one source at a time
    from scipy.sparse.csgraph import dijkstra

    from nodes.common.meshops import edge_length_graph

    m = trimesh.creation.capsule(height=2.0, radius=0.3, count=[24, 24])
    v, f = np.asarray(m.vertices) / 0.05, np.asarray(m.faces)
    graph, _ = edge_length_graph(v, f)
    covered, picks = np.zeros(len(v), bool), []
    for i in np.random.default_rng(0).permutation(len(v)):
        if not covered[i]:
            picks.append(i)
            covered |= np.isfinite(dijkstra(graph, directed=False, indices=i, limit=4.0))
    assert np.array_equal(deform.sample_nodes(v, f, 4.0, seed=0), picks) and len(picks) > 20


@pytest.mark.parametrize("route", ["cholmod", "superlu"])
def test_graph_is_geodesic_and_fit_recovers_a_bend(route, monkeypatch):
    # a capsule bent by 20 degrees in one step (its tip moves 9 voxels): the fit (same connectivity, so the
    # truth is vertex for vertex) lands on it, by either route of the factorisation (nodes/common/cholesky.py)
    from nodes.common import cholesky

    monkeypatch.setattr(cholesky, "ROUTE", route)
    cap = trimesh.creation.capsule(height=2.0, radius=0.3, count=[24, 24])
    rest = cap.vertices
    angle = np.radians(20) * np.clip((rest[:, 2] + 0.2) / 1.3, 0, 1)
    bent = rest.copy()
    bent[:, 0] = rest[:, 0] * np.cos(angle) + np.maximum(rest[:, 2], -0.2) * np.sin(angle)
    bent[:, 2] = np.where(rest[:, 2] > -0.2, -0.2 + (rest[:, 2] + 0.2) * np.cos(angle) - rest[:, 0] * np.sin(angle), rest[:, 2])
    voxel = 0.05
    src = deform.Target(rest, cap.faces, rest.min(axis=0), voxel)
    tgt = deform.Target(bent, cap.faces, rest.min(axis=0), voxel)
    graph = deform.build_graph(src.vertices, cap.faces, spacing=4.0)
    assert 10 < len(graph.nodes) < len(rest) / 4
    assert np.allclose(graph.vertex_weights.sum(axis=1), 1)
    reg = deform.Registration(graph, cap.faces, deform.FitParams())
    assert reg.cholesky.route == route
    state, info = reg.fit(deform.GraphState.identity(graph), tgt)
    S = ring_operator(cap.faces, len(rest))
    x = deform.detail(graph.deform(state), cap.faces, tgt, reg.params, S, offsets=deform.laplacian_offsets(graph, state, S))
    err = np.linalg.norm(x - tgt.vertices, axis=1)
    before = np.linalg.norm(src.vertices - tgt.vertices, axis=1)
    assert before.max() > 8 and err.mean() < 1.2 and np.percentile(err, 95) < 2.0, (before.max(), err.mean())
    _, d = tgt.query.closest(x)
    assert d.mean() < 0.1
    # rotations stay rotations
    R = state.R
    assert np.allclose(np.einsum("nab,nac->nbc", R, R), np.eye(3), atol=1e-9) and np.allclose(np.linalg.det(R), 1)


@pytest.mark.parametrize("route", ["cholmod", "superlu"])
def test_normal_equations_factorisation_matches_superlu(route, caplog):
    # the fit's factorisation (CHOLMOD, or SuperLU in a once-found order without cvxopt) on the registration's own
    # pattern, assembled as an ICP iteration assembles it: the lower triangle holds the whole matrix (built here
    # independently from every (pair, a, b) value) and the solve is scipy's SuperLU's; with CHOLMOD an indefinite
    # matrix (a negative diagonal entry) falls back to SuperLU with a warning instead of failing
    from scipy.sparse import coo_matrix, csc_matrix

    from nodes.common.cholesky import SparseCholesky

    cap = trimesh.creation.capsule(height=2.0, radius=0.3, count=[24, 24])
    graph = deform.build_graph(cap.vertices / 0.05, cap.faces, spacing=4.0)
    reg = deform.Registration(graph, cap.faces, deform.FitParams())
    rng = np.random.default_rng(3)
    n = rng.normal(size=(len(reg.src), 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    pairs = reg.pair_of_sample @ ((n[:, :, None] * n[:, None, :]).reshape(-1, 9) / len(n)) + 0.1 * reg.arap_blocks
    pairs[reg.diag_pair] += 1e-8 * np.eye(3).ravel()
    ab = np.arange(9)
    rows = (reg.pair_j[:, None] * 3 + ab // 3).ravel()
    cols = (reg.pair_k[:, None] * 3 + ab % 3).ravel()
    whole = coo_matrix((pairs.ravel(), (rows, cols)), shape=(reg.n3, reg.n3)).tocsr()
    values = pairs.ravel()[reg.gather]
    chol = SparseCholesky(reg.cholesky.pattern, route=route)
    assert abs(chol.full(values) - whole).max() == 0 and abs(whole - whole.T).max() == 0
    b = rng.normal(size=reg.n3)
    chol.factor(values)
    x = chol.solve(b)
    assert np.abs(x - chol.reference(values, b)).max() < 1e-9 * np.abs(x).max()
    assert np.abs(whole @ x - b).max() < 1e-9 * np.abs(b).max()
    if route == "cholmod":
        values[0] = -5.0                                   # (0, 0) is the pattern's first lower-triangle slot
        assert chol.full(values)[0, 0] == -5.0
        chol.factor(values)
        assert "not positive definite" in caplog.text
        assert np.abs(chol.full(values) @ chol.solve(b) - b).max() < 1e-8 * np.abs(b).max()
    with pytest.raises(ValueError, match="sorted indices"):        # column 0's rows 1, 0: out of order
        SparseCholesky(csc_matrix((np.ones(3), [1, 0, 2], [0, 2, 3, 3]), shape=(3, 3)), route=route)
    with pytest.raises(ValueError, match="lower triangle"):
        SparseCholesky(csc_matrix((np.ones(2), [0, 0], [0, 1, 2, 2]), shape=(3, 3)), route=route)


# ---------------------------------------------------------------- tracking
def correspondence_error(seq, data, frames) -> np.ndarray:
    """Per frame: mean distance (voxels) between each tracked vertex and where its body point truly is.
    Tracked vertices are the keyframe's remeshed vertices; their truth at frame t is M_key @ truth(t)."""
    out = []
    for m, f in zip(seq, frames):
        key = frames.index(m.metadata["keyframe"])
        M = data[key][1]
        out.append(np.linalg.norm(m.vertices - M @ truth(f), axis=1).mean() / VOXEL)
    return np.array(out)


@pytest.mark.slow
def test_track_figure_constant_connectivity_and_true_correspondences(walk):
    frames, data = walk
    out = run_node("track", {"meshes": [m for m, _ in data]}, {"voxel": VOXEL}, frames=frames, roundtrip=True)
    seq, table = out["sequence"], out["residuals"]
    assert sequence_segments(seq) == [(0, 5)] and table["segment_count"] == 1
    assert all(np.array_equal(m.faces, seq[0].faces) for m in seq)
    assert [m.metadata["frame"] for m in seq] == frames
    key = frames.index(seq[0].metadata["keyframe"])
    assert np.array_equal(seq[key].vertices, data[key][0].vertices)       # the keyframe is its reconstruction
    assert max(table["residual"]["distance"]) < 0.25                       # voxels, both directions
    err = correspondence_error(seq, data, frames)
    # the identity map (each frame's vertices where they were at the keyframe) is far off: the limbs swing
    still = [np.linalg.norm(data[key][0].vertices - data[key][1] @ truth(f), axis=1).mean() / VOXEL for f in frames]
    assert err.max() < 0.6 and max(still) > 2.0, (err, still)


@pytest.mark.slow
def test_track_starts_a_segment_at_a_topology_change():
    sphere = trimesh.creation.icosphere(3, radius=1.0)
    torus = trimesh.creation.torus(0.9, 0.35, major_sections=48, minor_sections=16)
    seq = [trimesh.Trimesh(sphere.vertices * [1 + 0.03 * k, 1, 1], sphere.faces, process=False) for k in range(3)]
    seq += [trimesh.Trimesh(torus.vertices * [1 + 0.03 * k, 1, 1], torus.faces, process=False) for k in range(3)]
    out = run_node("track", {"meshes": seq}, {"voxel": 0.05}, frames=list(range(6)))
    segs = out["residuals"]["segments"]
    assert [(s["start"], s["stop"], s["genus"]) for s in segs] == [(0, 2, 0), (3, 5, 1)]
    assert "frame 3" in segs[0]["ended_after"] and segs[0]["keyframe"] in (0, 1, 2)
    assert sequence_segments(out["sequence"]) == [(0, 3), (3, 6)]
    classes = run_node("track.classify", {"sequence": out["sequence"]})["report"]["ranges"]
    assert [(r["start"], r["stop"], r["class"]) for r in classes] == [(0, 2, DYNAMIC), (3, 5, DYNAMIC)]


@pytest.mark.slow
def test_track_with_silhouettes_keeps_iou(golden):
    cams = ring_rig(6, 200, 150, radius=3.0, z=0.9, target=(0, 0, 0.9), fov=55)
    frames = [0, 3, 6]
    data = [figure_frame(f, seed=f) for f in frames]
    from nodes.common import raster

    masks = [MaskSet([np.where(s > 0, 255, 0).astype(np.uint8) for s in raster.silhouette(truth(f), scenes.figure_rest(VOXEL)[0].faces, cams)])
             for f in frames]
    crop = [run_node("track.crop", {"masks": m, "cameras": cams}, {"margin": 8}) for m in masks]
    assert all(c["masks"].masks[0].size < m.masks[0].size for c, m in zip(crop, masks))
    out = run_node("track", {"meshes": [m for m, _ in data], "masks": [c["masks"] for c in crop],
                             "cameras": [c["cameras"] for c in crop]}, {"voxel": VOXEL}, frames=frames)
    table = out["residuals"]
    assert table["segment_count"] == 1 and table["iou_drop_max"] <= 0.01
    assert min(table["timeline"]["iou"]) > 0.9
    last = out["sequence"][-1]
    golden.check("track_figure_frame6", last, Mesh, count_rtol=0.0, hausdorff=0.2 * VOXEL)


def test_track_errors_name_the_problem():
    m = trimesh.creation.icosphere(2)
    with pytest.raises(NodeError, match="both 'masks' and 'cameras'"):
        run_node("track", {"meshes": [m], "masks": [MaskSet([np.zeros((4, 4), np.uint8)])]})
    with pytest.raises(NodeError, match="2 masks for 1 meshes"):
        run_node("track", {"meshes": [m], "masks": [None, None], "cameras": [None, None]})


def test_empty_frame_is_its_own_segment():
    s = trimesh.creation.icosphere(2)
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
    out = run_node("track", {"meshes": [s, empty, s]}, {"voxel": 0.1}, frames=[0, 1, 2])
    assert [(x["start"], x["stop"]) for x in out["residuals"]["segments"]] == [(0, 0), (1, 1), (2, 2)]
    assert len(out["sequence"][1].faces) == 0


# ---------------------------------------------------------------- exports and the sequence type
@pytest.fixture(scope="module")
def tracked_pair():
    return two_segments()


def test_frame_node_gives_the_frame_and_its_keyframe(tracked_pair):
    def stored(m):  # a Mesh value is what its file holds (float32 vertices), in memory as from the cache
        return np.asarray(m.vertices, np.float32)

    out = run_node("track.frame", {"sequence": tracked_pair}, frame=11)
    np.testing.assert_array_equal(out["mesh"].vertices, stored(tracked_pair[1]))
    np.testing.assert_array_equal(out["keyframe"].vertices, stored(tracked_pair[0]))   # keyframe 10, same segment
    out = run_node("track.frame", {"sequence": tracked_pair}, frame=14)
    np.testing.assert_array_equal(out["keyframe"].vertices, stored(tracked_pair[3]))   # keyframe 13
    assert np.array_equal(out["mesh"].faces, out["keyframe"].faces)
    with pytest.raises(NodeError, match="frame 7 is not in the sequence"):
        run_node("track.frame", {"sequence": tracked_pair}, frame=7)


def test_usd_points_at_frame_k_equal_ours(tracked_pair):
    data = formats.usd_bytes(tracked_pair, fps=25.0)
    for m in tracked_pair:
        got = formats.usd_points(data, m.metadata["frame"])
        assert np.array_equal(got, np.asarray(m.vertices, np.float32))
    from pxr import Usd, UsdGeom
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "a.usdc"
        p.write_bytes(data)
        stage = Usd.Stage.Open(str(p))
        assert stage.GetTimeCodesPerSecond() == 25.0 and (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (10, 14)
        seg1 = UsdGeom.Mesh(stage.GetPrimAtPath("/DynamicMesh/segment_0001"))
        assert seg1.ComputeVisibility(Usd.TimeCode(12)) == UsdGeom.Tokens.invisible
        assert list(seg1.GetFaceVertexIndicesAttr().Get()) == tracked_pair[3].faces.ravel().tolist()


def test_gltf_and_draco_reproduce_the_frames(tracked_pair):
    import DracoPy

    glb = formats.gltf_bytes(tracked_pair, fps=25.0)
    for k, m in enumerate(tracked_pair):
        assert np.allclose(formats.gltf_frame(glb, k), m.vertices, atol=1e-6)
    scene = trimesh.load(trimesh.util.wrap_as_stream(glb), file_type="glb")      # another reader opens it
    assert len(scene.geometry) == 2
    files = formats.draco_sequence(tracked_pair, bits=14)
    assert sorted(files) == ["frame_00010.drc", "frame_00011.drc", "frame_00012.drc", "frame_00013.drc", "frame_00014.drc",
                             "segment_0000.drc", "segment_0001.drc"]
    for m in tracked_pair:
        faces = DracoPy.decode(files[f"segment_{m.metadata['segment']:04d}.drc"]).faces
        points = DracoPy.decode(files[f"frame_{m.metadata['frame']:05d}.drc"]).points
        assert np.array_equal(faces, m.faces)                                    # vertex order preserved
        assert np.abs(points - m.vertices).max() <= np.ptp(m.vertices, axis=0).max() / 2 ** 13


def test_export_node_publishes_and_sizes(tracked_pair):
    out = run_node("track.export", {"sequence": tracked_pair, "meshes": tracked_pair}, {"name": "walk"})
    names = set(out["files"])
    assert {"walk.usdc", "walk.glb"} <= names and sum(n.startswith("walk_draco/") for n in names) == 7
    s = out["sizes"]
    assert s["segments_frames"] == [3, 2] and s["files"]["walk.usdc"] == len(out["files"]["walk.usdc"])
    assert s["dynamic_raw_bytes"] < s["reconstruction_raw_bytes"]
    with pytest.raises(NodeError, match="unknown formats"):
        run_node("track.export", {"sequence": tracked_pair}, {"formats": ["fbx"]})


def test_mesh_sequence_roundtrip_keeps_segments(tracked_pair, tmp_path):
    MeshSequence.save(tracked_pair, tmp_path)
    back = MeshSequence.load(tmp_path)
    assert [m.metadata for m in back] == [m.metadata for m in tracked_pair]
    assert all(np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces) for a, b in zip(back, tracked_pair))
    assert len(list(tmp_path.glob("*.ply"))) == 2                                # one PLY per segment
    # read from the arrays (no PLY parsed), writable (bindings that take buffers refuse read-only ones), and a
    # write stays in the reader's copy, not in the stored file
    assert len(list(tmp_path.glob("*.faces.npy"))) == 2 and back[0].vertices.flags.writeable
    back[0].vertices[0] = 7.0
    assert np.array_equal(MeshSequence.load(tmp_path)[0].vertices, tracked_pair[0].vertices)
    for f in tmp_path.glob("*.ply"):
        f.rename(f.with_suffix(".look"))
    assert all(np.array_equal(a.faces, b.faces) for a, b in zip(MeshSequence.load(tmp_path), back))
    for f in tmp_path.glob("*.look"):
        f.rename(f.with_suffix(".ply"))
    for f in tmp_path.glob("*.faces.npy"):      # an entry written before the faces were stored: from its PLYs
        f.unlink()
    old = MeshSequence.load(tmp_path)
    assert all(np.array_equal(a.faces, b.faces) and np.array_equal(a.vertices, b.vertices) for a, b in zip(old, tracked_pair))
    del back, old
    MeshSequence.save(tracked_pair, tmp_path)
    np.save(tmp_path / "bad.npy", np.asarray(tracked_pair[0].faces, np.int32) + len(tracked_pair[0].vertices))
    (tmp_path / "bad.npy").replace(tmp_path / "segment_0000.faces.npy")
    with pytest.raises(DataError, match="do not index its"):
        MeshSequence.load(tmp_path)
    MeshSequence.save(tracked_pair, tmp_path)
    (tmp_path / "bad.npy").write_bytes(b"not an array")
    (tmp_path / "bad.npy").replace(tmp_path / "segment_0001.npy")
    with pytest.raises(DataError, match="unreadable array"):
        MeshSequence.load(tmp_path)
    bad = list(tracked_pair)
    bad[1] = trimesh.Trimesh(bad[3].vertices, bad[3].faces, process=False, metadata={"segment": 0})
    assert "do not share their faces" in MeshSequence.check(bad)


def test_windows_of_a_sequence_join_with_their_segments_numbered_on(tracked_pair, tmp_path):
    """A windowed track's windows each number their segments from 0; joined, they stay apart."""
    second = [trimesh.Trimesh(m.vertices, m.faces, process=False, metadata={**m.metadata, "segment": 0})
              for m in tracked_pair[3:]]
    joined = MeshSequence.join([tracked_pair[:3], second])
    assert MeshSequence.check(joined) is None
    assert sequence_segments(joined) == [(0, 3), (3, 5)]
    assert [m.metadata for m in joined] == [m.metadata for m in tracked_pair]
    assert [m.metadata["segment"] for m in second] == [0, 0], "the windows' own values are not changed"
    assert all(np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces) for a, b in zip(joined, tracked_pair))
    MeshSequence.save(joined, tmp_path)
    assert sequence_segments(MeshSequence.load(tmp_path)) == [(0, 3), (3, 5)]


def test_crop_keeps_the_point_test():
    from nodes.common.silhouettes import Silhouettes, inside_hull

    cams = ring_rig(4, 160, 120, radius=3.0, z=0.5, target=(0, 0, 0.5))
    sphere = trimesh.creation.icosphere(3, radius=0.4).apply_translation([0, 0, 0.5])
    from nodes.common import raster

    masks = MaskSet([np.where(s > 0, 255, 0).astype(np.uint8) for s in raster.silhouette(sphere.vertices, sphere.faces, cams)])
    out = run_node("track.crop", {"masks": masks, "cameras": cams}, {"margin": 4})
    p = np.random.default_rng(0).uniform([-0.6, -0.6, -0.1], [0.6, 0.6, 1.1], (4000, 3))
    full = inside_hull(p, Silhouettes.from_inputs(masks, cams))
    cropped = inside_hull(p, Silhouettes.from_inputs(out["masks"], out["cameras"]))
    assert full.sum() > 100 and np.array_equal(full, cropped)
    uv, _ = cams.project(p, 0)
    uv_c, _ = out["cameras"].project(p, 0)
    c0 = out["cameras"][0]
    assert np.allclose(uv - uv_c, [cams[0].K[0, 2] - c0.K[0, 2], cams[0].K[1, 2] - c0.K[1, 2]])
    # each crop is the box of the mask's pixels > 127 grown by the margin, clipped to the image (one view's mask
    # touches the image's corner, one is empty: 1 x 1)
    masks.masks[1][:5, :3] = 200
    masks.masks[2][:] = 0
    out = run_node("track.crop", {"masks": masks, "cameras": cams}, {"margin": 4})
    for m, got, cam in zip(masks.masks, out["masks"].masks, out["cameras"]):
        ys, xs = np.nonzero(m > 127)
        if len(xs) == 0:
            assert got.shape == (1, 1) and cam.width == cam.height == 1
            continue
        x0, y0 = max(0, xs.min() - 4), max(0, ys.min() - 4)
        x1, y1 = min(m.shape[1], xs.max() + 5), min(m.shape[0], ys.max() + 5)
        assert np.array_equal(got, m[y0:y1, x0:x1]) and (cam.width, cam.height) == (x1 - x0, y1 - y0)


# ---------------------------------------------------------------- graphs
@pytest.mark.parametrize("name", ["track_synth.yaml", "track_child_rope.yaml"])
def test_track_graphs_validate(name):
    g = load_graph(ROOT / "graphs" / name)
    assert {"track", "track.classify", "track.export"} <= {s.type_name for s in g.nodes.values()}



# ---------------------------------------------------------------- real data
@pytest.mark.slow
@pytest.mark.realdata
def test_child_rope_graph_tracks_a_few_frames(tmp_path, data_dir, monkeypatch):
    from nodegraph.cache import Cache
    from nodegraph.executors import LocalExecutor
    from nodegraph.run import run_graph

    monkeypatch.setenv("VOLCAP_DATA", str(data_dir))
    g = load_graph(ROOT / "graphs/track_child_rope.yaml", overrides=["hull.resolution=64", "track.voxel=0.0244"],
                   frames="0:5")
    res = run_graph(g, Cache(tmp_path / "cache"), tmp_path / "out", LocalExecutor(1), progress=False)
    assert res.ok, res.failures
    rec = {r["node"]: r for r in res.records if r["frame"] is None}
    seq = MeshSequence.load(Path(rec["track"]["cache_dir"]) / "sequence")
    table = Table.load(Path(rec["track"]["cache_dir"]) / "residuals")
    assert [m.metadata["frame"] for m in seq] == [0, 1, 2, 3, 4]
    for a, b in sequence_segments(seq):
        assert all(np.array_equal(seq[i].faces, seq[a].faces) for i in range(a, b))
    assert table["iou_drop_max"] <= 0.01 and max(table["residual"]["distance"]) <= 1.0
    before = Table.load(Path(rec["classify"]["cache_dir"]) / "report")
    after = Table.load(Path(rec["tracked"]["cache_dir"]) / "report")
    assert before["class"] != "dynamic mesh"
    multi = [b - a for a, b in sequence_segments(seq) if b - a > 1]           # every tracked segment: a dynamic mesh
    assert multi and sorted(r["frames"] for r in after["ranges"] if r["class"] == DYNAMIC) == sorted(multi)
    usd = (tmp_path / "out" / "child_rope_dynamic.usdc").read_bytes()
    assert np.array_equal(formats.usd_points(usd, 3), np.asarray(seq[3].vertices, np.float32))
    # per frame again through track.frame: the tracked mesh is published and scores like the reconstruction
    for a, b in sequence_segments(seq):
        for i in range(a, b):
            ply = trimesh.load(tmp_path / "out" / f"child_rope_tracked_{i:04d}.ply", process=False)
            assert np.array_equal(ply.faces, seq[a].faces) and np.allclose(ply.vertices, seq[i].vertices, atol=1e-6)
    own = [r for r in res.records if r["node"] == "score"]
    ours = {r["frame"]: r for r in res.records if r["node"] == "tracked_score"}
    for r in own:
        iou = Table.load(Path(r["cache_dir"]) / "report")["mean_iou"]
        tracked = Table.load(Path(ours[r["frame"]]["cache_dir"]) / "report")["mean_iou"]
        assert tracked >= iou - 0.01, (r["frame"], iou, tracked)


def test_snap_puts_the_tracked_surface_on_the_target():
    """deform.snap: vertices within snap_reach of the target end on its surface (same faces), farther ones stay."""
    src = trimesh.creation.icosphere(3, radius=1.0)
    dst = trimesh.creation.icosphere(4, radius=1.02)
    target = deform.Target(dst.vertices, dst.faces, np.zeros(3), 0.05)          # 0.4 voxel apart
    x = np.asarray(src.vertices) / 0.05
    far = np.argmax(x[:, 2])
    x[far] *= 1.2                                                               # ~4 voxels out: beyond the reach
    S = ring_operator(src.faces, len(x))
    degree = np.asarray(S.sum(axis=1)).ravel() - 1.0
    offsets = x - (S @ x - x) / degree[:, None]                                  # the layout's umbrella offsets
    out = deform.snap(x, np.asarray(src.faces), target, deform.FitParams(), S, offsets=offsets)
    _, d = target.query.closest(out)
    near = np.ones(len(x), bool)
    near[np.asarray(src.faces)[np.any(np.asarray(src.faces) == far, axis=1)].ravel()] = False
    assert target.query.closest(x)[1][near].min() > 0.3                          # they started ~0.4 voxel off
    assert d[near].max() < 1e-9 and d[far] > 3.0
    # the tangential steps keep the layout: vertices slide little along the surface (angles; 0.05 = 1 voxel)
    slide = np.linalg.norm(out[near] / np.linalg.norm(out[near], axis=1, keepdims=True)
                           - x[near] / np.linalg.norm(x[near], axis=1, keepdims=True), axis=1)
    assert np.median(slide) < 0.002 and slide.max() < 0.05


def test_unfold_opens_folds_and_puts_the_vertices_back_on_the_target():
    """deform.unfold: a vertex pushed across its neighbour folds four edges; the fold's vertices are smoothed
    open and put back on the target surface; vertices away from the fold do not move."""
    src = trimesh.creation.icosphere(4, radius=1.0)
    target = deform.Target(src.vertices, src.faces, np.zeros(3), 0.05)
    faces = np.asarray(src.faces)
    x = np.asarray(src.vertices) / 0.05
    nb = src.vertex_neighbors[5]
    x[5] += 1.5 * (x[nb[0]] - x[5])                                          # across its neighbour: a fold
    pairs = edge_face_pairs(faces)
    assert len(pairs[0]) == len(src.edges_unique)
    assert len(folded_edges(x, faces, pairs)) == 4
    S = ring_operator(faces, len(x))
    out = deform.unfold(x, faces, pairs, S, rounds=8, target=target)
    assert len(folded_edges(out, faces, pairs)) == 0
    assert target.query.closest(out)[1].max() < 0.05                       # voxels: back on the surface
    seed = np.zeros(len(x))
    seed[5] = 1.0
    ring = np.flatnonzero(S @ (S @ seed) > 0)                               # two rings around the fold
    still = np.setdiff1d(np.arange(len(x)), ring)
    assert np.array_equal(out[still], x[still])


def test_trial_truncates_where_another_segment_took_frames():
    """A keyframe trial kept for a later round is cut at the first frame another segment took, each side."""
    from nodes.track.tracking import FrameResult, Segment, _Trial

    res = {i: FrameResult(np.zeros((1, 3)), -1, 5, 0, 0, 0, 0) for i in range(2, 10)}
    t = _Trial(Segment(-1, 5, 2, 9, np.zeros((0, 3), np.int64), 1, "a", "b"), res)
    done = np.zeros(12, bool)
    done[[3, 8]] = True
    assert t.truncate(done)
    assert (t.seg.start, t.seg.stop, t.length) == (4, 7, 4) and sorted(t.results) == [4, 5, 6, 7]
    assert t.seg.reason_start == "frame 3: already tracked" and t.seg.reason_stop == "frame 8: already tracked"
    done[5] = True
    assert not t.truncate(done)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["retry", "bridge", "fails"])
def test_a_failed_fit_is_tried_again_then_bridged_and_kept_only_if_it_fits(monkeypatch, mode):
    """A fit that fails going forwards (here: frame 3's first fit, forced) is tried again from frame 2's state
    (``retry``); without that second try it is tracked through: the next frame that fits (4) is the bridge's
    far end and frame 3 is fitted again from it, kept when that fit holds (one segment, frames 3-4 marked
    bridged), else the segment ends before frame 3 (no frame kept that failed)."""
    from nodes.track import tracking

    sphere = trimesh.creation.icosphere(3, radius=1.0)
    seq = [trimesh.Trimesh(sphere.vertices * [1 + 0.02 * k, 1, 1], sphere.faces, process=False) for k in range(6)]
    frames = tracking.Frames(seq, voxel=0.05, numbers=range(200, 206))   # a run that starts at frame 200
    fitted = []                                      # frame of each fit, in order (Frames.target is asked first)
    target = frames.target
    monkeypatch.setattr(frames, "target", lambda i: fitted.append(i) or target(i))
    real = tracking._failure

    def failure(res, iou, iou_rec, p):
        i = fitted[-1]
        if i == 3 and (fitted.count(3) == 1 or mode == "fails"):
            return "forced failure"
        return real(res, iou, iou_rec, p)

    monkeypatch.setattr(tracking, "_failure", failure)
    params = tracking.TrackParams(voxel=0.05, bridge=2, retry=2 if mode == "retry" else 0)
    results, segments = tracking.track_sequence(frames, params, keyframe=0)
    spans = [(s.start, s.stop) for s in segments]
    bridged = [i for i, r in enumerate(results) if r.bridged]
    if mode == "fails":
        assert spans[0] == (0, 2) and segments[0].reason_stop == "frame 203: forced failure" and bridged == []
        return
    assert spans == [(0, 5)] and max(r.completeness_mean for r in results) < 0.2
    if mode == "retry":
        assert bridged == [] and fitted[:7] == [0, 1, 2, 3, 3, 4, 5]          # frame 3 twice, then on
    else:
        assert bridged == [3, 4] and fitted[:6] == [0, 1, 2, 3, 4, 3]        # on to 4 (fits), back to 3


def test_simplify_replaces_replayed_vertices_that_are_not_finite_or_far():
    """track.simplify replays the keyframe's collapses on every frame, and the replay solves each merged vertex's
    quadric whenever its determinant is not exactly 0: a nearly singular one gave NaN (the demo's stage at 6 cameras,
    pose2sim_single) or a point far off. Such a vertex takes the keyframe's place of it moved by the mean motion of
    the vertices merged into it; every other vertex is the replay's, bit for bit; the report counts them."""
    import fast_simplification

    from nodes.track import simplify as S

    base = trimesh.creation.icosphere(subdivisions=3)
    frames = []
    for k, (shift, scale) in enumerate(((0.0, 1.0), (0.05, 1.02), (0.1, 1.05))):
        m = trimesh.Trimesh(base.vertices * scale + [shift, 0, 0], base.faces, process=False)
        m.metadata.update(segment=0, keyframe=0, frame=k)
        frames.append(m)
    plain, report = S.simplify_sequence(frames, 0.25)                  # the library's replay, nothing refused
    assert report["segments"][0]["vertices_replaced"] == 0
    faces = np.asarray(base.faces, np.int64)
    _, _, collapses = fast_simplification.simplify(np.asarray(base.vertices, np.float64), faces,
                                                   target_reduction=0.75, return_collapses=True)
    _, _, mapping = fast_simplification.replay_simplification(np.asarray(base.vertices, np.float64), faces, collapses)
    real = fast_simplification.replay_simplification

    def broken(points, triangles, col):                # frame 2: one NaN and one point 1 km away; the keyframe: a NaN
        p, f, mp = real(points, triangles, col)
        p = p.copy()
        if points[0, 0] > frames[1].vertices[0, 0] + 0.01:
            p[5] = np.nan
            p[9] += 1000.0
        elif points[0, 0] == frames[0].vertices[0, 0]:
            p[11] = np.nan
        return p, f, mp

    original = fast_simplification.replay_simplification
    fast_simplification.replay_simplification = broken
    try:
        got, report = S.simplify_sequence(frames, 0.25)
    finally:
        fast_simplification.replay_simplification = original
    assert report["segments"][0]["vertices_replaced"] == 3
    assert all(np.isfinite(np.asarray(m.vertices)).all() for m in got)
    x0, x2 = np.asarray(frames[0].vertices), np.asarray(frames[2].vertices)
    # the keyframe's NaN: the mean of the vertices merged into it (the replay's points are float32: 1e-6)
    assert np.allclose(np.asarray(got[0].vertices)[11], x0[mapping == 11].mean(axis=0), rtol=0, atol=1e-6)
    for k in (0, 1, 2):
        keep = np.setdiff1d(np.arange(len(got[k].vertices)), [11] if k == 0 else [5, 9] if k == 2 else [])
        assert np.array_equal(np.asarray(got[k].vertices)[keep], np.asarray(plain[k].vertices)[keep]), k
    for j in (5, 9):   # the keyframe's place moved by the merged vertices' mean motion
        motion = (x2[mapping == j] - x0[mapping == j]).mean(axis=0)
        assert np.allclose(np.asarray(got[2].vertices)[j], np.asarray(got[0].vertices)[j] + motion, rtol=0, atol=1e-6)
        assert not np.allclose(np.asarray(got[2].vertices)[j], x2[mapping == j].mean(axis=0), rtol=0, atol=1e-6)


def test_meshes_with_vertices_that_are_not_finite_are_refused_as_outputs():
    """A node whose output mesh (or a frame of its sequence) has a NaN or infinite vertex fails there, named, with
    the type's message: its readers (texture.transfer's kernels, the stream's quantiser) cannot use it."""
    m = trimesh.creation.icosphere(1)
    assert Mesh.check(m) is None and MeshSequence.check([m, m]) is None
    bad = trimesh.Trimesh(np.array(m.vertices), m.faces, process=False)
    bad.vertices[2] = [0.0, np.inf, 0.0]
    bad.metadata["frame"] = 41
    assert "1 of its 42 vertices are not finite" in Mesh.check(bad)
    assert MeshSequence.check([m, bad]).startswith("mesh 1 (frame 41): 1 of its 42 vertices are not finite")


def test_a_fit_that_diverges_ends_the_segment_and_does_not_stop_the_node(monkeypatch):
    """A graph fit whose vertices come out NaN (frame 3's, forced) is a failed fit like any other: the segment ends
    before it, with that reason, and tracking goes on from another keyframe (the closest-point queries that
    follow refuse NaN points: without this the whole node stopped there)."""
    from nodes.track import deform, tracking

    sphere = trimesh.creation.icosphere(3, radius=1.0)
    seq = [trimesh.Trimesh(sphere.vertices * [1 + 0.02 * k, 1, 1], sphere.faces, process=False) for k in range(5)]
    frames = tracking.Frames(seq, voxel=0.05)
    real = deform.Registration.fit

    def fit(self, init, target):
        state, info = real(self, init, target)
        if target is frames._targets.get(3):
            state = deform.GraphState(state.R, state.t + np.nan)
        return state, info

    monkeypatch.setattr(deform.Registration, "fit", fit)
    results, segments = tracking.track_sequence(frames, tracking.TrackParams(voxel=0.05, bridge=0, retry=0), keyframe=0)
    assert [(s.start, s.stop) for s in segments][0] == (0, 2)
    assert segments[0].reason_stop == "frame 3: the fit diverged (vertices not finite)"
    assert all(np.isfinite(r.vertices).all() for r in results) and sum(s.stop - s.start + 1 for s in segments) == 5

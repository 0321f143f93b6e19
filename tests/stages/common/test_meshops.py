"""The mesh core (nodes.common.meshops), each operation once, on meshes small enough to count by hand: a
tetrahedron, a cube (12 triangles), a folded pair, a lone triangle."""
import numpy as np
import pytest
import trimesh

from nodes.common.meshops import (FOLD_COS, FOLD_DEG, edge_face_pairs, edge_faces, edge_length_graph, face_areas,
                                  face_neighbours, face_normals, folded_edges, neighbour_mean, padded_rows, ring_average,
                                  ring_operator, row_norms, unique_edges, vertex_faces, vertex_neighbours,
                                  vertex_normals)

TET_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])      # outward
TRI_F = np.array([[0, 1, 2]])


def folded_pair(height: float):
    """Two triangles on edge 0-1: face 1 is face 0 turned about that edge, by 180 degrees when height = 0."""
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, 1, height]])
    return v, np.array([[0, 1, 2], [1, 0, 3]])


def test_unique_edges_of_a_tetrahedron():
    edges, fe = unique_edges(TET_F)
    assert edges.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
    for i, f in enumerate(TET_F):                       # side k runs f[k] -> f[k + 1]
        for k in range(3):
            assert sorted(edges[fe[i, k]]) == sorted([f[k], f[(k + 1) % 3]])
    assert unique_edges(np.zeros((0, 3), np.int64))[0].shape == (0, 2)


def test_edge_faces_counts_borders_interiors_and_non_manifold_edges():
    edges, _, pair, count = edge_faces(TET_F)
    assert count.tolist() == [2] * 6 and pair.tolist() == [[0, 1], [0, 2], [1, 2], [0, 3], [1, 3], [2, 3]]
    _, _, pair, count = edge_faces(TRI_F)
    assert count.tolist() == [1, 1, 1] and (pair[:, 1] == -1).all() and (pair[:, 0] == 0).all()
    fin = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])   # three faces on edge 0-1
    edges, _, pair, count = edge_faces(fin)
    assert count[0] == 3 and edges[0].tolist() == [0, 1] and pair[0].tolist() == [0, 1]
    e, p = edge_face_pairs(fin)                          # interior = exactly two faces: none here
    assert len(e) == 0 and p.shape == (0, 2)
    cube = trimesh.creation.box()
    e, p = edge_face_pairs(cube.faces)
    assert len(e) == 18 and len(p) == 18 and (p[:, 0] < p[:, 1]).all()


def test_edge_faces_are_each_edges_first_two_faces_on_a_shuffled_non_manifold_mesh():
    # every edge's two smallest face indices, by a plain loop, on a sphere with repeated and flipped faces
    # (edges of 3 and more faces) in random order: the pairs edge_faces finds without a stable sort
    rng = np.random.default_rng(4)
    f = np.asarray(trimesh.creation.icosphere(2).faces)
    f = np.concatenate([f, f[rng.choice(len(f), 40)], f[rng.choice(len(f), 30)][:, ::-1]])[rng.permutation(len(f) + 70)]
    edges, fe, pair, count = edge_faces(f)
    faces_of = {}
    for i, face in enumerate(f):
        for k in range(3):
            faces_of.setdefault(tuple(sorted((face[k], face[(k + 1) % 3]))), []).append(i)
    assert len(faces_of) == len(edges) and (count > 2).sum() > 10
    for e, (a, b) in enumerate(edges):
        got = faces_of[(a, b)]
        assert count[e] == len(got) and pair[e, 0] == got[0] and pair[e, 1] == (got[1] if len(got) > 1 else -1)


def test_face_neighbours():
    nbr = face_neighbours(TET_F)
    for i in range(4):                                   # every face touches the three others once
        assert sorted(nbr[i].tolist()) == sorted(set(range(4)) - {i})
    assert nbr[0].tolist() == [2, 3, 1]                  # face 0 = (0, 2, 1): 0-2 face 2, 2-1 face 3, 1-0 face 1
    assert face_neighbours(TRI_F).tolist() == [[-1, -1, -1]]
    m = trimesh.creation.icosphere(2)                    # the same pairs as trimesh's face adjacency
    nbr = face_neighbours(m.faces)
    assert np.all(nbr >= 0)
    pairs = {tuple(sorted((f, int(g)))) for f in range(len(nbr)) for g in nbr[f]}
    assert pairs == {tuple(sorted(p)) for p in m.face_adjacency.tolist()}


def test_vertex_faces_csr_and_padded():
    off, idx = vertex_faces(TET_F, 5)                    # vertex 4 unused
    assert off.dtype == np.int32 and idx.dtype == np.int32
    assert off.tolist() == [0, 3, 6, 9, 12, 12]
    assert idx.tolist() == [0, 1, 2, 0, 1, 3, 0, 2, 3, 1, 2, 3]
    pad = padded_rows(off, idx)
    assert pad.shape == (5, 3) and pad[4].tolist() == [-1, -1, -1] and pad[3].tolist() == [1, 2, 3]
    assert padded_rows(np.array([0, 0]), np.zeros(0, np.int32)).tolist() == [[-1]]


def test_vertex_neighbours_of_a_tetrahedron():
    off, nb = vertex_neighbours(TET_F, 4)
    assert off.tolist() == [0, 3, 6, 9, 12] and nb.tolist() == [1, 2, 3, 0, 2, 3, 0, 1, 3, 0, 1, 2]


def test_face_and_vertex_normals():
    n = face_normals(TET_V, TET_F)
    np.testing.assert_allclose(n[:3], [[0, 0, -1], [0, -1, 0], [-1, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(n[3], np.ones(3) / np.sqrt(3), rtol=1e-15)
    assert face_normals(np.zeros((3, 3)), TRI_F).tolist() == [[0, 0, 0]]       # degenerate: zero
    np.testing.assert_allclose(face_areas(TET_V, TET_F), [0.5, 0.5, 0.5, np.sqrt(3) / 2], rtol=1e-15)
    cube = trimesh.creation.box()
    np.testing.assert_allclose(face_normals(cube.vertices, cube.faces), cube.face_normals, atol=1e-15)
    vn = vertex_normals(cube.vertices, cube.faces)      # area-weighted: a corner with two triangles on one side
    counts = np.zeros((8, 3))                            # and one on each of the others leans to that side
    for f, n in zip(cube.faces, cube.face_normals):
        counts[f] += np.abs(n)
    assert {tuple(sorted(c)) for c in counts} <= {(1.0, 1.0, 2.0), (1.0, 2.0, 2.0)}
    np.testing.assert_allclose(vn, np.sign(cube.vertices) * counts / np.linalg.norm(counts, axis=1)[:, None], rtol=1e-12)
    assert vertex_normals(np.zeros((4, 3)), TRI_F)[3].tolist() == [0, 0, 0]    # unused: zero
    # vertex 0 of the tetrahedron: its three axis faces have equal areas, weights equal
    np.testing.assert_allclose(vertex_normals(TET_V, TET_F)[0], -np.ones(3) / np.sqrt(3), rtol=1e-15)


def test_row_norms_are_numpys_bit_for_bit():
    rng = np.random.default_rng(5)
    x = np.vstack([rng.normal(size=(5000, 3)) * 10.0 ** rng.integers(-8, 8, (5000, 1)), np.zeros((1, 3)),
                   [[np.inf, 0, 1]], [[3.0, 4.0, 0.0]]])
    ours = row_norms(x)
    assert np.array_equal(ours, np.linalg.norm(x, axis=1)) and ours[-1] == 5.0 and ours[-3] == 0.0


@pytest.mark.parametrize("turn, folded", [(179.0, True), (FOLD_DEG + 0.01, True), (FOLD_DEG - 0.01, False), (90.0, False)])
def test_the_fold_test(turn, folded):
    """Face 1 = face 0 turned by ``turn`` degrees about their edge: a fold beyond 150 degrees."""
    a = np.radians(180.0 - turn)                         # dihedral opening between the faces
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, np.cos(a), np.sin(a)]])
    f = np.array([[0, 1, 2], [1, 0, 3]])
    cos = float(np.dot(*face_normals(v, f)))
    np.testing.assert_allclose(cos, np.cos(np.radians(turn)), atol=1e-12)
    assert folded_edges(v, f).tolist() == ([0] if folded else [])
    assert FOLD_DEG == 150.0 and FOLD_COS == np.cos(np.radians(150.0))


def test_fold_test_on_a_cube_and_a_subset():
    cube = trimesh.creation.box()
    pairs = edge_face_pairs(cube.faces)
    assert len(folded_edges(cube.vertices, cube.faces, pairs)) == 0
    v = cube.vertices.copy()
    v[np.argmax(v.sum(axis=1))] = [-0.4, -0.4, -0.4]     # a corner pushed through to the inside
    bad = folded_edges(v, cube.faces, pairs)
    assert len(bad) > 0
    assert folded_edges(v, cube.faces, pairs, bad[::-1]).tolist() == bad[::-1].tolist()
    assert folded_edges(v, cube.faces, pairs, np.setdiff1d(np.arange(18), bad)).tolist() == []


def test_edge_length_graph():
    g, e = edge_length_graph(TET_V, TET_F)
    assert len(e) == 6 and g.shape == (4, 4) and g.nnz == 12 and (g != g.T).nnz == 0
    assert g[1, 2] == pytest.approx(np.sqrt(2)) and g[0, 3] == pytest.approx(1.0)


def test_averaging_operators():
    x = np.arange(12.0).reshape(4, 3) ** 2
    S = ring_operator(TET_F, 5)                          # vertex 4 is isolated
    assert S.shape == (5, 5) and S.nnz == 4 * 4 + 1 and (S.data == 1).all()
    x5 = np.vstack([x, [[7.0, 7, 7]]])
    mean = neighbour_mean(S, x5)
    np.testing.assert_allclose(mean[0], x[1:].mean(axis=0), rtol=1e-15)
    assert mean[4].tolist() == [0, 0, 0]
    R = ring_average(TET_F, 5)
    np.testing.assert_allclose(np.asarray(R.sum(axis=1)).ravel(), 1.0, rtol=1e-15)
    np.testing.assert_allclose(R @ x5, np.vstack([np.tile(x.mean(axis=0), (4, 1)), [[7, 7, 7]]]), rtol=1e-15)


def test_smooth_vertex_normals_weld_seams_and_are_unit():
    import trimesh

    from nodes.common.meshops import smooth_vertex_normals, vertex_normals

    ball = trimesh.creation.icosphere(2)
    v, f = np.asarray(ball.vertices), np.asarray(ball.faces)
    # split the vertices of half the faces (a texture seam): the copies keep the welded mesh's normals
    split = f.copy()
    half = np.arange(len(f)) < len(f) // 2
    split[half] += len(v)
    v2 = np.vstack([v, v, [[5.0, 5.0, 5.0]]])                  # and one unused vertex
    n = smooth_vertex_normals(v2, split)
    np.testing.assert_allclose(n[:len(v)], vertex_normals(v, f), atol=1e-12)
    np.testing.assert_allclose(n[len(v):2 * len(v)], vertex_normals(v, f), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1)
    assert n[-1].tolist() == [0.0, 0.0, 1.0]


def test_weld_coincident_is_numpy_unique_of_the_rows():
    from nodes.common.meshops import weld_coincident

    rng = np.random.default_rng(3)
    p = rng.integers(0, 4, (500, 3)).astype(np.float64) / 2        # many exact repeats and ties per column
    p[::7] = rng.normal(size=(len(p[::7]), 3))
    p[5] = [-0.0, 1.0, 0.0]                                          # -0 and +0 are one coordinate
    p[6] = [0.0, 1.0, -0.0]
    for pts in (p, p.astype(np.float32), p[:1]):
        rows, inverse = weld_coincident(pts)
        ref_rows, ref_inverse = np.unique(pts, axis=0, return_inverse=True)
        np.testing.assert_array_equal(rows, ref_rows)
        np.testing.assert_array_equal(inverse, ref_inverse.reshape(-1))
        assert inverse.dtype == np.int64
    assert weld_coincident(p)[1][5] == weld_coincident(p)[1][6]

"""Mesh operations shared by stages (the one mesh core: every stage calls these, none keeps a copy).

    topology     unique_edges, edge_faces / edge_face_pairs (edge -> faces), face_neighbours, vertex_faces (CSR)
                 and padded_rows, vertex_neighbours (CSR), component_sizes / drop_small_components /
                 largest_component
    geometry     face_normals, face_areas, vertex_normals (area-weighted), weld_coincident, smooth_vertex_normals
                 (welded, for shading: what the exports write), edge_length_graph
    folds        FOLD_DEG / FOLD_COS (faces turned more than 150 degrees), folded_edges
    averaging    ring_operator (I + A), ring_average (row-normalised I + A), neighbour_mean (uniform Laplacian), ring_degree
    refinement   split_edges (conforming edge splits)

Arrays in, arrays out (NumPy; float64 geometry, int64 indices unless a kernel needs int32: the CSR tables).

Conforming edge splits: chosen edges get a new vertex, and every face adapts so the mesh stays crack-free
(no T-junctions) and keeps its orientation ("red-green" refinement). A face with one split edge becomes two
triangles, with two split edges three, with all three the four of a 1-to-4 split.

    edges, face_edges = unique_edges(faces)                    # (E, 2) vertex pairs, (F, 3) edge per face side
    v2, f2 = split_edges(vertices, faces, edges, face_edges, split, points)
    pairs = edge_face_pairs(faces)                             # interior edges and their two faces
    bad = folded_edges(vertices, faces, pairs)                 # indices into pairs[0]
"""
from __future__ import annotations

import numpy as np

FOLD_DEG = 150.0                                   # an edge is folded when its faces turn more than this
FOLD_COS = float(np.cos(np.radians(FOLD_DEG)))     # -0.8660254037844387: unit normals' dot product below it


def unique_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(edges (E, 2) sorted vertex pairs, face_edges (F, 3)): side k of face i runs from faces[i, k] to
    faces[i, (k + 1) % 3] and is edge face_edges[i, k]."""
    edges, inverse, _ = _sorted_sides(faces)
    return edges, inverse.reshape(-1, 3)


def _sorted_sides(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``unique_edges``' edges, the edge of each side (3 F,: side k of face i at 3 i + k) and the sides in the
    order of their edges (ties in no particular order)."""
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    a, b = faces.ravel(), faces[:, [1, 2, 0]].ravel()         # side k of face i: row 3 i + k
    lo, hi = np.minimum(a, b), np.maximum(a, b)                 # np.sort(sides, axis=1), 20x faster
    n = int(faces.max(initial=0)) + 1
    keys = lo * n + hi
    order = np.argsort(keys)  # np.unique(keys, return_inverse=True), several times faster here
    first = np.ones(len(keys), bool)       # (no faces: no edges)
    first[1:] = keys[order][1:] != keys[order][:-1]
    inverse = np.empty(len(keys), np.int64)
    inverse[order] = np.cumsum(first) - 1
    keys = keys[order][first]
    return np.stack([keys // n, keys % n], axis=1), inverse, order


def edge_faces(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Edge -> face adjacency.

    Returns
    -------
    edges (E, 2), face_edges (F, 3) as ``unique_edges``; faces (E, 2): the first two faces of each edge in
    increasing order, -1 where it has fewer; count (E,): faces per edge (1 border, 2 interior, > 2 non-manifold).
    """
    edges, flat, order = _sorted_sides(faces)
    count = np.bincount(flat, minlength=len(edges))
    start = np.cumsum(count) - count
    # each edge's sides in increasing order (np.argsort(flat, kind="stable"), 2x the time): the sort by key left
    # the two sides of an interior edge in either order, and the rare edges of three or more sides are sorted
    two = np.flatnonzero(count == 2)
    first, second = order[start[two]], order[start[two] + 1]
    order[start[two]], order[start[two] + 1] = np.minimum(first, second), np.maximum(first, second)
    many = np.flatnonzero(count > 2)
    if len(many):
        c = count[many]
        at = np.repeat(start[many] - (np.cumsum(c) - c), c) + np.arange(int(c.sum()))   # their sides' slots
        order[at] = order[at][np.lexsort((order[at], flat[order[at]]))]
    pair = np.full((len(edges), 2), -1, np.int64)
    pair[:, 0] = order[start] // 3
    two = count >= 2
    pair[two, 1] = order[start[two] + 1] // 3
    return edges, flat.reshape(-1, 3), pair, count


def edge_face_pairs(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(edges (M, 2), their two faces (M, 2)) of the interior edges: those exactly two faces share."""
    edges, _, pair, count = edge_faces(faces)
    two = count == 2
    return edges[two], pair[two]


def face_neighbours(faces: np.ndarray) -> np.ndarray:
    """(F, 3): the face across side k of each face (side k runs from corner k to corner k + 1), -1 on a border
    or a non-manifold edge."""
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    _, fe, pair, count = edge_faces(faces)
    own = np.arange(len(faces))[:, None]
    a, b = pair[fe, 0], pair[fe, 1]
    return np.where(count[fe] == 2, np.where(a == own, b, a), -1)


def vertex_faces(faces: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertex -> faces in CSR form: (off (count + 1,) int32, idx int32), each vertex's faces in increasing order
    (a face twice where it uses the vertex twice)."""
    flat = np.asarray(faces, np.int64).reshape(-1)
    order = np.argsort(flat, kind="stable")
    off = np.zeros(count + 1, np.int64)
    off[1:] = np.cumsum(np.bincount(flat, minlength=count))
    return off.astype(np.int32), (order // 3).astype(np.int32)


def padded_rows(off: np.ndarray, idx: np.ndarray, fill: int = -1) -> np.ndarray:
    """A CSR table as a (rows, M) int64 array, M the longest row (at least 1), short rows padded with ``fill``."""
    counts = np.diff(np.asarray(off, np.int64))
    out = np.full((len(counts), max(int(counts.max(initial=0)), 1)), fill, np.int64)
    row = np.repeat(np.arange(len(counts)), counts)
    out[row, np.arange(len(row)) - np.asarray(off, np.int64)[row]] = idx
    return out


def _face_cross(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(b - a) x (c - a) per face as three (F,) rows: np.cross's formula on contiguous rows (1.5x faster)."""
    vt = np.ascontiguousarray(v.T)
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    e1 = [vt[k][b] - vt[k][a] for k in range(3)]
    e2 = [vt[k][c] - vt[k][a] for k in range(3)]
    return (e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0])


def row_norms(x: np.ndarray) -> np.ndarray:
    """Lengths of the rows of an (N, 3) array: ``np.linalg.norm(x, axis=1)``'s values bit for bit (the same sum,
    x0^2 + x1^2 then + x2^2), 5-6x faster (NumPy reduces along a length-3 axis slowly)."""
    x = np.asarray(x, np.float64)
    q = x * x
    return np.sqrt(q[:, 0] + q[:, 1] + q[:, 2])


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit face normals (F, 3) float64, right-handed in the corner order; zero for a degenerate face."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    n = np.stack(_face_cross(v, f), axis=1)
    length = row_norms(n)[:, None]
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas (F,) float64 (half the cross product's length)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) float64 (the sum of the faces' cross products); zero for an
    unused vertex."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    fn = _face_cross(v, f)
    n = np.zeros_like(v)
    for a in range(3):
        for c in range(3):
            n[:, a] += np.bincount(f[:, c], fn[a], minlength=len(v))
    norm = row_norms(n)[:, None]
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def weld_coincident(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unique rows in lexicographic order, (N,) index of each point's row): ``np.unique(points, axis=0,
    return_inverse=True)``'s result, by a lexsort of the columns and a comparison of neighbours (4x faster on
    14k points than its sort of the rows as one structured type)."""
    p = np.asarray(points)
    order = np.lexsort(p.T[::-1])
    rows = p[order]
    new = np.ones(len(p), bool)
    np.any(rows[1:] != rows[:-1], axis=1, out=new[1:])
    inverse = np.empty(len(p), np.int64)
    inverse[order] = np.cumsum(new) - 1
    return rows[new], inverse


def smooth_vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals (V, 3) for shading: ``vertex_normals`` of the mesh with coincident vertices
    welded (a texture atlas splits vertices at chart borders; welded, both copies get one normal and the seam
    does not show in the shading); a vertex of no face area gets +Z, so every normal has unit length.

    Parameters
    ----------
    vertices : (V, 3) positions.  faces : (F, 3) vertex indices.
    """
    v = np.asarray(vertices, np.float64)
    if not len(v):
        return np.zeros((0, 3))
    welded, inverse = weld_coincident(v)
    n = vertex_normals(welded, inverse[np.asarray(faces, np.int64).reshape(-1, 3)])[inverse]
    n[np.linalg.norm(n, axis=1) == 0] = (0.0, 0.0, 1.0)
    return n


def folded_edges(vertices: np.ndarray, faces: np.ndarray, pairs=None, which: np.ndarray | None = None) -> np.ndarray:
    """The fold test: edges whose two faces' unit normals are more than FOLD_DEG (150) degrees apart.

    Parameters
    ----------
    pairs : (edges, faces of each edge) as ``edge_face_pairs(faces)`` (made when None)
    which : edge indices into ``pairs`` to test (all when None)

    Returns
    -------
    Indices into ``pairs``' edges of the folded ones, increasing (in ``which``'s order when given).
    """
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    _, pair = edge_face_pairs(f) if pairs is None else pairs
    if which is None:
        which, need = np.arange(len(pair)), slice(None)
    else:
        which = np.asarray(which, np.int64)
        need = np.unique(pair[which].ravel())
    n = np.zeros((len(f), 3))
    n[need] = face_normals(vertices, f[need])
    return which[np.einsum("ij,ij->i", n[pair[which, 0]], n[pair[which, 1]]) < FOLD_COS]


def edge_length_graph(vertices: np.ndarray, faces: np.ndarray):
    """(symmetric sparse (V, V) CSR of the mesh edges weighted by length (+ 1e-12: no edge drops out), edges)."""
    from scipy.sparse import coo_matrix

    e, _ = unique_edges(faces)
    v = np.asarray(vertices, np.float64)
    w = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1) + 1e-12
    n = len(v)
    return coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr(), e


def ring_operator(faces: np.ndarray, count: int):
    """Sparse (count, count) CSR I + A: each vertex and its one-ring (the edges' neighbours), all ones."""
    from scipy.sparse import coo_matrix, identity

    e, _ = unique_edges(faces)
    A = coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(count, count))
    return (A + identity(count)).tocsr()


def ring_average(faces: np.ndarray, count: int):
    """Row-normalised ``ring_operator``: (S @ x)[i] is the mean of x over vertex i and its neighbours."""
    from scipy.sparse import csr_matrix

    S = ring_operator(faces, count)
    return csr_matrix(S.multiply(1.0 / np.asarray(S.sum(axis=1)).ravel()[:, None]))


def ring_degree(S) -> np.ndarray:
    """Per vertex the number of its neighbours (at least 1), given S = ``ring_operator``: what ``neighbour_mean``
    divides by (computed once for a loop of steps on one mesh)."""
    return np.maximum(np.asarray(S.sum(axis=1)).ravel() - 1.0, 1.0)


def neighbour_mean(S, x: np.ndarray, degree: np.ndarray | None = None) -> np.ndarray:
    """Umbrella (uniform Laplacian) mean: per vertex the mean of x over its neighbours, given S = ``ring_operator``
    (and its ``ring_degree``, made when None); an isolated vertex gets 0. ``neighbour_mean(S, x) - x`` is the
    umbrella step."""
    degree = ring_degree(S) if degree is None else degree
    return (S @ x - x) / degree[:, None]


def split_edges(vertices, faces, edges, face_edges, split, points) -> tuple[np.ndarray, np.ndarray]:
    """Split the edges where ``split`` (E,) is True, placing each new vertex at ``points`` (E, 3) of its edge.

    Returns (vertices (V + S, 3), faces): old vertices first, then one vertex per split edge in edge order.
    Each new triangle keeps its parent's winding."""
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    split = np.asarray(split, bool)
    new_index = np.full(len(edges), -1, np.int64)
    new_index[split] = len(vertices) + np.arange(int(split.sum()))
    out_vertices = np.vstack([vertices, np.asarray(points, np.float64)[split]])

    s = split[face_edges]
    count = s.sum(axis=1)
    out = [faces[count == 0]]
    for c in (1, 2):
        sel = np.flatnonzero(count == c)
        # rotate each face so that side 0 is the split side (one split) or the unsplit side (two splits)
        first = np.argmax(s[sel], axis=1) if c == 1 else np.argmin(s[sel], axis=1)
        order = (first[:, None] + np.arange(3)) % 3
        rows = np.arange(len(sel))[:, None]
        a, b, d = faces[sel][rows, order].T
        mid = new_index[face_edges[sel][rows, order]]
        if c == 1:
            m = mid[:, 0]
            out += [np.stack([a, m, d], 1), np.stack([m, b, d], 1)]
        else:  # sides 1 (b-d, midpoint m1) and 2 (d-a, midpoint m2) are split
            m1, m2 = mid[:, 1], mid[:, 2]
            out += [np.stack([d, m2, m1], 1), np.stack([a, b, m1], 1), np.stack([a, m1, m2], 1)]
    sel = np.flatnonzero(count == 3)
    a, b, d = faces[sel].T
    m0, m1, m2 = new_index[face_edges[sel]].T
    out += [np.stack([a, m0, m2], 1), np.stack([m0, b, m1], 1), np.stack([m2, m1, d], 1), np.stack([m0, m1, m2], 1)]
    return out_vertices, np.vstack(out)


def vertex_neighbours(faces: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Umbrella neighbourhoods in CSR form: (offsets (count + 1,) int32, neighbours int32), each edge once
    per direction, neighbours of a vertex in increasing order."""
    e, _ = unique_edges(faces)
    keys = np.sort(np.concatenate([e[:, 0] * count + e[:, 1], e[:, 1] * count + e[:, 0]]))  # (from, to) in order
    both = np.stack([keys // count, keys % count], axis=1)
    offsets = np.zeros(count + 1, np.int64)
    np.add.at(offsets, both[:, 0] + 1, 1)
    return np.cumsum(offsets).astype(np.int32), both[:, 1].astype(np.int32)


def component_sizes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(component label per face, face count per label) of the components connected through shared vertices."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces)
    n = len(vertices)
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    _, label = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False)
    face_label = label[faces[:, 0]]
    return face_label, np.bincount(face_label)


def _keep_faces(vertices, faces, keep) -> tuple[np.ndarray, np.ndarray]:
    used = np.zeros(len(vertices), bool)
    used[faces[keep].ravel()] = True
    remap = np.cumsum(used) - 1
    return vertices[used], remap[faces[keep]]


def drop_small_components(vertices: np.ndarray, faces: np.ndarray, min_fraction: float):
    """Keep the components (connected through shared vertices) with at least ``min_fraction`` of the largest
    one's faces (1.0: the largest only); drop unused vertices. Returns (vertices, faces, face counts of the
    components kept, face counts of those dropped), counts largest first."""
    if len(faces) == 0:
        return vertices, faces, np.zeros(0, np.int64), np.zeros(0, np.int64)
    face_label, counts = component_sizes(vertices, faces)
    big = counts.max()
    keep_label = counts >= min_fraction * big
    if min_fraction >= 1.0:  # exactly one, also when two components tie
        keep_label = np.zeros(len(counts), bool)
        keep_label[counts.argmax()] = True
    v, f = _keep_faces(vertices, faces, keep_label[face_label])
    return v, f, np.sort(counts[keep_label])[::-1], np.sort(counts[~keep_label & (counts > 0)])[::-1]


def largest_component(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the connected component (through shared vertices) with the most faces; drop unused vertices."""
    if len(faces) == 0:
        return vertices, faces
    v, f, _, _ = drop_small_components(vertices, faces, 1.0)
    return v, f


def carried_vertex_colors(mesh, vertices: np.ndarray) -> np.ndarray | None:
    """Vertex colours of ``mesh`` (None when it has none) for ``vertices`` of a mesh made from it: the same
    colours when it has the same vertices (moved or not: refine and relax keep mc's connectivity), else the
    colour of the nearest vertex of ``mesh`` (subdivided or decimated meshes)."""
    if getattr(mesh.visual, "kind", None) != "vertex" or len(mesh.vertices) == 0:
        return None
    old = np.asarray(mesh.visual.vertex_colors)
    vertices = np.asarray(vertices, np.float64)
    if len(vertices) == len(old):
        return old
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(np.asarray(mesh.vertices)).query(vertices)
    return old[nearest]

"""Triangle budget and fold repair for refine (host-side mesh operations, NumPy).

``meet_budget``: more faces by conforming edge splits (nodes.common.meshops.split_edges), the edges with the
largest chord error first (length times the angle between their ends' normals, plus a share of the length: flat
regions are split last), fewer faces by quadric decimation (fast-simplification, Garland & Heckbert), after which
the duplicate triangles it sometimes leaves (two faces on the same three vertices: a zero-volume flap that makes
their edges non-manifold) are dropped.

``repair_folds``: edge flips at folded edges (two faces more than 150 degrees apart, eval.mesh's fold): the
quadrilateral of the two faces gets its other diagonal when that leaves no fold between the new faces and no
duplicate edge; otherwise the edge collapses to its midpoint when that keeps the mesh manifold. The fairing's
unfold steps (fairing.cl) repair most folds by moving vertices; a fold they leave (a flipped triangle between
long edges after decimation, a crumpled cluster of small ones) is repaired here.
"""
from __future__ import annotations

import numpy as np

from nodes.common.meshops import edge_faces, face_normals, folded_edges, split_edges, unique_edges, vertex_normals


def folded(v: np.ndarray, f: np.ndarray):
    """Indices of the folded edges (nodes.common.meshops.folded_edges) into the whole edge table, and that table
    (edges, face_edges, faces of each edge, faces per edge: nodes.common.meshops.edge_faces)."""
    table = edge_faces(f)
    two = np.flatnonzero(table[3] == 2)
    return two[folded_edges(v, f, (table[0][two], table[2][two]))], table


def repair_folds(vertices, faces, rounds: int = 6) -> tuple[np.ndarray, np.ndarray, int]:
    """Folded edges flipped where that removes the fold, else collapsed to their midpoint when the two ends share
    no neighbour but the two opposite corners (the link condition: the mesh stays manifold); see the module
    docstring. Returns (vertices, faces, folded edges left); vertices are dropped only where an edge collapsed."""
    v = np.asarray(vertices, np.float64).copy()
    f = np.asarray(faces, np.int64).copy()
    keep = np.ones(len(f), bool)
    gone = np.zeros(len(v), bool)
    left = None
    for _ in range(rounds):
        f = f[keep]
        keep = np.ones(len(f), bool)
        bad, (edges, fe, pair, _) = folded(v, f)
        if not len(bad):
            left = 0                     # the faces as they stand were just tested
            break
        used, touched = set(), set()
        # the round's edges, looked up by their sorted-pair code (the table lists them in that order; a set of
        # 54k tuples took 87 ms of a 0.19 s repair on a pose2sim frame), and the diagonals flipped in since
        codes, added = edges[:, 0] * len(v) + edges[:, 1], set()

        def have(p, q):
            k = int(min(p, q)) * len(v) + int(max(p, q))
            i = int(np.searchsorted(codes, k))
            return k in added or (i < len(codes) and int(codes[i]) == k)

        changed = 0
        for e in bad:
            fa, fb = pair[e]
            a, b = (int(x) for x in edges[e])
            if fa in used or fb in used or a in touched or b in touched:
                continue
            ta, tb = f[fa], f[fb]
            ka = int(np.flatnonzero((ta != a) & (ta != b))[0])  # side k of face fa runs x -> y, c opposite
            x, y, c = ta[(ka + 1) % 3], ta[(ka + 2) % 3], ta[ka]
            d = tb[np.flatnonzero((tb != a) & (tb != b))[0]]
            if c != d and not have(c, d):
                new = np.array([[c, x, d], [d, y, c]])
                n = face_normals(v, new)
                if np.dot(n[0], n[1]) >= 0.5:
                    f[fa], f[fb] = new
                    added.add(int(min(c, d)) * len(v) + int(max(c, d)))
                    used.update((fa, fb))
                    changed += 1
                    continue
            ring_a = set(f[(f == a).any(axis=1)].ravel().tolist()) - {a}
            ring_b = set(f[(f == b).any(axis=1)].ravel().tolist()) - {b}
            if ring_a & ring_b != {int(c), int(d)}:
                continue
            v[a] = 0.5 * (v[a] + v[b])
            f[f == b] = a
            keep[[fa, fb]] = False
            gone[b] = True
            used.update((fa, fb))
            touched.update(ring_a | ring_b | {a, b})
            changed += 1
        if not changed:
            break
    f = f[keep]
    if left is None:
        left = len(folded(v, f)[0])
    if gone.any():
        index = np.cumsum(~gone) - 1
        v, f = v[~gone], index[f]
    return v, f, left


def drop_duplicate_faces(faces: np.ndarray) -> np.ndarray:
    """Faces without the triangles that share their three vertices with another (both copies go)."""
    f = np.asarray(faces, np.int64)
    key = np.sort(f, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return f[counts[inverse.ravel()] == 1]


def split_scores(v: np.ndarray, f: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Chord error estimate per edge: length x (angle between its ends' normals + 0.15 rad)."""
    n = vertex_normals(v, f)
    cos = np.clip(np.einsum("ij,ij->i", n[edges[:, 0]], n[edges[:, 1]]), -1, 1)
    return np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1) * (np.arccos(cos) + 0.15)


def meet_budget(vertices, faces, target: int) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) with about ``target`` faces: edges split (largest chord error first) while below it,
    quadric decimation (fast-simplification) down to it. Vertices land near, not on, the hull: the quality steps
    that follow put them back."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if target <= 0 or len(f) == 0:
        return v, f
    while len(f) < target:
        edges, fe = unique_edges(f)
        k = (target - len(f) + 1) // 2  # each split edge adds two faces
        split = np.ones(len(edges), bool)
        if k < len(edges):
            split[:] = False
            split[np.argsort(-split_scores(v, f, edges), kind="stable")[:k]] = True
        v, f = split_edges(v, f, edges, fe, split, v[edges].mean(axis=1))
    if len(f) > target:
        import fast_simplification

        v, f = fast_simplification.simplify(v, f, target_count=int(target))
        f = drop_duplicate_faces(f)
    return np.asarray(v, np.float64), np.asarray(f, np.int64)

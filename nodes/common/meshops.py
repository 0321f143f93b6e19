"""Mesh operations shared by stages: unique edges, conforming edge splits, vertex neighbourhoods (CSR),
connected components (the largest, or all but the small ones).

Conforming edge splits: chosen edges get a new vertex, and every face adapts so the mesh stays crack-free
(no T-junctions) and keeps its orientation ("red-green" refinement). A face with one split edge becomes two
triangles, with two split edges three, with all three the four of a 1-to-4 split.

    edges, face_edges = unique_edges(faces)                    # (E, 2) vertex pairs, (F, 3) edge per face side
    v2, f2 = split_edges(vertices, faces, edges, face_edges, split, points)
"""
from __future__ import annotations

import numpy as np


def unique_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(edges (E, 2) sorted vertex pairs, face_edges (F, 3)): side k of face i runs from faces[i, k] to
    faces[i, (k + 1) % 3] and is edge face_edges[i, k]."""
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    sides = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1).reshape(-1, 2)
    sides = np.sort(sides, axis=1)
    n = int(faces.max(initial=0)) + 1
    keys = sides[:, 0] * n + sides[:, 1]
    order = np.argsort(keys)  # np.unique(keys, return_inverse=True), several times faster here
    first = np.ones(len(keys), bool)       # (no faces: no edges)
    first[1:] = keys[order][1:] != keys[order][:-1]
    inverse = np.empty(len(keys), np.int64)
    inverse[order] = np.cumsum(first) - 1
    keys = keys[order][first]
    return np.stack([keys // n, keys % n], axis=1), inverse.reshape(-1, 3)


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
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.sort(e, axis=1)
    keys = np.sort(np.concatenate([e[:, 0] * count + e[:, 1], e[:, 1] * count + e[:, 0]]))  # (from, to) in order
    keys = keys[np.r_[True, keys[1:] != keys[:-1]][: len(keys)]]      # (no faces: no keys)
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

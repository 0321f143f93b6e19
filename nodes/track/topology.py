"""Topology of a triangle mesh and the class of a mesh sequence (seed chapter 8.4, Table 8.1, after Arcila 2011):

    number of vertices  connectivity  topology   name
    constant            constant      constant   dynamic mesh
    variable            variable      constant   stable mesh sequence
    variable            variable      variable   unconstrained mesh sequence

Topology is read from the Euler characteristic: per surface V - E + F = 2c - 2g - b (c connected components,
g genus = handles, b boundary loops), counted over the whole mesh.

    topo = mesh_topology(vertices, faces)                   # {"vertices", "faces", "components", "genus", ...}
    ranges = classify_sequence([(v, f), ...])               # [{"start", "stop", "class"}, ...] (indices)
"""
from __future__ import annotations

import numpy as np

from nodes.common.meshops import component_sizes, edge_faces

DYNAMIC, STABLE, UNCONSTRAINED = "dynamic mesh", "stable mesh sequence", "unconstrained mesh sequence"
CLASSES = (DYNAMIC, STABLE, UNCONSTRAINED)


def _boundary_loops(border: np.ndarray) -> int:
    """Boundary loops: the cycles the border edges (B, 2) form (components of their graph)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(border) == 0:
        return 0
    verts, inv = np.unique(border.ravel(), return_inverse=True)
    inv = inv.reshape(-1, 2)
    m = len(verts)
    k, _ = connected_components(coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(m, m)), directed=False)
    return int(k)


def mesh_topology(vertices, faces) -> dict:
    """Counts that decide a mesh's topology: vertices, faces, edges, components, boundary loops, Euler
    characteristic, genus (handles per surface, summed), and whether it is closed (watertight)."""
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    n = len(np.asarray(vertices).reshape(-1, 3))
    if len(faces) == 0:
        return {"vertices": n, "faces": 0, "edges": 0, "components": 0, "boundary_loops": 0, "euler": 0, "genus": 0,
                "closed": False}
    edges, _, _, count = edge_faces(faces)
    used = int(np.count_nonzero(np.bincount(faces.ravel(), minlength=n)))
    c = int(np.count_nonzero(component_sizes(np.asarray(vertices).reshape(-1, 3), faces)[1]))
    border = edges[count == 1]
    b = _boundary_loops(border)
    chi = used - len(edges) + len(faces)
    genus = max(0, (2 * c - b - chi) // 2)
    return {"vertices": n, "faces": int(len(faces)), "edges": int(len(edges)), "components": c, "boundary_loops": b,
            "euler": int(chi), "genus": int(genus), "closed": len(border) == 0}


def same_connectivity(a_vertices, a_faces, b_vertices, b_faces) -> bool:
    """Same vertex count and the same face array (vertex i is the same point of the surface in both)."""
    return (len(a_vertices) == len(b_vertices) and np.shape(a_faces) == np.shape(b_faces)
            and bool(np.array_equal(a_faces, b_faces)))


def _same_topology(a: dict, b: dict) -> bool:
    keys = ("components", "genus", "boundary_loops")
    return all(a[k] == b[k] for k in keys) and a["faces"] > 0 and b["faces"] > 0


def classify_sequence(meshes: list[tuple[np.ndarray, np.ndarray]], topologies: list[dict] | None = None) -> list[dict]:
    """Frame ranges (indices into ``meshes``, stop inclusive) with their Table 8.1 class.

    The sequence is cut where the topology changes; a piece of one topology is cut where the connectivity
    changes; runs of >= 2 frames with one connectivity are dynamic meshes, the rest of a piece of >= 2 frames a
    stable mesh sequence, and runs of frames whose topology differs from both neighbours are unconstrained."""
    if topologies is None:
        topologies = [mesh_topology(v, f) for v, f in meshes]
    n = len(meshes)
    if n == 0:
        return []
    same_topo = [_same_topology(topologies[i], topologies[i + 1]) for i in range(n - 1)]
    same_conn = [same_topo[i] and same_connectivity(*meshes[i], *meshes[i + 1]) for i in range(n - 1)]
    labels = []                                # class per frame
    start = 0
    pieces = []
    for i in range(n):
        if i == n - 1 or not same_topo[i]:
            pieces.append((start, i))
            start = i + 1
    for a, b in pieces:
        if a == b:
            labels.append(UNCONSTRAINED)
            continue
        run_start = a
        for i in range(a, b + 1):
            if i == b or not same_conn[i]:
                labels += [DYNAMIC if i > run_start else STABLE] * (i - run_start + 1)
                run_start = i + 1
    ranges = []
    for i, label in enumerate(labels):
        prev = ranges[-1]["class"] if ranges else None
        joined = prev == label and (label == UNCONSTRAINED or (label == STABLE and same_topo[i - 1])
                                    or (label == DYNAMIC and same_conn[i - 1]))
        if joined:
            ranges[-1]["stop"] = i
        else:
            ranges.append({"start": i, "stop": i, "class": label})
    return ranges


def sequence_class(meshes: list[tuple[np.ndarray, np.ndarray]], topologies: list[dict] | None = None) -> str:
    """The class of the whole sequence: one connectivity -> dynamic mesh, one topology -> stable, else
    unconstrained."""
    if topologies is None:
        topologies = [mesh_topology(v, f) for v, f in meshes]
    pairs = range(len(meshes) - 1)
    if not all(_same_topology(topologies[i], topologies[i + 1]) for i in pairs):
        return UNCONSTRAINED if len(meshes) > 1 else DYNAMIC
    if all(same_connectivity(*meshes[i], *meshes[i + 1]) for i in pairs):
        return DYNAMIC
    return STABLE

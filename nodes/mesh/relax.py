"""Relaxation that removes the pixel and voxel aliasing without leaving the silhouettes.

The refined mesh lies on the exact visual hull of the masks, and that hull carries the masks' pixel
staircase (horizontal stair streaks in a shaded render) and the grid's triangulation. The true surface's
outline lies within half a pixel of the staircase, so the relaxation is free inside a *shell*: every view
may see the surface's outline up to ``outside_px`` pixels beyond the mask edge and ``inside_px`` pixels
within it (levels of the smooth silhouette field, nodes/mesh/hullfit.py). Inside the shell the mesh is faired
(nodes/mesh/fairing.py): face normals are smoothed first, vertices move towards the planes of their faces
with the smoothed normals and evenly along the surface. Every ``iterations`` steps make one round: each round
sets each vertex's line along its smoothed normal and searches the shell on it once on the device; the steps
then clamp each vertex to its line's shell interval (and at most ``across`` off it). Relax computes from its
inputs alone (no search handed over from refine in memory: a cached value must equal what the node computes).

With ``keep_silhouettes`` false the fairing runs free (no masks needed). Same topology.

    field = SilhouetteField.from_inputs(masks, cameras, origin)
    vertices, faces = relax_vertices(mesh.vertices, mesh.faces, field, rounds=1, iterations=8)
"""
from __future__ import annotations

import numpy as np

from .budget import repair_folds
from .fairing import CLOps, NumPyOps, fair
from .hullfit import RELAX_OUTSIDE_PX, FieldCL, SilhouetteField, level_of


def mean_edge_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Mean length of the faces' sides (each interior edge counted twice)."""
    if len(faces) == 0:
        return 0.0
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    return float(np.mean(np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2)))


def relax_vertices(vertices, faces, field: SilhouetteField | None = None, *, rounds: int = 1, iterations: int = 8,
                   filter_rounds: int = 2, lam_t: float = 0.5, inside_px: float = 0.0,
                   outside_px: float = RELAX_OUTSIDE_PX, steps: int = 8,
                   method: str = "opencl") -> tuple[np.ndarray, np.ndarray]:
    """(faired vertices (V, 3) float64, faces); with ``field`` kept in the shell between ``inside_px`` pixels
    within the masks' outline and ``outside_px`` beyond it. The vertices and faces are the input's unless a fold
    the fairing could not open had its edge flipped or collapsed (``budget.repair_folds``)."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(vertices) == 0 or len(faces) == 0 or rounds * iterations == 0:
        return vertices.copy(), faces
    shell = None if field is None else (level_of(inside_px), level_of(-outside_px))
    origin = field.origin if field is not None else vertices.mean(axis=0)
    edge = mean_edge_length(vertices, faces)
    p = (vertices - origin).astype(np.float32)
    if method == "opencl":
        ops = CLOps(p, faces, FieldCL.get().prepare(field) if field is not None else None)
    else:
        ops = NumPyOps(p, faces, field)
    out, _, folds = fair(ops, rounds=rounds, iterations=iterations, filter_rounds=filter_rounds, lam_t=lam_t,
                         shell=shell, reach=0.5 * edge, across=0.5 * edge, steps=steps)
    result = ops.read(out).astype(np.float64) + origin
    if folds:  # a fold the repair steps could not open: flip or collapse its edge
        result, faces, _ = repair_folds(result, faces)
    return result, faces

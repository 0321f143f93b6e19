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

from kernels import source
from nodegraph import Input, Node, NodeError, Param
from nodes.common.meshops import carried_vertex_colors
from nodes.common.silhouettes import POLICIES
from nodes.common.types import CameraSet, Masks, Mesh

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


# ---------------------------------------------------------------- node
class Relax(Node):
    """Fairing that keeps the silhouettes: normals smoothed first, then vertices moved towards their faces'
    smoothed planes and evenly along the surface, each step clamped to the shell where every view sees the
    outline within a fraction of a pixel of the mask edge (keep_silhouettes). Removes stair streaks and
    slivers; same topology."""

    type_name = "relax"
    version = 4
    inputs = {"mesh": Mesh,
              "masks": Input(Masks, optional=True, doc="silhouettes to stay within (keep_silhouettes)"),
              "cameras": Input(CameraSet, optional=True, doc="cameras of the masks (keep_silhouettes)")}
    outputs = {"mesh": Mesh}
    params = {
        "rounds": Param(int, 1, range=(0, 100), doc="rounds: the shell is searched along fresh normals once per round"),
        "iterations": Param(int, 8, range=(0, 100), doc="fairing steps per round"),
        "filter_rounds": Param(int, 2, range=(1, 20), doc="face-normal smoothing passes before each step"),
        "tangential": Param(float, 0.5, range=(0.0, 1.0), doc="tangential step towards the neighbours' mean (triangle quality)"),
        "keep_silhouettes": Param(bool, True, doc="keep the outline in every view within the shell (needs masks + cameras)"),
        "outside_px": Param(float, RELAX_OUTSIDE_PX, range=(0.0, 3.0), doc="how far beyond the mask edge the outline may go, pixels"),
        "inside_px": Param(float, 0.0, range=(-1.0, 3.0), doc="how far within the mask edge the outline may go, pixels "
                           "(negative: at least that far beyond)"),
        "steps": Param(int, 8, range=(1, 40), doc="regula falsi iterations of the shell search"),
        "min_views": Param(int, 0, range=(0, None), doc="hull vote: 0 = all views; k = at least k silhouettes"),
        "outside": Param(str, "carve", choices=POLICIES, doc="points projecting outside an image: carve, or ignore that view"),
        "use_alpha": Param(bool, True, doc="read soft alpha when the masks carry it"),
        "method": Param(str, "opencl", choices=("opencl", "numpy"), doc="OpenCL kernels or the NumPy reference"),
    }
    kernels = [source("hullfit.cl"), source("fairing.cl")]

    def run(self, mesh, masks=None, cameras=None, *, rounds, iterations, filter_rounds, tangential, keep_silhouettes,
            outside_px, inside_px, steps, min_views, outside, use_alpha, method):
        import trimesh

        if -inside_px > outside_px:
            raise NodeError(f"relax: the shell is empty (inside_px {inside_px} is beyond outside_px {outside_px})")
        field = None
        if keep_silhouettes:
            if masks is None or cameras is None:
                raise NodeError("relax: keep_silhouettes needs the 'masks' and 'cameras' inputs connected "
                                "(or set keep_silhouettes: false)")
            v = np.asarray(mesh.vertices, np.float64)
            origin = 0.5 * (v.min(axis=0) + v.max(axis=0)) if len(v) else np.zeros(3)
            field = SilhouetteField.from_inputs(masks, cameras, origin, min_views, outside, use_alpha, node="relax")
        out, faces = relax_vertices(mesh.vertices, mesh.faces, field, rounds=rounds, iterations=iterations,
                             filter_rounds=filter_rounds, lam_t=tangential, inside_px=inside_px,
                             outside_px=outside_px, steps=steps, method=method)
        return {"mesh": trimesh.Trimesh(out, faces, vertex_colors=carried_vertex_colors(mesh, out), process=False)}

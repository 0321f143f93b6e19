"""Exact visual-hull surface from a marching-cubes mesh: every vertex onto the hull along its grid edge, then a
few steps of tangential relaxation on the hull that even out the triangles.

Liang & Wong, "Exact visual hull from marching cubes" (VISAPP 2008). Marching cubes on an occupancy grid puts
every vertex on an edge between two neighbouring voxel centres, one inside and one outside; the hull surface
crosses that edge somewhere between them. The crossing is searched on the device view by view
(nodes/mesh/hullfit.py: the silhouettes read as a smooth B-spline field, the crossing of level 0.5 found by
regula falsi in the one view that cuts the edge first). Vertices whose edge disagrees with the point test
are searched for along their normal instead.

Vertices that slid along their edges leave slivers (a vertex near a lattice corner next to its neighbours)
and, where neighbours slid in opposite directions, folds. ``quality`` fairing steps (nodes/mesh/fairing.py:
normals smoothed first, then each vertex towards its faces' planes and the mean of its neighbours) even out
the triangles and open the folds; then every vertex goes back onto the exact hull along its smoothed normal
(the fairing's final clamp onto the hull's level), and fold repair steps follow where that left a fold (then
edge flips or collapses, nodes/mesh/budget.py). The searches visit, per vertex, only the views that may cut its neighbourhood (``hullfit.ball_cull``).
Same faces as the input by default; a triangle budget (``faces`` or ``edge_length``) splits the edges with the
largest chord error or decimates (quadric error metrics, fast-simplification) before the quality steps.

    field = SilhouetteField.from_inputs(masks, cameras, origin=volume centre)
    vertices, faces, stats = refine_vertices(mesh.vertices, mesh.faces, volume, field, steps=8, quality=6)
"""
from __future__ import annotations

import numpy as np

from nodes.common.meshops import face_areas

from .budget import meet_budget, repair_folds
from .fairing import CLOps, NumPyOps, fair, smoothed_normals
from .hullfit import (RELAX_OUTSIDE_PX, FieldCL, SilhouetteField, ball_cull, cross_reference, level_of,
                      onto_reference)

HULL = 0.5  # the field's level of the visual hull (the pixel-edge outline)


# ---------------------------------------------------------------- lattice edges
def lattice_edges(vertices: np.ndarray, volume) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The voxel-centre edge each vertex lies on: (inside end (V, 3), outside end (V, 3), ok (V,) bool).

    In voxel-centre lattice units g = (x - bbox_min) / voxel_size - 0.5 a marching-cubes vertex has two
    integer coordinates; the third (the one farthest from an integer) names the edge. ``ok`` is False where
    the vertex is not on an edge of this grid or both ends have the same occupancy (the vertex is kept)."""
    occ = np.asarray(volume.occupancy)
    occ = occ > 0.5 if occ.dtype.kind == "f" else occ > 0
    dims = np.array(occ.shape)
    g = (np.asarray(vertices, np.float64) - volume.bbox_min) / volume.voxel_size - 0.5
    frac = np.abs(g - np.round(g))
    axis = np.argmax(frac, axis=1)
    rows = np.arange(len(g))
    lo = np.round(g).astype(np.int64)
    lo[rows, axis] = np.floor(g[rows, axis]).astype(np.int64)
    hi = lo.copy()
    hi[rows, axis] += 1
    others = frac.copy()
    others[rows, axis] = 0
    ok = (others.max(axis=1, initial=0) < 1e-3) & np.all(lo >= 0, axis=1) & np.all(hi < dims, axis=1)
    lo_c, hi_c = np.clip(lo, 0, dims - 1), np.clip(hi, 0, dims - 1)
    occ_lo = occ[lo_c[:, 0], lo_c[:, 1], lo_c[:, 2]]
    occ_hi = occ[hi_c[:, 0], hi_c[:, 1], hi_c[:, 2]]
    ok &= occ_lo != occ_hi
    centre = lambda idx: volume.bbox_min + (idx + 0.5) * volume.voxel_size  # noqa: E731
    inside = np.where(occ_lo[:, None], centre(lo), centre(hi))
    outside = np.where(occ_lo[:, None], centre(hi), centre(lo))
    return inside, outside, ok


# ---------------------------------------------------------------- triangle budget
def target_face_count(vertices, faces, faces_param: int, edge_length: float) -> int:
    """The face count asked for: ``faces_param`` when > 0, else the count whose equilateral triangles of side
    ``edge_length`` cover the mesh's area when that is > 0, else the input's (0: keep)."""
    if faces_param > 0:
        return int(faces_param)
    if edge_length > 0 and len(faces):
        area = face_areas(vertices, faces).sum()
        return max(4, int(round(area / (np.sqrt(3) / 4 * edge_length ** 2))))
    return 0


# ---------------------------------------------------------------- work function
CULL_VOXELS = 1.6  # radius of each vertex's ball for view culling: its grid edge and its last search line lie in it


def refine_vertices(vertices, faces, volume, field: SilhouetteField, steps: int = 8, quality: int = 6,
                    lam_t: float = 0.5, method: str = "opencl", target_faces: int = 0,
                    relax_levels: tuple | None = (HULL, level_of(-RELAX_OUTSIDE_PX))):
    """Vertices onto the hull (Liang & Wong along grid edges, else along the normal within one voxel), then
    ``quality`` fairing steps and the projection back onto the hull. With ``target_faces`` > 0 the mesh is
    first brought to that many faces (``meet_budget``). Returns (vertices (V, 3) float64, faces, counts): the
    faces change with a budget, and when a fold the fairing could not open had its edge collapsed. The searches visit, per vertex, only the views that may see its
    neighbourhood cut (``ball_cull``). The last fairing clamps to the shell at ``relax_levels`` (relax's default
    levels)."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    stats = {"vertices": len(vertices), "on_edges": 0, "on_normals": 0, "folds_left": 0}
    if len(vertices) == 0:
        return vertices.copy(), faces, stats
    origin = field.origin
    voxel = float(np.max(volume.voxel_size))
    p = (vertices - origin).astype(np.float32)
    a, b, ok = lattice_edges(vertices, volume)
    a = np.where(ok[:, None], a - origin, p).astype(np.float32)  # not on an edge: an empty segment, no crossing
    b = np.where(ok[:, None], b - origin, p).astype(np.float32)
    cull = None
    if method == "opencl":
        fc = FieldCL.get().prepare(field)
        cull = fc.active(ball_cull(p, CULL_VOXELS * voxel))
        out, on = fc.cross_host(a, b, p, HULL, steps, cull)
        ops = CLOps(out, faces, fc)
    else:
        out, on = cross_reference(a, b, p, field, HULL, steps)
        ops = NumPyOps(out, faces, field)
    rest = np.flatnonzero(~on)
    found = np.zeros(0, bool)
    if len(rest) and len(faces):
        normals = ops.read(smoothed_normals(ops, ops.v, 1)[2])[rest]
        if method == "opencl":
            q, found = fc.onto_host(p[rest], normals, voxel, HULL, steps)
        else:
            q, found = onto_reference(p[rest], normals, voxel, field, HULL, steps)
        out[rest] = q
    stats.update(on_edges=int(on.sum()), on_normals=int(found.sum()))
    if target_faces > 0:
        v, faces = meet_budget(out.astype(np.float64), faces, target_faces)
        out = v.astype(np.float32)
        quality = max(quality, 1)
        if method == "opencl":
            cull = fc.active(ball_cull(out, CULL_VOXELS * voxel))
    if quality > 0 and len(faces):
        ops = CLOps(out, faces, fc, cull) if method == "opencl" else NumPyOps(out, faces, field)
        levels = relax_levels if relax_levels is not None else (HULL, HULL)
        v, _, folds = fair(ops, rounds=1, iterations=quality, filter_rounds=1, lam_t=lam_t, shell=levels,
                              reach=0.5 * voxel, steps=steps, clamp_steps=False, final="onto")
        out = ops.read(v)
        result = out.astype(np.float64) + origin
        if folds:  # a fold the repair steps could not open (after decimation): flip or collapse its edge
            result, faces, stats["folds_left"] = repair_folds(result, faces)
    else:
        result = out.astype(np.float64) + origin
    return result, faces, stats

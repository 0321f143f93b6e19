"""Mesh stage nodes: marching cubes, refinement onto the visual hull, relaxation (work in mc.py, refine.py, relax.py)."""
from __future__ import annotations

import numpy as np

from kernels import source
from nodegraph import Input, Node, NodeError, Param
from nodes.common.meshops import carried_vertex_colors, drop_small_components
from nodes.common.silhouettes import POLICIES
from nodes.common.types import CameraSet, Masks, Mesh, Volume

from .hullfit import RELAX_OUTSIDE_PX, SilhouetteField
from .mc import marching_cubes, marching_cubes_reference, vertex_colors
from .refine import refine_vertices, target_face_count
from .relax import relax_vertices


class MarchingCubes(Node):
    """Marching cubes: the volume's iso-surface at `level` as a watertight mesh with outward normals; a
    coloured volume (e.g. from carve) gives vertex colours."""

    type_name = "mc"
    version = 2
    inputs = {"volume": Volume}
    outputs = {"mesh": Mesh}
    params = {
        "level": Param(float, 0.5, doc="iso-value; a float (soft) volume places vertices between voxels"),
        "largest": Param(bool, False, doc="drop small disconnected parts (noise): keep the components with at least "
                                          "min_part of the largest one's faces; what is dropped is logged"),
        "min_part": Param(float, 0.01, range=(0.0, 1.0), doc="with largest: the smallest part kept, as a fraction of "
                                                             "the largest part's faces (1.0 = the largest only)"),
        "method": Param(str, "opencl", choices=("opencl", "numpy"), doc="OpenCL kernels or the NumPy reference"),
    }
    kernels = [source("mc.cl")]

    def run(self, volume, *, level, largest, method, min_part=0.01):
        occ = volume.occupancy
        if occ.ndim != 3 or min(occ.shape) < 1:
            raise NodeError(f"mc: volume occupancy must be a non-empty 3-D array, got shape {occ.shape}")
        if max(occ.shape) + 2 > 1 << 15:
            raise NodeError(f"mc: volume {occ.shape} is too large")
        import trimesh

        fn = marching_cubes if method == "opencl" else marching_cubes_reference
        verts, faces = fn(volume, level)
        if largest:
            verts, faces, kept, dropped = drop_small_components(verts, faces, min_part)
            if len(dropped):
                total = int(kept.sum() + dropped.sum())
                msg = (f"mc: dropped {len(dropped)} of {len(kept) + len(dropped)} parts smaller than {min_part:g} of the "
                       f"largest: {int(dropped.sum())} faces ({100 * dropped.sum() / total:.2g} % of the mesh; the biggest "
                       f"dropped part had {int(dropped[0])} faces, the largest kept {int(kept[0])}); kept {len(kept)}")
                # noise is a few specks; a visible share of the surface going away deserves a warning
                (self.log.warning if dropped.sum() > 0.01 * total else self.log.info)(msg)
        colors = None
        if getattr(volume, "colors", None) is not None and len(verts):
            if volume.colors.shape != (*occ.shape[:3], 3):
                raise NodeError(f"mc: volume colors have shape {volume.colors.shape}, expected {(*occ.shape[:3], 3)}")
            colors = vertex_colors(volume, verts, level)
        return {"mesh": trimesh.Trimesh(verts.astype(np.float64), faces.astype(np.int64), vertex_colors=colors,
                                        process=False)}


class Refine(Node):
    """Exact visual-hull surface (Liang & Wong 2008): every marching-cubes vertex moves along its grid edge to
    where the edge leaves the hull of the silhouettes (read as a smooth B-spline field, sub-pixel), then fairing
    steps even out the triangles and every vertex goes back onto the hull. Same faces as the input, or a
    triangle budget (faces or edge_length: edge splits by chord error, or quadric decimation; fold-free)."""

    type_name = "refine"
    version = 4
    inputs = {"mesh": Mesh, "volume": Volume, "masks": Masks, "cameras": CameraSet}
    outputs = {"mesh": Mesh}
    params = {
        "steps": Param(int, 8, range=(1, 40), doc="regula falsi iterations per crossing (each view)"),
        "quality": Param(int, 6, range=(0, 50), doc="fairing steps before the projection onto the hull; 0 = Liang & Wong alone"),
        "faces": Param(int, 0, range=(0, None), doc="triangle budget: about this many faces (0 = mc's faces)"),
        "edge_length": Param(float, 0.0, range=(0.0, None), doc="triangle budget as a mean edge length, scene units "
                             "(used when faces is 0; 0 = mc's faces)"),
        "min_views": Param(int, 0, range=(0, None), doc="0 = all views; k = inside at least k silhouettes (as the hull)"),
        "outside": Param(str, "carve", choices=POLICIES, doc="points projecting outside an image: carve, or ignore that view"),
        "use_alpha": Param(bool, True, doc="read soft alpha (8-bit) when the masks carry it, else the binary masks"),
        "method": Param(str, "opencl", choices=("opencl", "numpy"), doc="OpenCL kernels or the NumPy reference"),
    }
    kernels = [source("hullfit.cl"), source("fairing.cl")]

    def run(self, mesh, volume, masks, cameras, *, steps, quality, faces, edge_length, min_views, outside, use_alpha,
            method):
        import trimesh

        origin = 0.5 * (np.asarray(volume.bbox_min, np.float64) + np.asarray(volume.bbox_max, np.float64))
        field = SilhouetteField.from_inputs(masks, cameras, origin, min_views, outside, use_alpha, node="refine")
        target = target_face_count(mesh.vertices, mesh.faces, faces, edge_length)
        faces = np.asarray(mesh.faces)
        if target > 0:
            vertices, faces, stats = refine_vertices(mesh.vertices, faces, volume, field, steps, quality, method=method,
                                                     target_faces=target)
        else:
            vertices, faces, stats = refine_vertices(mesh.vertices, faces, volume, field, steps, quality, method=method)
        self.log.info("refine: %d of %d vertices onto the hull along grid edges, %d along normals",
                      stats["on_edges"], stats["vertices"], stats["on_normals"])
        out = trimesh.Trimesh(vertices, faces, vertex_colors=carried_vertex_colors(mesh, vertices), process=False)
        return {"mesh": out}


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


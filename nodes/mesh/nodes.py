"""Mesh stage nodes: marching cubes, refinement onto the visual hull, relaxation (work in mc.py, refine.py, relax.py)."""
from __future__ import annotations

import numpy as np

from kernels import source
from nodegraph import Input, Node, NodeError, Param
from nodes.common import raster
from nodes.common.meshops import carried_vertex_colors, drop_small_components, vertex_normals
from nodes.common.silhouettes import POLICIES
from nodes.common.types import CameraSet, Images, Masks, Mesh, Volume

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


class Photo(Node):
    """Photo-consistent refinement (nodes/mesh/photo.py): every vertex moves along its normal to where the views
    that see it best agree on its colour (a 3 x 3 tangent patch, weighted colour variance over its best views),
    the offsets smoothed over the mesh by how much they lower that variance; inward only by default, since
    the true surface is inside the visual hull. Place it after relax and before texture: the views then paint
    each point with the same place, so the texture is sharper and lands where the held-out camera sees it."""

    type_name = "photo"
    version = 1
    inputs = {"mesh": Mesh, "images": Images, "masks": Masks, "cameras": CameraSet}
    outputs = {"mesh": Mesh}
    params = {
        "search": Param(float, 0.01, range=(0.0, 0.1), doc="offsets searched, a fraction of the bounding-box diagonal"),
        "steps": Param(int, 21, range=(3, 101), doc="offsets tried within the search range"),
        "views": Param(int, 6, range=(2, 64), doc="best views per vertex compared (cos^2 of the viewing angle)"),
        "rounds": Param(int, 30, range=(0, 500), doc="smoothing rounds (confident vertices pull their neighbours)"),
        "inward_only": Param(bool, True, doc="search inside the surface only (a silhouette-built mesh is outside the "
                                             "true surface); false: both ways"),
        "margin": Param(int, 2, range=(0, 64), doc="mask erosion before sampling, pixels"),
        "keep_outlines": Param(bool, True, doc="vertices on a view's outline (the ray grazes them at the mask's edge) "
                                               "stay: the silhouettes fix the surface there"),
    }
    kernels = [raster.KERNELS]   # the z-buffer of the visibility test

    def run(self, mesh, images, masks, cameras, *, search, steps, views, rounds, inward_only, margin, keep_outlines):
        import trimesh

        from .photo import photo_offsets

        if len(images.images) != len(cameras) or len(masks.masks) != len(cameras):
            raise NodeError(f"photo: {len(images.images)} images and {len(masks.masks)} masks for {len(cameras)} "
                            "cameras: connect one image and one mask per camera")
        v = np.asarray(mesh.vertices, np.float64)
        if len(mesh.faces) == 0:
            return {"mesh": mesh}
        r = photo_offsets(v, mesh.faces, images.images, masks.masks, cameras, search=search, steps=steps,
                          views=views, rounds=rounds, inward_only=inward_only, erode_px=margin,
                          keep_outlines=keep_outlines)
        diag = float(np.linalg.norm(np.ptp(v, axis=0)))
        moved = r.confidence > 0
        self.log.info("photo: %d of %d vertices with evidence (seen by >= 2 views and a colour agreement off the "
                      "surface); offset median %.3g %% of the diagonal, 90th percentile %.3g %%", int(moved.sum()),
                      len(v), 100 * np.median(np.abs(r.offsets)) / diag, 100 * np.percentile(np.abs(r.offsets), 90) / diag)
        out = v + r.offsets[:, None] * vertex_normals(v, mesh.faces)
        return {"mesh": trimesh.Trimesh(out, np.asarray(mesh.faces), vertex_colors=carried_vertex_colors(mesh, out),
                                        process=False)}

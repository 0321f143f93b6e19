"""Texture nodes: ``texture`` paints a mesh from the camera images (atlas + PNG, or vertex colours);
``texture.atlas`` makes one UV atlas for a constant-connectivity sequence, to be given back to ``texture``
on every frame (only baking then runs per frame)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from kernels import source
from nodegraph import DataType, Input, Node, NodeError, Output, Param
from nodes.common import raster
from nodes.common.meshops import face_neighbours
from nodes.common.types import CameraSet, Images, Masks, Mesh, TexturedMesh, ViewTextures, nonfinite_vertices

from . import views
from .atlas import Atlas, make_atlas
from .reuse import reference_atlas
from .texturing import Settings, coloured_trimesh, texture_mesh, textured_trimesh
from .viewdep import NONE


class AtlasType(DataType):
    """A UV layout for one mesh connectivity (nodes.texture.atlas.Atlas), stored as atlas.npz (uncompressed:
    compressing took 28 ms of every textured frame)."""

    name = "Atlas"

    @classmethod
    def check(cls, v):
        if not isinstance(v, Atlas):
            return f"expected an Atlas, got {type(v).__name__}"
        if v.face_uv.shape != (len(v.faces), 3, 2) or v.face_chart.shape != (len(v.faces),):
            return "atlas arrays disagree with its face count"
        return None

    @classmethod
    def save(cls, v: Atlas, folder: Path):
        np.savez(folder / "atlas.npz", face_uv=v.face_uv, face_chart=v.face_chart, faces=v.faces, size=np.int64(v.size))

    @classmethod
    def load(cls, folder: Path) -> Atlas:
        with np.load(folder / "atlas.npz") as z:
            return Atlas(z["face_uv"], z["face_chart"], int(z["size"]), z["faces"])

    @classmethod
    def preview(cls, value, size, companions):
        import cv2

        s = value.size
        scale = size / s
        img = np.full((size, size, 3), 24, np.uint8)
        rng = np.random.default_rng(0)
        colours = rng.integers(60, 255, (max(value.n_charts, 1), 3))
        pts = np.round(value.face_uv * scale * 16).astype(np.int32)
        for f in range(len(pts)):
            cv2.fillPoly(img, [pts[f]], tuple(int(c) for c in colours[value.face_chart[f]]), shift=4)
        return img


def given_atlas(mesh, atlas, reference, size: int, directions: int):
    """The layout a node was given for ``mesh``: ``atlas`` itself, or the one charted on ``reference`` (same faces:
    track.frame's keyframe), or None; a NodeError naming the input when it does not fit the mesh's faces."""
    if atlas is not None and reference is not None:
        raise NodeError("connect 'atlas' or 'reference', not both")
    if reference is not None:
        if len(reference.faces) != len(mesh.faces) or not np.array_equal(reference.faces, mesh.faces):
            raise NodeError(f"input 'reference' has other faces ({len(reference.faces)}) than the mesh "
                            f"({len(mesh.faces)}): it must be the same connectivity (track.frame's keyframe)")
        atlas = reference_atlas(reference.vertices, reference.faces, size, directions)
    if atlas is not None and not atlas.matches(mesh.faces):
        raise NodeError(f"input 'atlas' was made for another connectivity ({len(atlas.faces)} faces); the mesh "
                        f"has {len(mesh.faces)} faces: an atlas is reused only for meshes with the same faces")
    return atlas


COMMON_PARAMS = {
    "size": Param(int, 2048, range=(16, 16384), doc="atlas texels per side"),
    "directions": Param(int, 6, choices=(6, 14), doc="chart projection directions (6 axes, or axes + diagonals)"),
}


class Texture(Node):
    """Paints a mesh from calibrated images: per-face view selection (frontal, high resolution, unoccluded,
    sharp, colour-consistent; Potts smoothness), per-camera exposure/white-balance gains, global seam
    levelling and a cross-fade across view seams, a UV atlas (or the one given), baked into a PNG texture.
    Pixels within ``margin`` of a mask border or ``edge_px`` of a depth edge are never sampled, so
    background cannot bleed in. mode=vertex gives vertex colours instead."""

    type_name = "texture"
    version = 1
    inputs = {
        "mesh": Mesh, "images": Images, "cameras": CameraSet,
        "masks": Input(Masks, optional=True, doc="silhouettes: only pixels inside them (minus margin) are sampled"),
        "atlas": Input(AtlasType, optional=True, doc="a layout made for this connectivity (texture.atlas): reused"),
        "reference": Input(Mesh, optional=True, doc="a mesh with the same faces to chart the atlas on (track.frame's "
                           "keyframe): every frame of a tracked segment gets the same layout"),
    }
    outputs = {
        "mesh": Output(TexturedMesh, "the mesh with UVs and its texture (GLB), or with vertex colours"),
        "atlas": Output(AtlasType, "the layout used (atlas mode)", optional=True),
        "views": Output(ViewTextures, "view-dependent layers on the same atlas (layers > 0): per face the K "
                        "cameras spread widest in direction, for a player that blends by viewing direction",
                        optional=True),
    }
    params = {
        "mode": Param(str, "atlas", choices=("atlas", "vertex"), doc="texture atlas or vertex colours"),
        **COMMON_PARAMS,
        "margin": Param(int, 2, range=(0, 64), doc="mask erosion before sampling, pixels"),
        "edge_px": Param(int, 2, range=(0, 64), doc="distance kept from depth edges and outlines, pixels"),
        "smoothness": Param(float, 0.5, range=(0.0, 100.0), doc="Potts weight between neighbouring faces' views"),
        "feather": Param(int, 2, range=(0, 64), doc="vertex rings of cross-fade on each side of a view seam"),
        "balance": Param(bool, True, doc="estimate per-camera exposure / white-balance gains"),
        "level": Param(bool, True, doc="global seam levelling"),
        "layers": Param(int, 0, range=(0, 16), doc="view-dependent layers kept per face (0: none; atlas mode)"),
        "layer_margin": Param(int, 0, range=(0, 64), doc="mask erosion for the layers, pixels: a camera paints its "
                              "own layer up to its mask's edge and its outline (depth test only)"),
    }
    kernels = [views.KERNELS, raster.KERNELS]

    def run(self, mesh, images, cameras, masks, atlas, reference, *, mode, size, directions, margin, edge_px,
            smoothness, feather, balance, level, layers, layer_margin):
        if len(mesh.faces) == 0:
            raise NodeError("the mesh has no faces: nothing to texture")
        if (atlas is not None or reference is not None) and mode == "vertex":
            raise NodeError("an atlas or a reference was given but mode is 'vertex' (vertex colours use no atlas)")
        if layers and mode == "vertex":
            raise NodeError("layers > 0 needs mode 'atlas' (view-dependent layers are atlas images)")
        if layers and len(cameras) > NONE:
            raise NodeError(f"layers > 0 supports at most {NONE} cameras; this rig has {len(cameras)}")
        atlas = given_atlas(mesh, atlas, reference, size, directions)
        s = Settings(size=size, margin=margin, edge_px=edge_px, smoothness=smoothness, feather=feather,
                     balance=balance, level=level, directions=directions, layers=layers,
                     layer_margin=layer_margin)
        r = texture_mesh(mesh.vertices, mesh.faces, images.images, None if masks is None else masks.masks, cameras,
                         s, atlas=atlas, mode=mode, mask_boxes=None if masks is None else masks.boxes)
        self.log.info("texture: %s; %s", json.dumps({k: round(v, 3) for k, v in r.timings.items()}), json.dumps(r.stats))
        if r.stats["faces_without_view"] > 0.25 * r.stats["faces"]:
            self.log.warning("%d of %d faces are seen by no camera; they are filled from their neighbours",
                             r.stats["faces_without_view"], r.stats["faces"])
        if mode == "vertex":
            return {"mesh": coloured_trimesh(mesh.vertices, mesh.faces, r.vertex_colours), "atlas": None, "views": None}
        return {"mesh": textured_trimesh(mesh.vertices, mesh.faces, r.atlas, r.texture), "atlas": r.atlas,
                "views": r.views}


class TextureAtlas(Node):
    """One UV atlas for a mesh sequence with constant connectivity (a tracked segment): made from the
    reference frame's mesh and given to ``texture`` on every frame, so only baking runs per frame and the
    texture stays in place over time."""

    type_name = "texture.atlas"
    version = 1
    per = "sequence"
    inputs = {"mesh": Mesh}
    outputs = {"atlas": AtlasType}
    params = {**COMMON_PARAMS,
              "reference": Param(int, 0, range=(0, None), doc="index (within the run's frames) of the mesh to chart")}

    def run(self, mesh, *, size, directions, reference):
        meshes = mesh if isinstance(mesh, list) else [mesh]
        if reference >= len(meshes):
            raise NodeError(f"reference {reference} is beyond the {len(meshes)} frames of this run")
        ref = meshes[reference]
        frames = getattr(self, "frames", list(range(len(meshes))))
        for fr, m in zip(frames, meshes):
            if m.faces.shape != ref.faces.shape or not np.array_equal(m.faces, ref.faces):
                raise NodeError(f"frame {fr}: its mesh has another connectivity ({len(m.faces)} faces) than the "
                                f"reference ({len(ref.faces)}); one atlas needs constant connectivity (track the sequence first)")
        if len(ref.faces) == 0:
            raise NodeError("the reference mesh has no faces")
        return {"atlas": make_atlas(ref.vertices, ref.faces, face_neighbours(ref.faces), size, directions=directions)}


class TextureTransfer(Node):
    """Paints a mesh's atlas from another textured mesh of the same surface instead of from the photos: every
    texel takes the source's texture at the closest point of the source surface (nodes/texture/transfer.py). For
    a stream's lower rung (the tracked sequence simplified, same motion): the same colours as the full rung
    (its gains, levelling and blending), at a cost that depends on the atlas only, not on the cameras."""

    type_name = "texture.transfer"
    version = 1
    inputs = {
        "mesh": Mesh,
        "source": Input(TexturedMesh, doc="the same surface textured (e.g. the full rung's texture.mesh of this frame)"),
        "atlas": Input(AtlasType, optional=True, doc="a layout made for this connectivity (texture.atlas): reused"),
        "reference": Input(Mesh, optional=True, doc="a mesh with the same faces to chart the atlas on (track.frame's "
                           "keyframe): every frame of a tracked segment gets the same layout"),
    }
    outputs = {"mesh": Output(TexturedMesh, "the mesh with UVs and its texture"),
               "atlas": Output(AtlasType, "the layout used")}
    params = {**COMMON_PARAMS}
    kernels = [source("closest.cl")]   # closest points on the source surface (nodes.common.closest.SurfaceQuery)

    def run(self, mesh, source, atlas, reference, *, size, directions):
        from .transfer import transfer_texture

        if len(mesh.faces) == 0:
            raise NodeError("the mesh has no faces: nothing to texture")
        for name, m in (("mesh", mesh), ("source", source)):
            problem = nonfinite_vertices(m)
            if problem:
                raise NodeError(f"input '{name}': {problem}")
        atlas = given_atlas(mesh, atlas, reference, size, directions)
        if atlas is None:
            atlas = reference_atlas(mesh.vertices, mesh.faces, size, directions)
        try:
            texture, stats = transfer_texture(mesh.vertices, mesh.faces, atlas, source)
        except ValueError as exc:
            raise NodeError(str(exc)) from None
        self.log.info("texture.transfer: %s", json.dumps(stats))
        return {"mesh": textured_trimesh(mesh.vertices, mesh.faces, atlas, texture), "atlas": atlas}

"""The texturing pipeline for one frame: visibility -> view selection -> levelling -> atlas -> baking.

    result = texture_mesh(vertices, faces, images, masks, cameras, Settings(size=2048))
    result.texture (S, S, 3) uint8, result.atlas, result.timings (seconds per step), result.stats

``atlas=`` reuses a layout made earlier for the same connectivity (a tracked sequence): only the
per-frame steps run. ``mode="vertex"`` gives per-vertex colours instead of an atlas.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from nodegraph import NodeError

from . import views as V
from .atlas import Atlas, make_atlas
from .bake import Blend, bake_samples, fill_texture
from .reuse import BakeLayout, Topology


@dataclass
class Settings:
    size: int = 2048                # atlas texels per side
    margin: int = 1                 # mask erosion, pixels
    edge_px: int = 1                # distance kept from depth edges, pixels
    depth_tol: float = 0.01         # z-buffer test tolerance, fraction of the mesh diagonal
    edge_tol: float = 0.02          # depth jump that counts as an edge, fraction of the mesh diagonal
    smoothness: float = 0.5         # Potts weight of the view selection
    consistency: float = 40.0       # colour distance (0..255) beyond which a view disagrees with a face's others
    feather: int = 2                # vertex rings of cross-fade on each side of a view seam
    adaptive: bool = True           # blend towards a weighted average where the views disagree
    spread_range: tuple = (12.0, 32.0)  # view disagreement (0..255) where that starts / is complete
    blend_views: int = 8            # most views blended per face
    average_power: float = 0.0      # quality exponent of the average (0: plain mean of the views)
    blur_px: float = 3.0            # radius of the blurred sample used where views disagree (0: never)
    balance: bool = True            # per-camera exposure / white-balance gains
    level: bool = True              # global seam levelling (offsets per vertex and view)
    gutter: int = 2                 # texels around each chart
    directions: int = 6             # chart directions (6 or 14)
    layers: int = 0                 # view-dependent layers (the K best views per face, viewdep.py); 0 = none
    stable_slots: bool = True       # a camera keeps one layer slot across faces (viewdep.stable_slots)
    layer_margin: int = 0           # mask erosion for the layers, pixels (< 0: grown): a camera paints its own layer up to its
                                    # mask's edge and its outline (depth test only), so its photo comes back there


@dataclass
class Result:
    atlas: Atlas | None
    texture: np.ndarray | None                 # (S, S, 3) uint8 (atlas mode)
    vertex_colours: np.ndarray | None          # (V, 3) uint8 (vertex mode)
    labels: np.ndarray
    blend: Blend
    layout: BakeLayout | None = None           # the atlas's texels (compact)
    weight: np.ndarray | None = None           # (N,) summed blend weight of each layout texel (0: not painted)
    timings: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    views: object = None                       # viewdep.ViewLayers (atlas mode with Settings.layers > 0)

    @property
    def texel_face(self) -> np.ndarray | None:
        """(S, S) face per texel, -1 = empty (the gutter borrows a neighbouring face)."""
        return None if self.layout is None else self.layout.texel_face

    @property
    def texel_weight(self) -> np.ndarray | None:
        """(S, S) summed blend weight (0: no view painted the texel)."""
        if self.layout is None:
            return None
        out = np.zeros(self.layout.size ** 2, np.float32)
        out[self.layout.texel] = self.weight
        return out.reshape(self.layout.size, self.layout.size)

    @property
    def texel_inner(self) -> np.ndarray | None:
        """(S, S) bool: texel centre inside a face (not the gutter)."""
        if self.layout is None:
            return None
        out = np.zeros(self.layout.size ** 2, bool)
        out[self.layout.texel[self.layout.inner]] = True
        return out.reshape(self.layout.size, self.layout.size)


def prepare(vertices, faces, images, masks, cameras, s: Settings, timings: dict, topo: Topology | None = None,
            mask_boxes=None):
    if len(images) != len(cameras):
        raise NodeError(f"{len(images)} images for {len(cameras)} cameras")
    if masks is not None and len(masks) != len(cameras):
        raise NodeError(f"{len(masks)} masks for {len(cameras)} cameras")
    for i, (im, cam) in enumerate(zip(images, cameras)):
        if im.shape[:2] != (cam.height, cam.width):
            raise NodeError(f"image {i} is {im.shape[1]}x{im.shape[0]} but camera '{cam.name}' is {cam.width}x{cam.height}")
        if masks is not None and masks[i].shape[:2] != im.shape[:2]:
            raise NodeError(f"mask {i} is {masks[i].shape[1]}x{masks[i].shape[0]} but image {i} is {im.shape[1]}x{im.shape[0]}")
    t = time.perf_counter()
    frame = V.FrameImages.build(images, masks, s.margin, boxes=mask_boxes)
    # the layers' frame: the same images, masks eroded by layer_margin (their visibility: FaceViews.seen)
    layer_frame = frame.with_margin(masks, s.layer_margin) if s.layers > 0 else None
    stats = V.face_view_stats(vertices, faces, cameras, frame, depth_tol=s.depth_tol, edge_tol=s.edge_tol,
                              edge_px=s.edge_px, seen_frame=layer_frame,
                              closed_parts=(topo or Topology.of(faces, len(vertices))).closed_parts)
    timings["visibility"] = time.perf_counter() - t
    return frame, stats, layer_frame


def choose(vertices, faces, cameras, frame, stats, s: Settings, topo: Topology, timings: dict):
    t = time.perf_counter()
    gains = V.camera_gains(stats.quality, stats.colour) if s.balance else np.ones((len(cameras), 3), np.float32)
    sharp = V.view_sharpness(frame.images, frame.valid, frame.boxes)
    q = stats.effective() * sharp[:, None].astype(np.float32)
    d_cost, spread, d_best = V.data_cost_cl(stats, sharp, gains, consistency=s.consistency)   # = V.data_cost(q, ...)
    labels = V.select_views_cl(d_cost, d_best, topo.nbr, len(cameras), smoothness=s.smoothness)   # = V.select_views
    face_view, weight = V.blend_weights(labels, q, faces, len(vertices), feather=s.feather,
                                        spread=spread if s.adaptive else None, spread_range=s.spread_range,
                                        K=s.blend_views, power=s.average_power, topo=topo)
    timings["selection"] = time.perf_counter() - t
    t = time.perf_counter()
    if s.level:
        offset = V.level_seams(vertices, faces, face_view, weight, cameras, frame, gains, topo=topo)
    else:
        offset = np.zeros(face_view.shape[:1] + (3,) + face_view.shape[1:] + (3,), np.float32)
    timings["levelling"] = time.perf_counter() - t
    blur = None
    if s.adaptive and s.blur_px > 0:
        lo, hi = s.spread_range
        blur = np.clip((spread - lo) / max(hi - lo, 1e-6), 0, 1).astype(np.float32)
    return labels, Blend(face_view, weight, offset, gains, blur, s.blur_px), q, sharp


def texture_mesh(vertices, faces, images, masks, cameras, s: Settings = Settings(), *, atlas: Atlas | None = None,
                 mode: str = "atlas", mask_boxes=None) -> Result:
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int32)
    timings: dict = {}
    topo = Topology.of(faces, len(vertices))
    frame, stats, layer_frame = prepare(vertices, faces, images, masks, cameras, s, timings, topo, mask_boxes)
    labels, blend, quality, sharp = choose(vertices, faces, cameras, frame, stats, s, topo, timings)

    def fallback():
        return V.fallback_vertex_colours(labels, stats.colour, blend.gains, faces, len(vertices), topo=topo)

    info = {"faces": int(len(faces)), "faces_without_view": int(np.sum(labels < 0)),
            "views_used": int(len(np.unique(labels[labels >= 0])))}
    if mode == "vertex":
        t = time.perf_counter()
        first_face = np.full(len(vertices), -1, np.int64)
        corner = np.zeros(len(vertices), np.int64)
        for k in (2, 1, 0):
            first_face[faces[:, k]] = np.arange(len(faces))
            corner[faces[:, k]] = k
        used = first_face >= 0
        bary = np.zeros((len(vertices), 3), np.float32)
        bary[np.arange(len(vertices)), corner] = 1.0
        rgbw = bake_samples(np.where(used, first_face, -1), bary, vertices, faces, cameras, frame, blend)
        col = np.where(rgbw[:, 3:4] > 0, rgbw[:, :3], fallback())
        timings["baking"] = time.perf_counter() - t
        info["vertices_from_fallback"] = int(np.sum(rgbw[:, 3] <= 0))
        return Result(None, None, np.clip(col + 0.5, 0, 255).astype(np.uint8), labels, blend, timings=timings, stats=info)

    t = time.perf_counter()
    if atlas is None:
        atlas = make_atlas(vertices, faces, topo.nbr, s.size, directions=s.directions, gutter=s.gutter)
        timings["atlas"] = time.perf_counter() - t
    else:
        if not atlas.matches(faces):
            raise NodeError(f"the atlas was made for {len(atlas.faces)} faces of another connectivity; this mesh has "
                            f"{len(faces)} faces (an atlas can be reused only for meshes with the same faces)")
        timings["atlas"] = 0.0
    t = time.perf_counter()
    layout = BakeLayout.of(atlas, max(1, s.gutter))
    rgbw = bake_samples(layout.face, layout.bary, vertices, faces, cameras, frame, blend,
                        device_samples=layout.device())
    col = rgbw[:, :3]
    w = rgbw[:, 3]
    need = np.flatnonzero(w <= 0)
    if len(need):                                             # no view may paint it: the vertex-colour fallback
        col[need] = np.einsum("nc,ncd->nd", layout.bary[need], fallback()[faces[layout.face[need]]])
    texture = fill_texture(col, layout)
    timings["baking"] = time.perf_counter() - t
    if s.layers > 0:
        from .viewdep import ViewLayers, bake_layers, choose_layers, stable_slots

        t = time.perf_counter()
        # a view the static tests refuse (the outline, the mask's edge) but that sees the face unoccluded inside
        # its mask may paint its own layer, ranked below every view the static atlas may use
        lq = np.where(quality > 0, quality, np.float32(0.01) * stats.seen * sharp[:, None]).astype(np.float32)
        fv = choose_layers(lq, faces, len(vertices), cameras.centers, vertices, K=s.layers, topo=topo)
        if s.stable_slots:
            fv = stable_slots(fv, len(cameras))
        layers, texel_view = bake_layers(layout, vertices, faces, cameras, layer_frame, fv, texture)
        views = ViewLayers(layers, texel_view, np.asarray(cameras.centers, np.float64), [c.name for c in cameras])
        timings["layers"] = time.perf_counter() - t
    else:
        views = None
    info.update({"charts": atlas.n_charts, "texels_covered": int(np.sum(layout.inner)),
                 "texels_from_fallback": int(np.sum(layout.inner[need]))})
    return Result(atlas, texture, None, labels, blend, layout=layout, weight=w, timings=timings, stats=info,
                  views=views)


# ---------------------------------------------------------------- trimesh output
def textured_trimesh(vertices, faces, atlas: Atlas, texture: np.ndarray):
    """A trimesh.Trimesh with one vertex per (vertex, chart) pair, per-vertex UVs and the texture as the PBR
    base colour (what GLB/OBJ/USD exports read)."""
    import trimesh

    from nodes.common.gltf import textured_visual

    src, tri, uv = _uv_vertices(atlas, faces)
    return trimesh.Trimesh(np.asarray(vertices, np.float64)[src], tri.copy(), visual=textured_visual(uv.copy(), texture),
                           process=False)


def _uv_vertices(atlas: Atlas, faces):
    """(source vertex per output vertex, output faces, uv per output vertex) of ``textured_trimesh``: they
    depend on the connectivity and the atlas only, so they are kept on the atlas object for the next frame."""
    faces = np.asarray(faces, np.int64)
    kept = getattr(atlas, "_uv_vertices", None)
    if kept is not None and np.array_equal(kept[0], faces):
        return kept[1:]
    key = faces * (atlas.n_charts or 1) + atlas.face_chart[:, None].astype(np.int64)
    uniq, inverse = np.unique(key.ravel(), return_inverse=True)
    src = uniq // (atlas.n_charts or 1)
    uv = np.zeros((len(uniq), 2), np.float64)
    uv[inverse] = atlas.uv01().reshape(-1, 2)
    out = (src, inverse.reshape(-1, 3), uv)
    try:
        atlas._uv_vertices = (faces.copy(), *out)
    except AttributeError:
        pass
    return out


def coloured_trimesh(vertices, faces, colours):
    import trimesh

    rgba = np.hstack([colours, np.full((len(colours), 1), 255, np.uint8)])
    return trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), vertex_colors=rgba, process=False)

"""Texture transfer: paint a mesh's atlas from another textured mesh of the same surface (a stream's lower rung
from its full rung) instead of from the photos.

    texture, stats = transfer_texture(vertices, faces, atlas, source_mesh)

Every texel of the atlas (inside a face or in its gutter: ``BakeLayout``) shows a surface point; its colour is
the source's texture at the closest point of the source surface (``SurfaceQuery.closest`` on the source welded
by position, so a source chart seam does not hide the faces across it; bilinear lookup as the renderer does);
the rest of the square is filled as ``texture`` fills it. The cost depends on the atlas, not on the cameras: no
visibility, view selection, levelling or bake per view. The source's colours are what its own texturing made of
the photos (gains, levelling, blending), so the rung shows the same colours as the full one.
"""
from __future__ import annotations

import numpy as np

from nodes.common.raster import sample_texture

from .atlas import Atlas
from .bake import fill_texture
from .reuse import BakeLayout


def welded(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) with the vertices of equal position merged (a textured mesh splits them at chart seams);
    the faces keep their order."""
    v = np.ascontiguousarray(vertices, np.float64)
    uniq, inverse = np.unique(v.view(np.dtype((np.void, 24))).ravel(), return_inverse=True)
    first = np.zeros(len(uniq), np.int64)
    first[inverse[::-1]] = np.arange(len(v))[::-1]
    return v[first], inverse.reshape(-1)[np.asarray(faces, np.int64)]


def source_parts(source) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, per-vertex uv (V, 2) in [0, 1] v up, texture (S, S, 3) uint8) of a textured trimesh."""
    visual = source.visual
    material = getattr(visual, "material", None)
    image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
    if getattr(visual, "kind", None) != "texture" or getattr(visual, "uv", None) is None or image is None:
        raise ValueError("input 'source': the source mesh has no texture (UVs and an image): texture it first (mode atlas)")
    return (np.asarray(source.vertices, np.float64), np.asarray(source.faces, np.int64),
            np.asarray(visual.uv, np.float64), np.ascontiguousarray(np.asarray(image.convert("RGB")), np.uint8))


def face_uv_maps(sv: np.ndarray, sf: np.ndarray, suv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per face the affine map of a point on its plane to its texture coordinates: uv = C + M p, with M (F, 2, 3)
    and C (F, 2) (barycentric coordinates from the dual basis of the face's edges; a degenerate face maps every
    point to its corners' mean)."""
    a, b, c = (sv[sf[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    d11, d12, d22 = (np.einsum("ij,ij->i", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
    det = d11 * d22 - d12 * d12
    ok = det > 1e-30 * np.maximum(d11 * d22, 1e-300)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    g1 = (d22 * inv)[:, None] * e1 - (d12 * inv)[:, None] * e2      # s = g1 . (p - a)
    g2 = (d11 * inv)[:, None] * e2 - (d12 * inv)[:, None] * e1      # t = g2 . (p - a)
    u0, u1, u2 = (suv[sf[:, k]] for k in range(3))
    M = (u1 - u0)[:, :, None] * g1[:, None, :] + (u2 - u0)[:, :, None] * g2[:, None, :]
    C = np.where(ok[:, None], u0 - np.einsum("fij,fj->fi", M, a), (u0 + u1 + u2) / 3)
    return M, C


def texel_uv(points: np.ndarray, sv: np.ndarray, sf: np.ndarray, suv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(uv (N, 2) of the closest point of the surface (sv, sf) to each point, with the per-vertex ``suv`` of the
    faces sf; distance (N,)). The surface is welded by position first, so a chart seam hides no face."""
    from nodes.common.closest import SurfaceQuery

    wv, wf = welded(sv, sf)
    q, d, face = SurfaceQuery(wv, wf, with_normals=False).closest(points, with_faces=True)
    M, C = face_uv_maps(sv, sf, suv)                         # a face's corners: the same points, split or welded
    return C[face] + np.einsum("nij,nj->ni", M[face], q), d


def transfer_texture(vertices, faces, atlas: Atlas, source, gutter: int = 2) -> tuple[np.ndarray, dict]:
    """The (S, S, 3) uint8 texture of ``atlas`` on the mesh (vertices, faces) with the colours of the textured
    trimesh ``source``, and stats: texels painted, distance to the source surface (median, max; mesh units).

    The texels are matched to the source on every frame: matched once on a segment's keyframes and kept, the
    match drifted by a median 4 mm (2 % of the texels by over 20 mm) on the demo's walk, whose simplified rung
    does not move with the full rung's surface points (the replayed collapses place their vertices anew)."""
    sv, sf, suv, stex = source_parts(source)
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    layout = BakeLayout.of(atlas, max(1, gutter))
    points = np.einsum("nc,ncd->nd", layout.bary, v[f[layout.face]])
    uv, d = texel_uv(points, sv, sf, suv)
    colour = sample_texture(stex, uv).astype(np.float64)
    texture = fill_texture(colour, layout)
    inner = d[layout.inner]
    return texture, {"texels": int(len(layout)), "distance_median": float(np.median(inner)) if len(inner) else 0.0,
                     "distance_max": float(inner.max()) if len(inner) else 0.0}

"""Measures of a texturing result: colour jumps across seams, and background texels.

    jumps = seam_jumps(result, faces)           # mean |colour difference| across atlas seams, view seams, inside
    bg, painted = background_texels(result, vertices, faces, masks, cameras)
    f = flicker(colours, truth)                 # frame-to-frame change of the same texels not in the truth
"""
from __future__ import annotations

import numpy as np

from nodes.common.raster import sample_texture

from .bake import texel_bary_reference
from nodes.common.meshops import face_neighbours


def _inside_edge_uv(face_uv, f, side, texels=1.5):
    """Texel coordinates of a point just inside face f, next to the midpoint of its side ``side``."""
    a = face_uv[f, side]
    b = face_uv[f, (side + 1) % 3]
    o = face_uv[f, (side + 2) % 3]
    m = 0.5 * (a + b)
    d = o - m
    ln = np.linalg.norm(d, axis=1, keepdims=True)
    t = np.minimum(texels / np.maximum(ln, 1e-9), 0.5)
    return m + t * d


def seam_jumps(result, faces) -> dict:
    """Mean absolute colour difference (0..255, averaged over RGB) between the two sides of each mesh edge,
    sampled 1.5 texels inside each face at the edge's midpoint, for edges on an atlas seam (charts differ),
    on a view seam inside a chart (selected views differ) and inside (same chart, same view)."""
    atlas, tex = result.atlas, result.texture
    faces = np.asarray(faces, np.int64)
    nbr = face_neighbours(faces)
    f = np.repeat(np.arange(len(faces)), 3)
    side = np.tile(np.arange(3), len(faces))
    g = nbr.ravel()
    keep = g > f                                   # each interior edge once
    f, side, g = f[keep], side[keep], g[keep]
    # the side of g that is the same edge
    ef = np.sort(np.stack([faces[f, side], faces[f, (side + 1) % 3]], 1), 1)
    gside = np.full(len(g), -1)
    for k in range(3):
        eg = np.sort(np.stack([faces[g, k], faces[g, (k + 1) % 3]], 1), 1)
        gside = np.where(np.all(eg == ef, axis=1), k, gside)
    ok = gside >= 0
    f, side, g, gside = f[ok], side[ok], g[ok], gside[ok]
    uf = _inside_edge_uv(atlas.face_uv, f, side)
    ug = _inside_edge_uv(atlas.face_uv, g, gside)
    s = atlas.size
    to01 = lambda u: np.stack([u[:, 0] / s, 1.0 - u[:, 1] / s], axis=1)  # noqa: E731
    cf, cg = sample_texture(tex, to01(uf)), sample_texture(tex, to01(ug))
    jump = np.abs(cf - cg).mean(axis=1)
    chart_seam = atlas.face_chart[f] != atlas.face_chart[g]
    view_seam = ~chart_seam & (result.labels[f] != result.labels[g])
    inside = ~chart_seam & ~view_seam

    def mean(sel):
        return float(jump[sel].mean()) if np.any(sel) else float("nan")

    return {"atlas_seams": mean(chart_seam), "view_seams": mean(view_seam), "inside": mean(inside),
            "n_atlas_seams": int(chart_seam.sum()), "n_view_seams": int(view_seam.sum()), "n_inside": int(inside.sum())}


def background_texels(result, vertices, faces, masks, cameras) -> tuple[int, int]:
    """(texels whose surface point is outside the mask of every view that has it in its image, of those the
    number painted from an image). Texels inside charts only (the gutter is not counted)."""
    tf = result.texel_face
    inner = np.flatnonzero(result.texel_inner.reshape(-1))
    bary = texel_bary_reference(tf, result.atlas.face_uv).reshape(-1, 3)[inner]
    f = tf.reshape(-1)[inner]
    X = np.einsum("nc,ncd->nd", bary, np.asarray(vertices, np.float64)[np.asarray(faces)[f]])
    inside_any = np.zeros(len(X), bool)
    seen_any = np.zeros(len(X), bool)
    for i in range(len(cameras)):
        uv, z = cameras.project(X, i)
        h, w = masks[i].shape
        x, y = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        ok = (x >= 0) & (y >= 0) & (x < w) & (y < h) & (z > 0)
        seen_any |= ok
        inside_any[ok] |= masks[i][y[ok], x[ok]] > 127
    bg = seen_any & ~inside_any
    painted = result.texel_weight.reshape(-1)[inner] > 0
    return int(bg.sum()), int((bg & painted).sum())


def view_seam_disagreement(result, vertices, faces, cameras, frame, *, corrected=True) -> dict:
    """How much the two views of a view seam disagree where they meet: at the midpoint of every edge whose
    faces were given different views, |colour in view a - colour in view b| (mean over RGB, 0..255), with
    the gains and levelling offsets applied (``corrected``) or as captured. The texture cross-fades between
    the two, so this is the jump a hard seam would show."""
    from .views import _sample_rgb_reference

    faces = np.asarray(faces, np.int64)
    nbr = face_neighbours(faces)
    labels = result.labels
    f = np.repeat(np.arange(len(faces)), 3)
    side = np.tile(np.arange(3), len(faces))
    g = nbr.ravel()
    keep = (g > f) & (labels[f] >= 0) & (labels[np.maximum(g, 0)] >= 0)
    keep[keep] &= labels[f[keep]] != labels[g[keep]]
    f, side, g = f[keep], side[keep], g[keep]
    va, vb = labels[f], labels[g]
    X = 0.5 * (np.asarray(vertices)[faces[f, side]] + np.asarray(vertices)[faces[f, (side + 1) % 3]])
    blend = result.blend

    def colour(view, face, corners):
        out = np.full((len(view), 3), np.nan)
        for v in np.unique(view):
            sel = np.flatnonzero(view == v)
            p, z = cameras.project(X[sel], int(v))
            val = frame.valid[v]
            h, w = val.shape
            x, y = np.round(p[:, 0]).astype(np.int64), np.round(p[:, 1]).astype(np.int64)
            ok = (x >= 0) & (y >= 0) & (x < w) & (y < h) & (z > 0)
            ok[ok] &= val[y[ok], x[ok]] > 0
            c = _sample_rgb_reference(frame.images[v], np.nan_to_num(p))
            if corrected:
                c = c * blend.gains[v]
                slot = np.argmax(blend.face_view[face[sel]] == v, axis=1)
                has = blend.face_view[face[sel], slot] == v
                off = blend.offset[face[sel][:, None], corners[sel], slot[:, None]].mean(axis=1)
                c = c + np.where(has[:, None], off, 0)
            out[sel[ok]] = c[ok]
        return out

    cf = np.stack([side, (side + 1) % 3], 1)
    gverts = faces[g]
    a_ids = faces[f, side]
    b_ids = faces[f, (side + 1) % 3]
    cg_ = np.stack([np.argmax(gverts == a_ids[:, None], axis=1), np.argmax(gverts == b_ids[:, None], axis=1)], 1)
    ca, cb = colour(va, f, cf), colour(vb, g, cg_)
    d = np.abs(ca - cb).mean(axis=1)
    d = d[np.isfinite(d)]
    return {"view_seam_disagreement": float(d.mean()) if len(d) else float("nan"), "edges": int(len(d))}


def uneven_shading(images) -> list:
    """Camera-dependent shading for seam tests: vignetting on odd cameras, a vertical brightness ramp on even
    ones (what per-camera gains alone cannot undo)."""
    out = []
    for i, im in enumerate(images):
        h, w = im.shape[:2]
        yy, xx = np.mgrid[:h, :w]
        r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (w / 2) ** 2
        fall = 1 - 0.5 * r2 if i % 2 else 1 + 0.2 * (yy / h)
        out.append(np.clip(im * fall[..., None], 0, 255).astype(np.uint8))
    return out


def flicker(colours, truth=None, keep=None) -> dict:
    """How much the same texels (one atlas over a tracked segment) change from frame to frame beyond what the
    surface itself does. ``colours`` (T, N, 3) the texels' colours per frame (0..255), ``truth`` (T, N, 3)
    what they should be (the albedo as lit in each frame; None: a static surface, no change), ``keep`` (N,)
    bool the texels to count. Returns flicker = mean over consecutive frames and texels of
    |(c_t+1 - c_t) - (a_t+1 - a_t)| averaged over RGB, change = the same without the truth, truth_change =
    the truth's own, and per_pair (T-1,) flicker."""
    c = np.asarray(colours, np.float64)
    if c.ndim != 3 or c.shape[0] < 2 or c.shape[2] != 3:
        raise ValueError(f"colours must be (T >= 2, N, 3), got {c.shape}")
    a = np.zeros_like(c) if truth is None else np.asarray(truth, np.float64)
    if a.shape != c.shape:
        raise ValueError(f"truth {a.shape} does not match colours {c.shape}")
    sel = np.ones(c.shape[1], bool) if keep is None else np.asarray(keep, bool)
    dc, da = np.diff(c[:, sel], axis=0), np.diff(a[:, sel], axis=0)
    per_pair = np.abs(dc - da).mean(axis=(1, 2)) if sel.any() else np.full(len(c) - 1, np.nan)
    return {"flicker": float(per_pair.mean()), "change": float(np.abs(dc).mean()) if sel.any() else float("nan"),
            "truth_change": float(np.abs(da).mean()) if sel.any() else float("nan"), "per_pair": per_pair}

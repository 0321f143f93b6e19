"""View-dependent texture (Debevec et al. 1996; weights after Buehler et al. 2001, unstructured lumigraph):
per face K views spread in direction are kept as K atlas layers, each painted by one camera only, with a
map saying which camera painted each texel; a renderer blends the layers by the angle between its viewing
ray and each layer's camera ray, so a surface seen from near a capture camera shows that camera's photo.

    face_view = choose_layers(quality, faces, n_vertices, centres, vertices, K=4)   # (F, K) views, -1 = none
    face_view = stable_slots(face_view, n_views)                                  # camera c in slot c mod K
    layers, texel_view = bake_layers(layout, vertices, faces, cameras, layer_frame, face_view, base)
    w = layer_weights(points, eye, centres, ids)                                # (N, K) blend weights

A static texture on approximate geometry can reproduce no photo exactly (each camera sees the surface's
errors with its own parallax); the layers can, where the viewer is near a camera. A layer is its camera's own
picture of the surface: a view may paint a face there wherever it sees it unoccluded inside its mask (texturing:
``layer_margin`` 0 and ``FaceViews.seen``, no edge margin), also at the outline the static atlas keeps away from,
so that at the capture camera the whole photo comes back. ``layer_weights`` is the
reference of what a player's shader does (docs in export.player).
"""
from __future__ import annotations

import numpy as np

from nodes.common.viewlayers import NONE, SIGMA, ViewLayers, layer_weights  # noqa: F401 (re-exported)

from .bake import Blend, bake_samples


def choose_layers(quality, faces, n_vertices, centres, vertices, *, K=8, topo=None) -> np.ndarray:
    """(F, K) int32: per face K views that see it, -1 where fewer do. The first is the view of highest quality;
    each next one the usable view farthest in direction from those already kept (angles seen from the face),
    so that from wherever a viewer looks some layer's camera is near (a grazing or edge view counts: the
    renderer needs the camera nearest the eye, not the best one). Quality is averaged over each vertex's faces
    first, so neighbouring faces tend to keep the same views. No colour test: where the geometry is off the
    surface the views disagree, and that is when the camera nearest the eye matters most (the static
    selection's consistency test as a filter here cost 0.9 dB held out on thu_wd_human and 4.2 dB on templeSR);
    a highlight a camera sees belongs near that camera."""
    from scipy.sparse import csr_matrix

    q = np.asarray(quality, np.float32)                       # (V, F)
    nv, nf = q.shape
    K = min(K, nv)
    faces = np.asarray(faces, np.int64)
    ok = q.T > 0                                              # (F, V) usable
    inc = topo.incidence if topo is not None else csr_matrix(
        (np.ones(3 * nf), (faces.ravel(), np.repeat(np.arange(nf), 3))), shape=(n_vertices, nf))
    cnt = np.asarray(inc.sum(axis=1)).ravel()
    qv = np.asarray(inc @ q.T) / np.maximum(cnt, 1)[:, None]  # (n_vertices, V)
    score = (qv[faces[:, 0]] + qv[faces[:, 1]] + qv[faces[:, 2]]) * ok
    v = np.asarray(vertices, np.float64)
    g = v[faces].mean(axis=1)                                 # (F, 3)
    d = np.asarray(centres, np.float64)[None] - g[:, None]    # (F, V, 3)
    d /= np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-12)
    d = d.astype(np.float32)
    rows = np.arange(nf)
    out = np.full((nf, K), -1, np.int32)
    first = np.argmax(np.where(ok, score, -1.0), axis=1)
    have = ok[rows, first]
    out[:, 0] = np.where(have, first, -1)
    near = np.where(ok, np.einsum("fvd,fd->fv", d, d[rows, first]), 2.0)   # cosine to the nearest kept view
    taken = np.zeros((nf, nv), bool)
    taken[rows, first] = True
    for k in range(1, K):
        far = np.where(ok & ~taken, near, 2.0)               # lowest cosine = farthest from the kept ones
        nxt = np.argmin(far, axis=1)
        have = far[rows, nxt] < 2.0
        out[:, k] = np.where(have, nxt, -1)
        taken[rows[have], nxt[have]] = True
        near = np.maximum(near, np.einsum("fvd,fd->fv", d, d[rows, nxt]))
    return out


def stable_slots(face_view, n_views) -> np.ndarray:
    """The same views per face as ``face_view`` (F, K), moved to layer slots that depend on the camera: camera c
    takes slot c mod K where free (else the next free one), in the order they were chosen. Neighbouring faces
    then keep a camera in the same layer, so a renderer's bilinear lookup of layer k at a face border reads
    that camera on both sides (with K >= the number of cameras, always); -1 = empty slot."""
    fv = np.asarray(face_view, np.int32)
    nf, K = fv.shape
    out = np.full((nf, K), -1, np.int32)
    rows = np.arange(nf)
    for k in range(K):
        c = fv[:, k]
        todo = c >= 0
        slot = np.where(todo, c % K, 0)
        for _ in range(K):
            free = todo & (out[rows, slot] < 0)
            out[rows[free], slot[free]] = c[free]
            todo &= ~free
            if not todo.any():
                break
            slot = (slot + 1) % K
    return out


def bake_layers(layout, vertices, faces, cameras, frame, face_view, base) -> tuple[np.ndarray, np.ndarray]:
    """Bake each layer from its one camera per face, in that camera's own colours (no gains, no blending, no
    seam levelling: near a capture camera its photo is what the viewer should see, and the renderer blends).
    ``base`` (S, S, 3) uint8, the blended texture, fills what a layer's camera cannot paint.
    Returns (layers (K, S, S, 3) uint8, texel_view (S, S, K) uint8)."""
    nf, K = face_view.shape
    S = layout.size
    layers = np.repeat(np.asarray(base, np.uint8)[None], K, axis=0)
    texel_view = np.full((S, S, K), NONE, np.uint8)
    flat_view = texel_view.reshape(-1, K)
    dev = layout.device()
    for k in range(K):
        fv = face_view[:, k:k + 1]
        blend = Blend(fv, np.repeat((fv >= 0)[:, None, :], 3, axis=1).astype(np.float32),
                      np.zeros((nf, 3, 1, 3), np.float32), np.ones((len(cameras), 3), np.float32))
        rgbw = bake_samples(layout.face, layout.bary, vertices, faces, cameras, frame, blend, device_samples=dev)
        got = rgbw[:, 3] > 0
        idx = layout.texel[got]
        layers[k].reshape(-1, 3)[idx] = np.clip(rgbw[got, :3] + 0.5, 0, 255).astype(np.uint8)
        flat_view[idx, k] = fv[layout.face[got], 0].astype(np.uint8)
    return layers, texel_view


def render_layers(vertices, faces, face_uv, base, vl: ViewLayers, cameras, view, *, sigma=None,
                  background=(0, 0, 0)):
    """Render the view-dependent texture into camera ``view`` (what a player does at that eye): the layers
    blended with the static texture ``base`` by ``layer_weights``. Returns (rgb (H, W,
    3) uint8, coverage (H, W) bool)."""
    from nodes.common.raster import rasterize, sample_texture

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    tri, _, bary = rasterize(v, f, cameras, view)
    hit = tri >= 0
    t = tri[hit]
    b = bary[hit].astype(np.float64)
    X = np.einsum("nc,ncd->nd", b, v[f[t]])
    uv = np.einsum("nc,ncd->nd", b.astype(np.float32), np.asarray(face_uv, np.float32)[t])
    S = vl.texel_view.shape[0]
    tx = np.clip((uv[:, 0] * S).astype(np.int64), 0, S - 1)
    ty = np.clip(((1.0 - uv[:, 1]) * S).astype(np.int64), 0, S - 1)
    ids = vl.texel_view[ty, tx]                                   # (N, K) nearest texel: ids do not interpolate
    w, wb = layer_weights(X, cameras.centers[view], vl.centres, ids, vl.sigma if sigma is None else sigma)
    col = wb[:, None] * sample_texture(base, uv)
    for k in range(vl.layers.shape[0]):
        col += w[:, k:k + 1] * sample_texture(vl.layers[k], uv)
    out = np.empty(tri.shape + (3,), np.uint8)
    out[:] = np.asarray(background, np.uint8)
    out[hit] = np.clip(col + 0.5, 0, 255).astype(np.uint8)
    return out, hit

"""Baking: atlas texels (or vertices) -> 3-D points -> blended, levelled image samples (kernels/texture.cl).

    texel_face = uv_raster(atlas)                         # (S, S) face id per texel, -1 = empty
    texel_face = add_gutter(texel_face, 2)                # border texels borrow a neighbouring face
    bary = texel_bary(texel_face, atlas.face_uv)          # (S, S, 3)
    rgbw = bake(samples..., blend)                        # (N, 4): colour 0..255 and the summed weight

Each has a NumPy reference (``*_reference``) used by the tests on small inputs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .views import FrameImages, TextureCL, _sample_rgb_reference


@dataclass
class Blend:
    """Per face: up to K views with per-corner weights, per-corner additive offsets, and per-view gains."""

    face_view: np.ndarray    # (F, K) int32, -1 unused
    weight: np.ndarray       # (F, 3, K) float32
    offset: np.ndarray       # (F, 3, K, 3) float32, 0..255 units
    gains: np.ndarray        # (V, 3) float32
    blur: np.ndarray | None = None   # (F,) float32 0..1: how much of a blurred sample to use
    blur_px: float = 2.0

    def face_blur(self) -> np.ndarray:
        return np.zeros(len(self.face_view), np.float32) if self.blur is None else np.asarray(self.blur, np.float32)


# ---------------------------------------------------------------- UV rasterization
def uv_raster(face_uv, size: int) -> np.ndarray:
    import pyopencl as cl

    nf = len(face_uv)
    tcl = TextureCL.get()
    out = np.empty((size, size), np.int32)
    d_tf = tcl.buffer("texel_face", 4 * size * size)
    cl.enqueue_fill_buffer(tcl.queue, d_tf, np.int32(-1), 0, 4 * size * size)
    if nf:
        d_uv = tcl.upload("face_uv", np.ascontiguousarray(face_uv, np.float32))
        tcl.launch("uv_raster", (nf,), (64,), d_uv, np.int32(nf), np.int32(size), d_tf)
    return tcl.read(d_tf, (size, size), np.int32, out=out)


def uv_raster_reference(face_uv, size: int) -> np.ndarray:
    out = np.full((size, size), -1, np.int64)
    uv = np.asarray(face_uv, np.float32)
    for f in range(len(uv)):
        a, b, c = uv[f]
        area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if area == 0:
            continue
        x0 = max(0, int(np.floor(min(a[0], b[0], c[0]) - 0.5)))
        x1 = min(size - 1, int(np.ceil(max(a[0], b[0], c[0]) - 0.5)))
        y0 = max(0, int(np.floor(min(a[1], b[1], c[1]) - 0.5)))
        y1 = min(size - 1, int(np.ceil(max(a[1], b[1], c[1]) - 0.5)))
        if x1 < x0 or y1 < y0:
            continue
        py, px = np.mgrid[y0:y1 + 1, x0:x1 + 1].astype(np.float32) + np.float32(0.5)
        inv = np.float32(1) / area
        w0 = ((c[0] - b[0]) * (py - b[1]) - (c[1] - b[1]) * (px - b[0])) * inv
        w1 = ((a[0] - c[0]) * (py - c[1]) - (a[1] - c[1]) * (px - c[0])) * inv
        w2 = np.float32(1) - w0 - w1
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        sub = out[y0:y1 + 1, x0:x1 + 1]
        sub[inside] = np.maximum(sub[inside], f)
    return out.astype(np.int32)


def add_gutter(texel_face: np.ndarray, rings: int = 2) -> np.ndarray:
    """Empty texels next to covered ones take the largest neighbouring face id, ``rings`` times, so bilinear
    filtering and mipmaps at chart borders read colours of the surface, not of the empty atlas."""
    import cv2

    tf = texel_face.astype(np.float32)                       # face ids < 2^24 are exact in float32
    k = np.ones((3, 3), np.uint8)
    for _ in range(rings):
        grown = cv2.dilate(tf, k)
        empty = tf < 0
        tf = np.where(empty, grown, tf)
    return tf.astype(np.int32)


def texel_bary(texel_face, face_uv) -> np.ndarray:
    size = texel_face.shape[0]
    tcl = TextureCL.get()
    d_tf = tcl.upload("texel_face", np.ascontiguousarray(texel_face, np.int32))
    d_uv = tcl.upload("face_uv", np.ascontiguousarray(face_uv, np.float32))
    d_b = tcl.buffer("texel_bary", 12 * size * size)
    tcl.launch("texel_bary", (size, size), (16, 16), d_tf, np.int32(size), d_uv, d_b)
    return tcl.read(d_b, (size, size, 3), np.float32)


def texel_bary_reference(texel_face, face_uv) -> np.ndarray:
    size = texel_face.shape[0]
    out = np.zeros((size, size, 3), np.float32)
    y, x = np.nonzero(texel_face >= 0)
    f = texel_face[y, x]
    uv = np.asarray(face_uv, np.float32)[f]
    a, b, c = uv[:, 0], uv[:, 1], uv[:, 2]
    px, py = x.astype(np.float32) + np.float32(0.5), y.astype(np.float32) + np.float32(0.5)
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    nz = area != 0
    with np.errstate(invalid="ignore", divide="ignore"):
        w0 = np.where(nz, ((c[:, 0] - b[:, 0]) * (py - b[:, 1]) - (c[:, 1] - b[:, 1]) * (px - b[:, 0])) / area, 0)
        w1 = np.where(nz, ((a[:, 0] - c[:, 0]) * (py - c[:, 1]) - (a[:, 1] - c[:, 1]) * (px - c[:, 0])) / area, 0)
    w2 = np.where(nz, 1 - w0 - w1, 0)
    w = np.maximum(np.stack([w0, w1, w2], axis=1), 0)
    s = w.sum(axis=1, keepdims=True)
    w = np.where(s > 0, w / np.where(s > 0, s, 1), 1 / 3)
    out[y, x] = w
    return out


# ---------------------------------------------------------------- sample baking
def bake_samples(sample_face, sample_bary, vertices, faces, cameras, frame: FrameImages, blend: Blend, *,
                 device_samples=None) -> np.ndarray:
    """(N, 4) float32: colour (0..255) and summed blend weight of each sample (kernel ``bake``).
    ``device_samples``: (face, bary, dest) already on the device (a BakeLayout's: its samples sorted by face,
    ``dest`` (N,) the layout's index of each device sample, where the kernel writes its result), used instead
    of uploading. The blend arrays are read by the device from their host memory (no copy on a CPU device)."""
    import pyopencl as cl

    tcl = TextureCL.get()
    n = len(sample_face)
    K = blend.face_view.shape[1]
    if device_samples is None:
        device_samples = (tcl.upload("s_face", np.ascontiguousarray(sample_face, np.int32)),
                          tcl.upload("s_bary", np.ascontiguousarray(sample_bary, np.float32).reshape(-1)), None)
    *device_samples, dest = device_samples
    keep = [np.ascontiguousarray(a, np.float32) for a in (blend.weight, blend.offset)]   # alive until the read
    args = [*device_samples,
            tcl.upload("verts", np.ascontiguousarray(vertices, np.float32)),
            tcl.upload("faces", np.ascontiguousarray(faces, np.int32)),
            tcl.upload("cams", cameras.pack()),
            frame.device_images(tcl), frame.device_valid(tcl),
            tcl.upload("img_off", frame.offsets.astype(np.int64)),
            np.int32(K),
            tcl.upload("face_view", np.ascontiguousarray(blend.face_view, np.int32)),
            *(tcl.host(a) if a.size else tcl.buffer(f"bake_empty{i}", 4) for i, a in enumerate(keep)),
            tcl.upload("gain", np.ascontiguousarray(blend.gains, np.float32)),
            tcl.upload("face_blur", blend.face_blur()), np.float32(blend.blur_px),
            dest if dest is not None else tcl.buffer("bake_dest", 4), np.int32(dest is not None)]
    d_out = tcl.buffer("bake_out", 16 * max(n, 1))
    out = np.empty((n, 4), np.float32)
    if n:
        tcl.launch("bake", (n,), (64,), np.int32(n), *args, d_out)
        cl.enqueue_copy(tcl.queue, out, d_out)
    del keep
    return out


def bake_samples_reference(sample_face, sample_bary, vertices, faces, cameras, frame: FrameImages, blend: Blend) -> np.ndarray:
    sample_face = np.asarray(sample_face, np.int64)
    b = np.asarray(sample_bary, np.float32).reshape(-1, 3)
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.int64)
    n = len(sample_face)
    out = np.zeros((n, 4), np.float32)
    idx = np.flatnonzero(sample_face >= 0)
    fs = sample_face[idx]
    bb = b[idx]
    X = np.einsum("nc,ncd->nd", bb, v[f[fs]])
    acc = np.zeros((len(idx), 3), np.float32)
    wsum = np.zeros(len(idx), np.float32)
    K = blend.face_view.shape[1]
    for k in range(K):
        view = blend.face_view[fs, k]
        wt = np.einsum("nc,nc->n", bb, blend.weight[fs, :, k])
        off = np.einsum("nc,ncd->nd", bb, blend.offset[fs, :, k, :])
        for vv in np.unique(view[(view >= 0) & (wt > 0)]):
            sel = np.flatnonzero((view == vv) & (wt > 0))
            p, z = cameras.project(X[sel].astype(np.float64), int(vv))
            val = frame.valid[vv]
            h, w = val.shape
            inside = (p[:, 0] > -0.5) & (p[:, 1] > -0.5) & (p[:, 0] < w - 0.5) & (p[:, 1] < h - 0.5) & (z > 1e-6)
            x = np.where(inside, np.floor(p[:, 0] + 0.5), 0).astype(np.int64)
            y = np.where(inside, np.floor(p[:, 1] + 0.5), 0).astype(np.int64)
            ok = inside & (val[y, x] != 0)
            sel, p = sel[ok], p[ok]
            img = frame.images[vv]
            c = _sample_rgb_reference(img, p)
            bl = blend.face_blur()[fs[sel]][:, None]
            r = np.float32(blend.blur_px)
            cross5 = c + sum(_sample_rgb_reference(img, p + d) for d in ((r, 0), (-r, 0), (0, r), (0, -r)))
            c = np.where(bl > 0, (1 - bl) * c + bl * np.float32(0.2) * cross5, c)
            c = c * blend.gains[vv] + off[sel]
            acc[sel] += wt[sel, None] * c
            wsum[sel] += wt[sel]
    good = wsum > 0
    out[idx[good], :3] = acc[good] / wsum[good, None]
    out[idx[good], 3] = wsum[good]
    return out


# ---------------------------------------------------------------- filling
def _pyramid_fill(c, wt):
    """Coarse colour sums ``c`` (h, w, 3) and known fractions ``wt`` (h, w), both area-averaged: every cell
    gets its own mean where it has known texels, the coarser levels' fill where it has few or none."""
    import cv2

    levels = []
    while True:
        levels.append((c, wt))
        if min(wt.shape) <= 1:
            break
        c = cv2.resize(c, ((c.shape[1] + 1) // 2, (c.shape[0] + 1) // 2), interpolation=cv2.INTER_AREA)
        wt = cv2.resize(wt, ((wt.shape[1] + 1) // 2, (wt.shape[0] + 1) // 2), interpolation=cv2.INTER_AREA)
    c, wt = levels[-1]
    filled = np.divide(c, wt[..., None], out=np.full_like(c, 128.0), where=wt[..., None] > 0)
    for c, wt in reversed(levels[:-1]):
        up = cv2.resize(filled, (wt.shape[1], wt.shape[0]), interpolation=cv2.INTER_LINEAR)
        if up.ndim == 2:
            up = up[..., None]
        mine = np.divide(c, wt[..., None], out=np.zeros_like(c), where=wt[..., None] > 0)
        a = np.clip(wt * 4, 0, 1)[..., None]
        filled = a * mine + (1 - a) * up
    return filled


def push_pull(rgb: np.ndarray, known: np.ndarray, coarse: int = 16) -> np.ndarray:
    """Fill unknown texels (outside the charts and their gutter) with a smooth extension of the known ones:
    a pyramid of weighted averages down to 1/``coarse`` resolution (holes there filled from coarser levels),
    upsampled once. Known texels are unchanged. Keeps mipmaps and PNG compression clean. (Full-image version of
    ``fill_texture``, which works on a BakeLayout's compact texels.)"""
    import cv2

    h, w = known.shape
    wt = known.astype(np.float32)
    c = rgb.astype(np.float32) * wt[..., None]
    ch, cw = max(1, -(-h // coarse)), max(1, -(-w // coarse))
    c = cv2.resize(c, (cw, ch), interpolation=cv2.INTER_AREA)
    wt = cv2.resize(wt, (cw, ch), interpolation=cv2.INTER_AREA)
    filled = _pyramid_fill(c, wt)
    up = cv2.resize(filled, (w, h), interpolation=cv2.INTER_LINEAR)
    return np.where(known[..., None], rgb, up)


def fill_texture(colour: np.ndarray, layout) -> np.ndarray:
    """The (S, S, 3) uint8 texture: the baked colours (N, 3) of a BakeLayout's texels, every other texel
    filled as ``push_pull`` does (block means at 1/16 resolution by bincount over the layout's cells, a
    pyramid there, one bilinear upsampling)."""
    import cv2

    s = layout.size
    ch, cw = layout.coarse_shape
    n = ch * cw
    area = layout.cell_area.reshape(-1)
    wt = (layout.cell_count / area).reshape(ch, cw).astype(np.float32)
    # one bincount over (cell, channel): per bin the same texels in the same order as one per channel
    # (the values as float64 and the bins as intp, what bincount works in: it converted them itself, 2-3x slower)
    c64 = np.ascontiguousarray(colour, np.float64)
    c = np.bincount(layout.cell_channel, c64.reshape(-1), minlength=3 * n).reshape(n, 3)
    c /= area[:, None]
    filled = _pyramid_fill(c.reshape(ch, cw, 3).astype(np.float32), wt)
    c16 = layout.COARSE                                       # cells of c16 texels (the last ones partial)
    up = cv2.resize(np.clip(filled + 0.5, 0, 255).astype(np.uint8), (cw * c16, ch * c16),
                    interpolation=cv2.INTER_LINEAR)[:s, :s]
    up = np.ascontiguousarray(up)
    v = np.add(c64, 0.5, out=c64)                             # as np.clip(colour + 0.5, 0, 255) in float64
    np.maximum(v, 0, out=v)
    np.minimum(v, 255, out=v)
    up.reshape(-1)[layout.texel_channel] = v.astype(np.uint8).reshape(-1)   # 1-D: rows of 3 were 4x slower
    return up

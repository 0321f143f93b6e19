"""Silhouette extraction ("keying"): chroma key, difference key, grey threshold, clean-up, multi-view consensus.

Per-pixel work runs in OpenCL (kernels/key.cl); each kernel has a NumPy reference here (``*_reference``)
computing the same thing, which the tests compare against the kernel on small images. ``chroma_key_bits`` is
the real-time path: the chroma key written straight into the hull's device silhouettes
(nodes.hull.SilhouetteBits). The CPU parts that a library does well (morphology, connected components, hole
filling) use OpenCV.

References: Horprasert, Harwood & Davis 1999 (brightness/chromaticity distortion); Prati et al. 2003
(shadows keep the background's chromaticity); Rother, Kolmogorov & Blake 2004 GrabCut (OpenCV) re-decides the
boundary band where colour alone cannot (hair against a dark wall); Zivkovic 2004 MOG2 is the baseline in
bench/key.py.
"""
from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

from kernels import source
from nodegraph import NodeError, clrt
from nodes.common.cameras import Cameras
from nodes.common.silhouettes import SilhouetteBits, check_sizes
from nodes.common.types import MaskSet, _mask_of_levels

KERNELS = source("key.cl")


# ---------------------------------------------------------------- colour helpers
def rgb_to_ycc(rgb: np.ndarray) -> np.ndarray:
    """BT.601 full-range YCbCr with chroma centred on 0, float32 (..., 3)."""
    c = rgb.astype(np.float32)
    y = np.float32(0.299) * c[..., 0] + np.float32(0.587) * c[..., 1] + np.float32(0.114) * c[..., 2]
    return np.stack([y, np.float32(0.564) * (c[..., 2] - y), np.float32(0.713) * (c[..., 0] - y)], axis=-1)


def ycc_to_rgb(ycc: np.ndarray) -> np.ndarray:
    y, cb, cr = ycc[..., 0], ycc[..., 1], ycc[..., 2]
    r = y + cr / np.float32(0.713)
    b = y + cb / np.float32(0.564)
    g = (y - np.float32(0.299) * r - np.float32(0.114) * b) / np.float32(0.587)
    return np.stack([r, g, b], axis=-1)


def estimate_key_direction(rgb: np.ndarray, border: int = 16) -> np.ndarray:
    """Unit CbCr direction of the screen colour: median chroma of the most saturated quarter of the pixels
    in a strip around the image, ``border`` pixels wide (at most a tenth of the short side), so dark or
    neutral border pixels are ignored. (``rgb_to_ycc``'s arithmetic on the strip's channels as contiguous rows,
    and the chroma's length as the float32 rounding of the double square root (IEEE: exact squares, one rounded
    sum, a correctly rounded root), which is glibc's hypotf: equal for all 2^24 colours; ~2x faster than the
    reference in all.)"""
    border = max(1, min(border, min(rgb.shape[:2]) // 10))
    strip = np.concatenate([rgb[:border].reshape(-1, 3), rgb[-border:].reshape(-1, 3),
                            rgb[:, :border].reshape(-1, 3), rgb[:, -border:].reshape(-1, 3)])
    r, g, b = np.ascontiguousarray(strip.T).astype(np.float32)
    f = np.float32
    y = f(0.299) * r + f(0.587) * g + f(0.114) * b
    cb, cr = f(0.564) * (b - y), f(0.713) * (r - y)
    chroma = np.sqrt(np.square(cb, dtype=np.float64) + np.square(cr, dtype=np.float64)).astype(np.float32)
    sel = chroma >= np.percentile(chroma, 75)
    return key_direction_from_ycc(np.median(cb[sel]), np.median(cr[sel]))


def estimate_key_direction_reference(rgb: np.ndarray, border: int = 16) -> np.ndarray:
    """``estimate_key_direction`` through ``rgb_to_ycc`` (what it must equal)."""
    border = max(1, min(border, min(rgb.shape[:2]) // 10))
    strip = np.concatenate([rgb[:border].reshape(-1, 3), rgb[-border:].reshape(-1, 3),
                            rgb[:, :border].reshape(-1, 3), rgb[:, -border:].reshape(-1, 3)])
    ycc = rgb_to_ycc(strip)
    chroma = np.hypot(ycc[:, 1], ycc[:, 2])
    sel = chroma >= np.percentile(chroma, 75)
    return key_direction_from_ycc(np.median(ycc[sel, 1]), np.median(ycc[sel, 2]))


def key_direction_from_ycc(cb: float, cr: float) -> np.ndarray:
    n = float(np.hypot(cb, cr))
    if n < 1e-3:
        raise NodeError("key.chroma: the key colour has no chroma (grey or black); give key_color explicitly")
    return np.array([cb / n, cr / n], dtype=np.float32)


def key_direction_from_rgb(rgb) -> np.ndarray:
    ycc = rgb_to_ycc(np.asarray(rgb, dtype=np.float32).reshape(1, 3))[0]
    return key_direction_from_ycc(ycc[1], ycc[2])


# ---------------------------------------------------------------- garbage matte
_mattes: "OrderedDict[tuple, np.ndarray]" = OrderedDict()
_mattes_lock = threading.Lock()
MATTES = 256        # garbage mattes kept per process (a static rig's are made once, not every frame)


def matte_edges(cameras: Cameras, view: int, bounds: np.ndarray, margin: float = 8.0) -> np.ndarray:
    """Edges of the convex hull of the capture box's projection into ``view``, as (E, 4) float32 rows
    (a, b, c, 0): a pixel (x, y) is inside when a*x + b*y + c >= 0 for all rows. ``margin`` pixels of slack.
    The box's 12 edges are sampled (not just its corners), so lens distortion bending them is followed.
    Returns an empty array (no matte) when part of the box lies behind the camera. Kept per process by what the
    projection reads (the camera's K, Rt, distortion and depth sign, the box, the margin): 24 HD views took
    9 ms a frame (idle), the same every frame of a static rig."""
    cam = cameras.cameras[view]
    key = (cam.K.tobytes(), cam.Rt.tobytes(), cam.dist.tobytes(), bool(cam.metric), cam.depth_sign,
           np.asarray(bounds, np.float64).tobytes(), float(margin))
    with _mattes_lock:
        edges = _mattes.get(key)
        if edges is not None:
            _mattes.move_to_end(key)
    if edges is None:
        edges = _matte_edges(cameras, view, bounds, margin)
        with _mattes_lock:
            _mattes[key] = edges
            while len(_mattes) > MATTES:
                _mattes.popitem(last=False)
    return edges.copy()


# the capture box's corners (0 = its low, 1 = its high value per axis), its 12 edges as corner pairs, 9 samples each
_BOX_CORNERS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)])
_BOX_EDGES = np.array([(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1])
_BOX_T = np.linspace(0, 1, 9)[:, None]


def _outline(cameras: Cameras, view: int, pts: np.ndarray) -> np.ndarray | None:
    """The convex hull (K, 2) float64 of points' projections into ``view``; None when a point lies behind the
    camera or does not project, or the hull has no area."""
    import cv2

    uv, depth = cameras.project(pts, view)
    if np.any(depth <= 0) or not np.all(np.isfinite(uv)):
        return None
    hull = cv2.convexHull(uv.astype(np.float32), clockwise=False)[:, 0, :].astype(np.float64)
    return hull if len(hull) >= 3 else None


def _matte_edges(cameras: Cameras, view: int, bounds: np.ndarray, margin: float) -> np.ndarray:
    lo, hi = np.asarray(bounds)                       # in the box's own type, as the reference's corners
    corners = np.where(_BOX_CORNERS == 0, lo, hi)
    a, b = corners[_BOX_EDGES[:, 0]], corners[_BOX_EDGES[:, 1]]
    hull = _outline(cameras, view, (a[:, None, :] + _BOX_T[None] * (b - a)[:, None, :]).reshape(-1, 3))
    if hull is None:
        return np.zeros((0, 4), np.float32)
    nxt = np.roll(hull, -1, axis=0)
    area2 = np.sum(hull[:, 0] * nxt[:, 1] - nxt[:, 0] * hull[:, 1])
    d = nxt - hull
    n = np.stack([-d[:, 1], d[:, 0]], axis=1) * np.sign(area2)      # inward normals
    n /= np.sqrt(n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1])[:, None] + 1e-12
    edges = np.zeros((len(hull), 4))
    edges[:, :2] = n
    edges[:, 2] = -(n[:, 0] * hull[:, 0] + n[:, 1] * hull[:, 1]) + margin
    return edges.astype(np.float32)


def _matte_edges_reference(cameras: Cameras, view: int, bounds: np.ndarray, margin: float) -> np.ndarray:
    """``_matte_edges`` with Python loops (the plain version it is tested against; the projection and hull shared)."""
    lo, hi = bounds
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pairs = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]
    t = np.linspace(0, 1, 9)[:, None]
    hull = _outline(cameras, view, np.concatenate([corners[i] + t * (corners[j] - corners[i]) for i, j in pairs]))
    if hull is None:
        return np.zeros((0, 4), np.float32)
    area2 = np.sum(hull[:, 0] * np.roll(hull[:, 1], -1) - np.roll(hull[:, 0], -1) * hull[:, 1])
    edges = []
    for p, q in zip(hull, np.roll(hull, -1, axis=0)):
        d = q - p
        n = np.array([-d[1], d[0]]) * np.sign(area2)  # inward normal
        n /= np.linalg.norm(n) + 1e-12
        edges.append([n[0], n[1], -n @ p + margin, 0.0])
    return np.asarray(edges, np.float32)


def matte_reference(edges: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Boolean (H, W): inside all matte edges (all True when there are none)."""
    ys, xs = np.mgrid[: shape[0], : shape[1]].astype(np.float32)
    inside = np.ones(shape, bool)
    for a, b, c, _ in edges:
        inside &= a * xs + b * ys + c >= 0
    return inside


# ---------------------------------------------------------------- NumPy references of the kernels
def chroma_key_reference(rgb, key, *, side=1.0, luma_floor=16.0, inner=0.05, outer=0.2, black=0.0, spill=1.0,
                         edges=None):
    """Foreground alpha (uint8 0..255) and despilled RGB of one image; see ``chroma_key`` in kernels/key.cl."""
    f = np.float32
    ycc = rgb_to_ycc(rgb)
    y, cb, cr = ycc[..., 0], ycc[..., 1], ycc[..., 2]
    along = cb * f(key[0]) + cr * f(key[1])
    across = np.abs(cb * f(key[1]) - cr * f(key[0]))
    s = (along - f(side) * across) / np.maximum(y, f(luma_floor))
    a = f(1) - np.clip((s - f(inner)) / (f(outer) - f(inner)), 0, 1)
    a = a * np.clip((y - f(black)) * f(0.25), 0, 1)
    if edges is not None and len(edges):
        a = np.where(matte_reference(edges, rgb.shape[:2]), a, f(0))
    alpha = np.rint(a * f(255)).astype(np.uint8)
    remove = f(spill) * np.maximum(along, 0)
    ycc = np.stack([y, cb - remove * f(key[0]), cr - remove * f(key[1])], axis=-1)
    despilled = np.clip(np.rint(ycc_to_rgb(ycc)), 0, 255).astype(np.uint8)
    return alpha, despilled


def difference_key_reference(rgb, mean, inv_var, *, cd_inner=4.0, cd_outer=8.0, shadow=0.5, highlight=1.2,
                             still=3.0):
    """Foreground alpha (uint8) and class (0 background, 1 shadow, 2 foreground) against a Gaussian plate
    model (mean, 1/sigma^2 per channel); see ``difference_key`` in kernels/key.cl."""
    I = rgb.astype(np.float32)
    E, w = mean.astype(np.float32), inv_var.astype(np.float32)
    b = np.sum(I * E * w, -1) / np.maximum(np.sum(E * E * w, -1), np.float32(1e-6))
    cd = np.sqrt(np.sum((I - b[..., None] * E) ** 2 * w, -1))
    dist = np.sqrt(np.sum((I - E) ** 2 * w, -1))
    a = np.clip((cd - np.float32(cd_inner)) / np.float32(cd_outer - cd_inner), 0, 1)
    a = np.where(((b < shadow) | (b > highlight)) & (dist > still), np.float32(1), a)
    a = np.where(dist <= still, np.float32(0), a)
    label = np.where(a >= 0.5, 2, np.where((b < 1) & (dist > still), 1, 0)).astype(np.uint8)
    return np.rint(a * np.float32(255)).astype(np.uint8), label


def grey_threshold_reference(rgb, t, use_max=False):
    c = rgb.astype(np.float32)
    g = c.max(-1) if use_max else (c[..., 0] + c[..., 1] + c[..., 2]) * np.float32(1 / 3)
    return np.where(g > np.float32(t), 255, 0).astype(np.uint8)


# ---------------------------------------------------------------- OpenCL
class KeyCL(clrt.Runner):
    """The key kernels (kernels/key.cl); buffers kept between frames, so same-size frames allocate once."""

    source = KERNELS


CHROMA_PIX = 16  # pixels per work item of the chroma_key and difference_key kernels
CHROMA_GROUP = 64  # work-group size (PoCL's own choice was slower)
BITS_GROUP = 8  # work-group size of chroma_key_bits (PoCL's own choice ran the ~136 rows on one thread)
BOX_GROUP = (16, 1)  # work-group of the box kernels: fixed, so PoCL builds them once (left to PoCL, every new box size
                     # got a work-group of its own, and each such variant is compiled: ~0.1-0.25 s, once per cache)


def chroma_key_cl(rgb, key, *, side=1.0, luma_floor=16.0, inner=0.05, outer=0.2, black=0.0, spill=1.0, edges=None,
                  despill=True, timings=None):
    """OpenCL ``chroma_key`` on one (H, W, 3) uint8 image: (alpha uint8 (H, W), despilled (H, W, 3) or None
    when ``despill`` is false). ``timings``, a dict, receives the seconds of upload / kernel / download
    (this waits for each step, so leave it None outside benchmarks)."""
    from pyopencl import cltypes

    run = KeyCL.get()
    h, w = rgb.shape[:2]
    npix = h * w
    edges = np.zeros((0, 4), np.float32) if edges is None else np.asarray(edges, np.float32)
    clock = _Clock(timings)
    src = run.host(rgb)
    spans = run.buffer("matte_spans", 8 * h)  # inside span of each row
    if len(edges):
        run.launch("matte_rows", h, None, run.upload("edges", edges), np.int32(len(edges)), np.int32(w), np.int32(h), spans)
    clock.lap("upload")
    alpha, desp = run.buffer("alpha", npix), run.buffer("rgb_out", npix * 3 if despill else 1)
    f = np.float32
    run.launch("chroma_key", -(-npix // CHROMA_PIX), CHROMA_GROUP, src, np.int32(npix),
               cltypes.make_float2(*map(float, key)), f(side), f(luma_floor), f(inner), f(1.0 / (outer - inner)),
               f(black), f(spill), np.int32(w), spans, np.int32(len(edges) > 0), alpha, np.int32(bool(despill)), desp)
    clock.lap("kernel")
    out = run.read(alpha, (h, w)), (run.read(desp, (h, w, 3)) if despill else None)
    clock.lap("download")
    return out


def alpha_window(alpha: np.ndarray, margin: int, offset=(0, 0), size=None) -> tuple[int, int, int, int]:
    """The box (x0, y0, x1, y1) of ``alpha`` > 0 grown by ``margin`` pixels and clipped to the image; (0, 0, 0, 0)
    when the alpha is empty. ``alpha`` may be a part of the image: at ``offset`` (x, y) of an image of ``size``
    (w, h)."""
    import cv2

    h, w = alpha.shape if size is None else size[::-1]
    x, y, bw, bh = cv2.boundingRect(alpha)  # an image: the box of its non-zero pixels
    if bw == 0 or bh == 0:
        return 0, 0, 0, 0
    x, y = x + offset[0], y + offset[1]
    return max(0, x - margin), max(0, y - margin), min(w, x + bw + margin), min(h, y + bh + margin)


def chroma_key_windowed(rgb, key, *, margin=16, side=1.0, luma_floor=16.0, inner=0.05, outer=0.2, black=0.0,
                        spill=1.0, edges=None, out=None, crop=False):
    """``chroma_key_cl`` with the despilled image made only inside the window of the alpha (``alpha_window``:
    its box grown by ``margin`` pixels) and black outside: (alpha, despilled, window). Inside the window the
    bytes are ``chroma_key_cl``'s; the despill runs and is read back on the window alone (24 HD views of the
    synthetic figure: a fifth of the pixels). With a garbage matte (``edges``) the alpha is keyed on the box of
    the matte alone (``chroma_key_box``: a third of the demo's HD pixels), the same bytes. ``out``: a zeroed
    (H, W, 3) uint8 array to write the despilled image into. ``crop``: the
    despilled window's pixels alone, (y1 - y0, x1 - x0, 3), instead of a whole image."""
    from pyopencl import cltypes

    h, w = rgb.shape[:2]
    if edges is not None and len(edges):
        alpha, (bx, by) = chroma_key_box(rgb, key, edges, side=side, luma_floor=luma_floor, inner=inner, outer=outer,
                                         black=black)
        x0, y0, x1, y1 = alpha_window(alpha[by[0]:by[1], bx[0]:bx[1]], margin, offset=(bx[0], by[0]), size=(w, h))
    else:
        alpha, _ = chroma_key_cl(rgb, key, side=side, luma_floor=luma_floor, inner=inner, outer=outer, black=black,
                                 spill=spill, edges=edges, despill=False)
        x0, y0, x1, y1 = alpha_window(alpha, margin)
    bw, rows = x1 - x0, y1 - y0
    if crop:
        out = np.empty((rows, bw, 3), np.uint8)
    elif out is None:
        out = np.zeros((h, w, 3), np.uint8)
    if bw > 0 and rows > 0:
        import pyopencl as cl

        run = KeyCL.get()
        box = run.buffer("despill_box", rows * bw * 3)
        run.launch("despill_box", (-(-bw // CHROMA_PIX), rows), BOX_GROUP, run.host(rgb), np.int32(w), np.int32(x0),
                   np.int32(y0), np.int32(bw), cltypes.make_float2(*map(float, key)), np.float32(spill), box)
        if crop:
            cl.enqueue_copy(run.queue, out, box, is_blocking=True)
        else:
            cl.enqueue_copy(run.queue, out, box, buffer_origin=(0, 0), host_origin=(3 * x0, y0), region=(3 * bw, rows),
                            buffer_pitches=(3 * bw,), host_pitches=(3 * w,), is_blocking=True)
    return alpha, out, [x0, y0, x1, y1]


def chroma_key_box(rgb, key, edges, *, side=1.0, luma_floor=16.0, inner=0.05, outer=0.2, black=0.0):
    """``chroma_key_cl``'s alpha (no despill) of one image with a garbage matte (``edges``), keyed on the box of
    the matte's row spans alone (kernel chroma_key_box) and 0 beyond, as it is there: (alpha (H, W) uint8 with
    pages beyond the box untouched, ((x0, x1), (y0, y1)) the box, empty where the matte is)."""
    import pyopencl as cl
    from pyopencl import cltypes

    run = KeyCL.get()
    h, w = rgb.shape[:2]
    spans = run.buffer("matte_spans", 8 * h)
    run.launch("matte_rows", h, None, run.upload("edges", np.asarray(edges, np.float32)), np.int32(len(edges)),
               np.int32(w), np.int32(h), spans)
    sp = run.read(spans, (h, 2), np.int32)
    inside = np.flatnonzero(sp[:, 1] > sp[:, 0])
    alpha = np.zeros((h, w), np.uint8)
    if not len(inside):
        return alpha, ((0, 0), (0, 0))
    y0, y1 = int(inside[0]), int(inside[-1]) + 1
    x0, x1 = int(sp[inside, 0].min()), int(sp[inside, 1].max())
    bw, rows = x1 - x0, y1 - y0
    box = run.buffer("alpha_box", rows * bw)
    f = np.float32
    run.launch("chroma_key_box", (-(-bw // CHROMA_PIX), rows), BOX_GROUP, run.host(rgb), np.int32(w), np.int32(x0),
               np.int32(y0), np.int32(bw), cltypes.make_float2(*map(float, key)), f(side), f(luma_floor), f(inner),
               f(1.0 / (outer - inner)), f(black), spans, box)
    cl.enqueue_copy(run.queue, alpha, box, buffer_origin=(0, 0), host_origin=(x0, y0), region=(bw, rows),
                    buffer_pitches=(bw,), host_pitches=(w,), is_blocking=True)
    return alpha, ((x0, x1), (y0, y1))


def chroma_key_bits(images, key, *, side=1.0, luma_floor=16.0, inner=0.05, outer=0.2, black=0.0, edges=None,
                    out=None):
    """The chroma key's silhouettes (alpha >= 128, the key.chroma node's masks) of (H, W, 3) uint8 ``images``
    (``key``: one key direction for all, or one per image)
    straight into the visual hull's device layout: ``nodes.hull.SilhouetteBits`` (bits and 8x8 block tables),
    with no alpha written, read back or re-packed; ``visual_hull`` takes the result as its masks. ``edges``:
    a garbage matte per view (``matte_edges``) or None; pixels outside the matte are not even read.
    ``out``: the SilhouetteBits of the previous frame, to reuse (overwritten). Returns when the device is done
    (the images may then change)."""
    from pyopencl import cltypes

    for v, im in enumerate(images):
        if im.dtype != np.uint8 or im.ndim != 3 or im.shape[2] != 3:
            raise NodeError(f"key.chroma: image {v} must be (H, W, 3) uint8, got {im.dtype} {im.shape}")
    if outer <= inner:
        raise NodeError(f"key.chroma: 'outer' ({outer}) must be larger than 'inner' ({inner})")
    mattes = [np.zeros((0, 4), np.float32) if e is None else np.asarray(e, np.float32).reshape(-1, 4)
              for e in (edges if edges is not None else [None] * len(images))]
    if len(mattes) != len(images):
        raise NodeError(f"key.chroma: {len(images)} images but {len(mattes)} garbage mattes")
    keys = [key] * len(images) if np.ndim(key) == 1 else list(key)
    if len(keys) != len(images):
        raise NodeError(f"key.chroma: {len(images)} images but {len(keys)} key colours")
    sizes = [(im.shape[1], im.shape[0]) for im in images]
    sil = SilhouetteBits.reuse(out, sizes)
    first = np.concatenate([[0], np.cumsum([len(e) for e in mattes])])
    run = KeyCL.get()
    ebuf = run.upload("edges_all", np.concatenate([*mattes, np.zeros((1, 4), np.float32)]))
    f = np.float32
    host = []
    for v, im in enumerate(images):
        src = run.host(im)
        host.append(src)
        w, h = sizes[v]
        rows = (h + 7) // 8 + 1  # work items: rows of the block table
        run.launch("chroma_key_bits", rows, BITS_GROUP, src, np.int32(w), np.int32(h), cltypes.make_float2(*map(float, keys[v])),
                   f(side), f(luma_floor), f(inner), f(1.0 / (outer - inner)), f(black), ebuf, np.int32(first[v]),
                   np.int32(len(mattes[v])), sil.bits, np.int32(sil.bit_off[v]), sil.sat, np.int32(sil.sat_off[v]))
    sil.prefix_columns()
    run.finish()  # the images' zero-copy buffers must outlive the kernels
    return sil


class _Clock:
    """Wall time per step of an OpenCL call, when asked for (finishes the queue at each lap)."""

    def __init__(self, timings: dict | None):
        import time

        self.timings, self.now = timings, time.perf_counter
        self.t = self.now()

    def lap(self, step: str):
        if self.timings is None:
            return
        KeyCL.get().finish()
        t = self.now()
        self.timings[step] = self.timings.get(step, 0.0) + t - self.t
        self.t = t


def difference_key_cl(rgb, mean, inv_var, *, cd_inner=4.0, cd_outer=8.0, shadow=0.5, highlight=1.2, still=3.0):
    """OpenCL ``difference_key`` on one (H, W, 3) uint8 image against a plate model (mean, inv_var: (H, W, 3)
    float32; read in place, not copied): (alpha uint8 (H, W), class uint8 (H, W))."""
    run = KeyCL.get()
    h, w = rgb.shape[:2]
    npix = h * w
    f = np.float32
    bufs = run.host(rgb), run.host(np.asarray(mean, f)), run.host(np.asarray(inv_var, f))
    alpha, label = run.buffer("alpha", npix), run.buffer("label", npix)
    run.launch("difference_key", -(-npix // CHROMA_PIX), CHROMA_GROUP, *bufs, np.int32(npix), f(cd_inner), f(cd_outer),
               f(shadow), f(highlight), f(still), alpha, label)
    return run.read(alpha, (h, w)), run.read(label, (h, w))


def grey_threshold_cl(rgb, t, use_max=False):
    run = KeyCL.get()
    h, w = rgb.shape[:2]
    npix = h * w
    out = run.buffer("alpha", npix)
    run.launch("grey_threshold", npix, None, run.host(rgb), np.int32(npix), np.float32(t), np.int32(bool(use_max)), out)
    return run.read(out, (h, w))


# ---------------------------------------------------------------- mask clean-up and consensus (CPU, OpenCV)
def disc(radius: int) -> np.ndarray:
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def clean_mask(mask: np.ndarray, *, open_px=1, close_px=2, keep=1, fill_holes=True) -> np.ndarray:
    """``clean_mask_box``'s mask alone."""
    return clean_mask_box(mask, open_px=open_px, close_px=close_px, keep=keep, fill_holes=fill_holes)[0]


def clean_mask_box(mask: np.ndarray, *, open_px=1, close_px=2, keep=1, fill_holes=True, hint=None):
    """Binary (0/255) mask after opening, closing, keeping the ``keep`` largest 8-connected components
    (0 = all) and filling holes (background regions not connected to the image border).

    The work is done on the foreground's bounding box grown by ``open_px + close_px + 1`` (clipped to the image),
    with the same result as on the whole image (``clean_mask_reference``): outside that box the result is
    background whatever is done; a structuring element reaching out of it from a pixel that matters meets the
    margin's background first (the discs are convex), so the morphology is the same; the components and their
    areas are the same; and the margin is a ring of background joined to the image border, so what the hole
    filling reaches is the same. Only the order of equal-sized components may differ (OpenCV numbers them by
    its 2x2-block scan): when the ``keep``-th and the next largest have the same area, the whole image is
    cleaned instead. A figure filling a tenth of a 640x480 view: ~5x less work; the areas counted from the
    labels, not OpenCV's statistics: 12 crops' labelling ~8 -> ~3 ms; none counted where no more components than
    kept are found (an HD view: clean-up 5.6 -> 1.9 ms).

    Returns (mask, box): ``box`` (x0, y0, x1, y1) the region worked on, 0 outside it (None: the whole image).
    ``hint`` (x0, y0, x1, y1): a box the input's foreground lies in (a key's alpha window): the threshold and the
    foreground's box are taken there alone, not over the whole frame (the same result)."""
    import cv2

    mask = np.asarray(mask)
    h, w = mask.shape[:2]
    hx0, hy0, hx1, hy1 = (0, 0, w, h) if hint is None else (int(v) for v in hint)
    if hx1 <= hx0 or hy1 <= hy0:   # an empty hint: no foreground
        return np.zeros((h, w), np.uint8), (0, 0, 0, 0)
    sub = mask[hy0:hy1, hx0:hx1]
    m = cv2.threshold(sub, 127, 1, cv2.THRESH_BINARY)[1] if sub.dtype == np.uint8 else (sub > 127).astype(np.uint8)
    box = _foreground_box(m, open_px + close_px + 1, offset=(hx0, hy0), size=(w, h))
    if box is None:   # no foreground: nothing to keep or fill
        return np.zeros((h, w), np.uint8), (0, 0, 0, 0)
    (y0, y1), (x0, x1) = box
    whole = dict(open_px=open_px, close_px=close_px, keep=keep, fill_holes=fill_holes)
    if hint is not None and (y0 < hy0 or x0 < hx0 or y1 > hy1 or x1 > hx1):   # the margin reaches out of the hint
        return clean_mask_box(mask, **whole)
    part = _clean_binary(m[y0 - hy0:y1 - hy0, x0 - hx0:x1 - hx0], open_px, close_px, keep, fill_holes, ties=False)
    if part is None:   # ties at the keep cut: the whole image (OpenCV's numbering decides, as on it)
        if hint is not None:
            return clean_mask_box(mask, **whole)
        return _clean_binary(m, open_px, close_px, keep, fill_holes) * np.uint8(255), None
    out = np.zeros((h, w), np.uint8)
    out[y0:y1, x0:x1] = part * np.uint8(255)
    return out, (x0, y0, x1, y1)


def _foreground_box(m: np.ndarray, margin: int, offset=(0, 0), size=None):
    """((y0, y1), (x0, x1)) of the nonzero pixels of ``m`` grown by ``margin`` and clipped to the image, or None.
    ``m`` may be a part of the image: at ``offset`` (x, y) of an image of ``size`` (w, h)."""
    import cv2

    x, y, w, h = cv2.boundingRect(m)
    if w == 0 or h == 0:
        return None
    x, y = x + offset[0], y + offset[1]
    W, H = (m.shape[1], m.shape[0]) if size is None else size
    return ((max(y - margin, 0), min(y + h + margin, H)), (max(x - margin, 0), min(x + w + margin, W)))


def _clean_binary(m: np.ndarray, open_px: int, close_px: int, keep: int, fill_holes: bool, ties: bool = True):
    """The clean-up of a 0/1 uint8 mask (see ``clean_mask``), 0/1 uint8; None when ``ties`` is false and the
    components kept would depend on how OpenCV numbers equal-sized ones."""
    import cv2

    if open_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, disc(open_px))
    if close_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, disc(close_px))
    if keep > 0:
        # labels without OpenCV's statistics (their boxes and centroids cost twice the labelling), 16-bit where
        # no image of this size can have more components; the areas by counting
        most = ((m.shape[0] + 1) // 2) * ((m.shape[1] + 1) // 2)
        n, labels = cv2.connectedComponents(m, connectivity=8, ltype=cv2.CV_16U if most < 65535 else cv2.CV_32S)
        if n - 1 > keep:   # more components than kept (at most ``keep``: all of them, ``m`` as it is)
            area = np.bincount(labels.ravel(), minlength=n)
            order = 1 + np.argsort(-area[1:], kind="stable")
            if not ties and keep < n - 1 and area[order[keep - 1]] == area[order[keep]]:
                return None
            order = order[:keep]
            m = (labels == order[0]).astype(np.uint8) if keep == 1 else np.isin(labels, order).astype(np.uint8)
    if fill_holes:
        # background reachable from the border, via a 1-pixel frame so every border pixel is a seed
        framed = np.pad(m, 1)
        cv2.floodFill(framed, None, (0, 0), 2)
        m = (framed[1:-1, 1:-1] != 2).astype(np.uint8)
    return m


def clean_mask_reference(mask: np.ndarray, *, open_px=1, close_px=2, keep=1, fill_holes=True) -> np.ndarray:
    """What ``clean_mask`` must equal: the clean-up on the whole image, components by OpenCV's statistics."""
    import cv2

    m = (mask > 127).astype(np.uint8)
    if open_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, disc(open_px))
    if close_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, disc(close_px))
    if keep > 0:
        n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        if n > 1:
            order = 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA], kind="stable")[:keep]
            m = np.isin(labels, order).astype(np.uint8)
    if fill_holes:
        framed = np.pad(m, 1)
        cv2.floodFill(framed, None, (0, 0), 2)
        m = (framed[1:-1, 1:-1] != 2).astype(np.uint8)
    return m * 255


def cleaned_alpha(cleaned: np.ndarray, mask: np.ndarray, alpha: np.ndarray, hint=None) -> np.ndarray:
    """The soft alpha that goes with a cleaned mask: ``alpha`` where the mask was kept as it was, opaque where the
    clean-up added foreground (filled holes, closed cracks), 0 where it removed it or there was none; computed
    on the cleaned mask's bounding box (outside it all 0). Same as ``cleaned_alpha_reference``. A uint8 ``alpha``
    (8-bit levels) gives levels (opaque = 255), a float alpha float32 (opaque = 1): levels / 255 are the float's."""
    import cv2

    from nodes.common.types import bounding_rect

    levels = alpha.dtype == np.uint8
    out = np.zeros(cleaned.shape, np.uint8 if levels else np.float32)
    x, y, w, h = bounding_rect(cleaned, hint)      # ``hint``: a box the cleaned mask lies in (its clean-up's)
    if w and h:
        box = np.s_[y:y + h, x:x + w]
        if levels:   # bytes: cleaned (0 / 255) AND (alpha OR NOT mask): alpha where kept, 255 where added, 0 elsewhere
            keep = cv2.threshold(np.asarray(mask)[box], 127, 255, cv2.THRESH_BINARY)[1]
            c = cv2.threshold(np.asarray(cleaned)[box], 0, 255, cv2.THRESH_BINARY)[1]
            out[box] = cv2.bitwise_and(c, cv2.bitwise_or(np.asarray(alpha)[box], cv2.bitwise_not(keep)))
        else:
            out[box] = cleaned_alpha_reference(cleaned[box], np.asarray(mask)[box], np.asarray(alpha)[box])
    return out


def cleaned_alpha_reference(cleaned: np.ndarray, mask: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    if alpha.dtype == np.uint8:
        return np.where(cleaned > 0, np.where(mask > 127, alpha, np.uint8(255)), np.uint8(0)).astype(np.uint8)
    return np.where(cleaned > 0, np.where(mask > 127, alpha, 1.0), 0.0).astype(np.float32)


def surface_centres(volume) -> np.ndarray:
    """(N, 3) centres of the occupied voxels of ``volume`` that touch an empty one or the grid's border."""
    from scipy import ndimage

    occ = volume.occupancy > (0.5 if volume.occupancy.dtype.kind == "f" else 0)
    if not occ.any():
        return np.zeros((0, 3))
    surface = occ & ~ndimage.binary_erosion(occ, border_value=0)
    return volume.bbox_min + (np.argwhere(surface) + 0.5) * volume.voxel_size


def hull_footprint(volume, cameras: Cameras, view: int, dilate_px: int = 1, centres: np.ndarray | None = None
                   ) -> np.ndarray:
    """uint8 (H, W) 0/255: the projection of the occupied voxels of ``volume`` into ``view``. Surface voxel
    centres (``surface_centres``, or ``centres`` made by it once for every view) are splatted, then dilated by
    the largest projected voxel radius (half the voxel diagonal) plus ``dilate_px``. The dilation and the hole
    filling run on the splat's box grown by the dilation's reach and a pixel (the same pixels: farther out the
    image stays background, and that ring joins the box's border to the image's)."""
    import cv2

    cam = cameras[view]
    out = np.zeros((cam.height, cam.width), np.uint8)
    centres = surface_centres(volume) if centres is None else centres
    if len(centres) == 0:
        return out
    vs = volume.voxel_size
    uv, depth = cameras.project(centres, view)
    front = (depth > 0) & np.all(np.isfinite(uv), axis=1)
    uv, centres = uv[front], centres[front]
    if len(uv) == 0:
        return out
    half = 0.5 * float(np.linalg.norm(vs))
    radius = 0.0
    for axis in range(3):  # projected length of a half-diagonal step along each axis, worst case
        off = np.zeros(3)
        off[axis] = half
        uv2, _ = cameras.project(centres + off, view)
        radius = max(radius, float(np.nanmax(np.linalg.norm(uv2 - uv, axis=1))))
    px = np.rint(uv).astype(np.int64)
    ok = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    if not ok.any():
        return out
    out[px[ok, 1], px[ok, 0]] = 255
    r = int(np.ceil(radius)) + dilate_px
    reach = r + 1
    y0, y1 = max(int(px[ok, 1].min()) - reach, 0), min(int(px[ok, 1].max()) + reach + 1, cam.height)
    x0, x1 = max(int(px[ok, 0].min()) - reach, 0), min(int(px[ok, 0].max()) + reach + 1, cam.width)
    box = cv2.dilate(out[y0:y1, x0:x1], disc(r))
    # the splat of surface centres is hollow where the surface is far from the centre line: fill it
    out[y0:y1, x0:x1] = clean_mask(box, open_px=0, close_px=0, keep=0, fill_holes=True)
    return out


def hull_footprint_reference(volume, cameras: Cameras, view: int, dilate_px: int = 1) -> np.ndarray:
    """What ``hull_footprint`` must equal: the splat dilated and filled on the whole image."""
    import cv2

    cam = cameras[view]
    out = np.zeros((cam.height, cam.width), np.uint8)
    centres = surface_centres(volume)
    if len(centres) == 0:
        return out
    uv, depth = cameras.project(centres, view)
    front = (depth > 0) & np.all(np.isfinite(uv), axis=1)
    uv, centres = uv[front], centres[front]
    if len(uv) == 0:
        return out
    half = 0.5 * float(np.linalg.norm(volume.voxel_size))
    radius = max(float(np.nanmax(np.linalg.norm(cameras.project(centres + np.eye(3)[a] * half, view)[0] - uv, axis=1)))
                 for a in range(3))
    px = np.rint(uv).astype(np.int64)
    ok = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    out[px[ok, 1], px[ok, 0]] = 255
    out = cv2.dilate(out, disc(int(np.ceil(radius)) + dilate_px))
    return clean_mask(out, open_px=0, close_px=0, keep=0, fill_holes=True)


def grabcut_band(rgb: np.ndarray, mask: np.ndarray, inner: int = 4, outer: int = 20, iterations: int = 2) -> np.ndarray:
    """``mask`` (0/255) re-decided near its boundary by GrabCut (OpenCV): pixels more than ``inner`` pixels
    inside it are foreground, more than ``outer`` pixels outside it background; in the band between, colour
    GMMs of both sides and a contrast-sensitive graph cut decide. Runs on the band's bounding box only;
    seeded, so the result is repeatable."""
    import cv2

    m = (mask > 127).astype(np.uint8)
    near = cv2.dilate(m, disc(outer)) if outer > 0 else m
    if not m.any() or near.all():
        return m * 255
    trimap = np.full(m.shape, cv2.GC_BGD, np.uint8)
    trimap[near > 0] = cv2.GC_PR_BGD
    trimap[m > 0] = cv2.GC_PR_FGD
    core = cv2.erode(m, disc(inner), borderValue=0) if inner > 0 else m
    trimap[core > 0] = cv2.GC_FGD
    ys, xs = np.nonzero(near)
    pad = 8  # some sure background around the band for the background GMM
    y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, m.shape[0])
    x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, m.shape[1])
    box = np.ascontiguousarray(trimap[y0:y1, x0:x1])
    if not np.isin(box, (cv2.GC_FGD, cv2.GC_PR_FGD)).any() or not np.isin(box, (cv2.GC_BGD, cv2.GC_PR_BGD)).any():
        return m * 255
    cv2.setRNGSeed(0)
    bgr = np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1])
    cv2.grabCut(bgr, box, None, np.zeros((1, 65)), np.zeros((1, 65)), iterations, cv2.GC_INIT_WITH_MASK)
    out = np.zeros_like(m)
    out[y0:y1, x0:x1] = (box == cv2.GC_FGD) | (box == cv2.GC_PR_FGD)
    return out * 255


def check_views(what: str, images, cameras: Cameras | None, kind: str = "image"):
    """One image (or mask) per camera at the camera's size, or a NodeError naming the camera."""
    if cameras is not None:
        check_sizes(images, cameras, what, kind)


def maskset(alphas: list[np.ndarray], names: list[str], boxes=None) -> MaskSet:
    """The MaskSet of uint8 alphas: masks alpha >= 128 (cv2.threshold: one pass; inside the alpha's box alone when
    ``boxes`` gives one: the pages beyond it are never touched), the alpha kept as its levels (``MaskSet.alpha8``:
    the float alpha is alpha / 255 when a reader asks); ``boxes``: per alpha a box it is 0 outside of
    (``MaskSet.boxes``), or None."""
    masks = [_mask_of_levels(a, None if boxes is None else boxes[i]) for i, a in enumerate(alphas)]
    return MaskSet(masks, None, list(names), alpha8=alphas, boxes=boxes)


def maskset_reference(alphas: list[np.ndarray], names: list[str]) -> MaskSet:
    masks = [np.where(a >= 128, 255, 0).astype(np.uint8) for a in alphas]
    return MaskSet(masks, [a.astype(np.float32) / 255 for a in alphas], list(names))


def plate_model(plate: np.ndarray, noise_floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel Gaussian of a single clean plate: mean = the plate; sigma per channel = the plate's sensor
    noise (1.4826 x MAD of plate minus its 3x3 median), at least ``noise_floor`` grey levels."""
    import cv2

    resid = plate.astype(np.float32) - cv2.medianBlur(plate, 3).astype(np.float32)
    mad = np.median(np.abs(resid.reshape(-1, 3)), axis=0) * 1.4826
    sigma = np.maximum(mad, noise_floor).astype(np.float32)
    inv_var = np.broadcast_to(1.0 / sigma**2, plate.shape).astype(np.float32, order="C")  # kernels read it in place
    return plate.astype(np.float32), inv_var


# ---------------------------------------------------------------- device probe
@clrt.register_probe
def probe_keys() -> float:
    """The OpenCL device probe of the key kernels (nodegraph.clrt ranks devices by it): the chroma key checked
    against its NumPy reference on a small image (a device that disagrees is not used), then the best of 5 of
    chroma_key + difference_key on a 1920x1080 frame held as NumPy gives it (not page-aligned), ms."""
    import time

    rng = np.random.default_rng(0)
    small = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    key = key_direction_from_rgb([31, 158, 56])
    got, want = chroma_key_cl(small, key, despill=False)[0], chroma_key_reference(small, key)[0]
    if np.abs(got.astype(int) - want.astype(int)).max() > 1:
        raise RuntimeError("chroma_key disagrees with its NumPy reference on this device")
    frame = np.ascontiguousarray(np.broadcast_to(np.array([40, 170, 60], np.uint8), (1080, 1920, 3)))
    frame[300:800, 700:1200] = (180, 60, 50)
    mean, inv_var = plate_model(np.ascontiguousarray(np.broadcast_to(np.array([40, 170, 60], np.uint8), frame.shape)), 4.0)
    best = float("inf")
    for i in range(6):
        t = time.perf_counter()
        chroma_key_cl(frame, key, despill=False)
        difference_key_cl(frame, mean, inv_var)
        if i:
            best = min(best, time.perf_counter() - t)
    return best * 1e3


# ---------------------------------------------------------------- plates from the footage
def footage_plate(frames: list[np.ndarray], tolerance: float = 12.0, min_share: float = 0.5):
    """(plate (H, W, 3) uint8, seen (H, W) bool, share (H, W) float32) of one camera from its frames where no clean
    plate was shot: the per-pixel median colour over the frames, and where at least ``min_share`` of them lie
    within ``tolerance`` grey levels of it on every channel (``seen``: the pixel showed the same background most
    of the time; elsewhere the subject stood there in most frames and the plate there is the subject's)."""
    stack = np.stack([np.asarray(f, np.uint8)[..., :3] for f in frames])
    plate = np.median(stack, axis=0).round().astype(np.uint8)
    close = (np.abs(stack.astype(np.int16) - plate.astype(np.int16)).max(axis=-1) <= tolerance)
    share = close.mean(axis=0).astype(np.float32)
    return plate, share >= min_share, share


# ---------------------------------------------------------------- keying against a background mixture
def _mixture_pick(alphas, labels):
    """Per pixel the component that explains it best: the lowest alpha; on a tie the lowest class (background
    before shadow). (alpha uint8, class uint8)."""
    code = np.min([a.astype(np.int32) * 4 + l for a, l in zip(alphas, labels)], axis=0)
    return (code >> 2).astype(np.uint8), (code & 3).astype(np.uint8)


def _component_kw(k: int, kw: dict) -> dict:
    """The Horprasert parameters for component ``k``: the shadow and highlight allowance on the first (most
    frequent) background only. A second background (a light switched off, a screen's other picture) matches by
    colour and chromaticity alone: its own shadow range would reach the subject's darker colours (measured on
    the key stage: 1.7x the misses inside a flickering band)."""
    return kw if k == 0 else {**kw, "shadow": 1.0, "highlight": 1.0}


def difference_key_mixture_reference(rgb, mean, sigma, **kw):
    """``difference_key_reference`` against each component of a mixture (mean (K, H, W, 3), sigma (K, H, W, 3);
    see ``_component_kw``): a pixel is as foreground as its best-explaining background component says (see
    ``_mixture_pick``)."""
    out = [difference_key_reference(rgb, m.astype(np.float32), 1 / np.square(s.astype(np.float32)), **_component_kw(k, kw))
           for k, (m, s) in enumerate(zip(mean, sigma))]
    return _mixture_pick([a for a, _ in out], [l for _, l in out])


def difference_key_mixture_cl(rgb, model: "PlateMixture", view: int, *, cd_inner=4.0, cd_outer=8.0, shadow=0.5,
                               highlight=1.2, still=3.0):
    """OpenCL ``difference_key_mixture`` on one (H, W, 3) uint8 image against camera ``view`` of ``model``, read as
    it is stored (uint8 means, float16 sigmas: no conversion, so a model loaded from the cache for every frame costs
    nothing); see the reference. (alpha uint8 (H, W), class uint8 (H, W))."""
    run = KeyCL.get()
    h, w = rgb.shape[:2]
    npix = h * w
    mean = np.ascontiguousarray(model.mean[view])
    sigma = np.ascontiguousarray(model.sigma[view], np.float16)
    f = np.float32
    alpha, label = run.buffer("alpha", npix), run.buffer("label", npix)
    run.launch("difference_key_mixture", npix, 64, run.host(np.ascontiguousarray(rgb)), run.host(mean),
               run.host(sigma), np.int32(npix), np.int32(len(mean)), f(cd_inner), f(cd_outer), f(shadow),
               f(highlight), f(still), alpha, label)
    return run.read(alpha, (h, w)), run.read(label, (h, w))

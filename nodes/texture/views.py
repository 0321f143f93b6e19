"""Which camera paints which face: per-view visibility and quality, MRF view selection, per-camera colour
gains, blend weights that cross-fade across view seams, and global seam levelling.

    frame = FrameImages.build(images, masks, margin=1)                         # images + valid (eroded) masks
    stats = face_view_stats(vertices, faces, cameras, frame)                   # quality (V, F), colour (V, F, 3)
    gains = camera_gains(stats.quality, stats.colour)                          # (V, 3), exposure / white balance
    cost, spread = data_cost(stats.effective(), stats.colour, gains, return_spread=True)
    labels = select_views(cost, face_neighbours(faces))                        # nodes.common.meshops
    face_view, weight = blend_weights(labels, stats.effective(), faces, len(vertices), feather=2, spread=spread)
    offset = level_seams(vertices, faces, face_view, weight, cameras, frame, gains)

Visibility (Waechter et al. 2014, with margins against background bleeding): a face is usable in a view
when it faces the camera and its centroid and three inner points pass the z-buffer test, fall on valid
pixels (the mask eroded by ``margin`` pixels) and lie ``edge_px`` pixels away from any depth edge or the
mesh's outline. Quality = projected area in pixels x cosine (resolution and frontality), times a per-view
sharpness factor; a weaker test (centroid only) backs up faces no view passes. Selection minimises
sum_f D(f, l_f) + smoothness * #{neighbour faces with another label} (Potts) with D = 1 - q / max_q, plus a
penalty for colours inconsistent with the face's other views (occluders and registration errors), by iterated
conditional modes over pseudo-random halves of the faces (kernels ``face_cost`` and ``icm_step``;
``data_cost`` and ``select_views`` are their NumPy references).
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from kernels import source
from nodegraph import clrt
from nodes.common.cameras import Cameras
from nodes.common.meshops import ring_average, unique_edges
from nodes.common.types import bounding_rect

KERNELS = source("texture.cl")
INVISIBLE = 1e6


class TextureCL(clrt.Runner):
    source = KERNELS


@dataclass
class FrameImages:
    """A frame's images (and valid masks) laid out once for the kernels: RGB bytes view after view."""

    images: list[np.ndarray]          # (H, W, 3) uint8 per view
    valid: list[np.ndarray]           # (H, W) uint8 1 = may be sampled
    packed: np.ndarray                # all images, concatenated bytes
    packed_valid: np.ndarray          # all valid masks, concatenated bytes
    offsets: np.ndarray               # (V,) int64 byte offset of each image in ``packed``
    boxes: list | None = None         # per view a box its mask (so its valid mask) is 0 outside of, or None (MaskSet.boxes)

    @classmethod
    def build(cls, images, masks=None, margin: int = 2, boxes=None) -> "FrameImages":
        """(Per view on a few threads, nodes.common.views: the masks' erosion and the copies into the packed
        arrays release the GIL.) Images that lie one after the other in one block (a key's despilled images,
        ``types._PasteBlock``) are taken as they are, not copied; the valid masks are made in place, in a block
        whose untouched pages (outside each mask's box) cost nothing. ``boxes``: per mask a box it is 0 outside of
        (``MaskSet.boxes``): looked at alone."""
        from nodes.common.types import one_block
        from nodes.common.views import map_views

        sizes = np.array([im.size for im in images], np.int64)
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        packed = one_block(images)
        copy = packed is None
        if copy:
            packed = np.empty(int(sizes.sum()), np.uint8)
        packed_valid = np.zeros(int(sizes.sum()) // 3, np.uint8)

        def one(i, im):
            a, n = int(offsets[i]), int(sizes[i])
            v = packed_valid[a // 3:(a + n) // 3].reshape(im.shape[:2])
            valid_mask(im.shape[:2], None if masks is None else masks[i], margin, out=v,
                       hint=None if masks is None or boxes is None else boxes[i])
            if copy:
                packed[a:a + n] = np.asarray(im).reshape(-1)
            return v

        valid = map_views(one, range(len(images)), images)
        return cls(list(images), valid, packed, packed_valid, offsets, None if masks is None else boxes)

    def with_margin(self, masks, margin: int) -> "FrameImages":
        """The same images with valid masks eroded by ``margin`` instead (the view-dependent layers' own
        pictures: a camera paints its layer up to its mask's edge)."""
        packed_valid = np.zeros(len(self.packed_valid), np.uint8)
        valid = []
        for i, im in enumerate(self.images):
            a = int(self.offsets[i]) // 3
            v = packed_valid[a:a + im.shape[0] * im.shape[1]].reshape(im.shape[:2])
            valid.append(valid_mask(im.shape[:2], None if masks is None else masks[i], margin, out=v,
                                    hint=None if masks is None or self.boxes is None else self.boxes[i]))
        out = FrameImages(self.images, valid, self.packed, packed_valid, self.offsets,
                          None if masks is None else self.boxes)
        out._d_img = getattr(self, "_d_img", None)
        return out

    def device_images(self, tcl):
        """``packed`` as a device buffer (made once per frame; on a CPU device it is the host memory itself)."""
        if getattr(self, "_d_img", None) is None:
            self._d_img = tcl.host(self.packed)
        return self._d_img

    def device_valid(self, tcl):
        if getattr(self, "_d_valid", None) is None:
            self._d_valid = tcl.host(self.packed_valid)
        return self._d_valid


def valid_mask(shape, mask, margin: int, out: np.ndarray | None = None, hint=None) -> np.ndarray:
    """uint8 1 where a pixel may be sampled: inside the mask eroded by ``margin`` pixels (all pixels without a
    mask). (Eroded on the mask's bounding box: outside it the mask is 0, as the erosion's border is, so the box
    gives the same pixels as the whole image, ``valid_mask_reference``.) ``out``: a zeroed uint8 array of
    ``shape`` to write into (only the mask's box is written where ``margin`` > 0, or where a ``hint`` is given:
    a box (x0, y0, x1, y1) the mask is 0 outside of, MaskSet.boxes: the mask is read there alone)."""
    import cv2

    if out is None:
        out = np.zeros(shape, np.uint8)
    if mask is None:
        out[...] = 1
        return out
    mask = np.asarray(mask)
    hx0, hy0, hx1, hy1 = (0, 0, mask.shape[1], mask.shape[0]) if hint is None else (int(v) for v in hint)
    if hx1 <= hx0 or hy1 <= hy0:                               # an empty box: nothing may be sampled
        if hint is None:
            out[...] = 0
        return out
    m = np.greater(mask[hy0:hy1, hx0:hx1], 127).view(np.uint8)  # the comparison's bytes are 0 / 1
    if margin > 0:
        x, y, w, h = cv2.boundingRect(m)
        if w and h:
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
            out[hy0 + y:hy0 + y + h, hx0 + x:hx0 + x + w] = cv2.erode(m[y:y + h, x:x + w], kernel, borderValue=0)
        return out
    out[hy0:hy1, hx0:hx1] = m
    return out


def valid_mask_reference(shape, mask, margin: int) -> np.ndarray:
    """``valid_mask`` on the whole image."""
    import cv2

    if mask is None:
        return np.ones(shape, np.uint8)
    m = (np.asarray(mask) > 127).astype(np.uint8)
    if margin > 0:
        m = cv2.erode(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1)),
                      borderValue=0)
    elif margin < 0:                              # grown by -margin pixels
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (1 - 2 * margin, 1 - 2 * margin)))
    return m


@dataclass
class FaceViews:
    quality: np.ndarray   # (V, F) float32, 0 = not usable
    colour: np.ndarray    # (V, F, 3) float32 mean colour (0..255) where usable (the centroid's where relaxed)
    relaxed: np.ndarray   # (V, F) float32 quality under the weaker test (centroid only, no edge margin)
    seen: np.ndarray | None = None   # (V, F) float32 the relaxed test on another frame's valid masks (the
                                     # layers': centroid unoccluded inside the mask), when asked for

    device = None         # (quality, relaxed, colour) device buffers, as written by face_view_stats

    def effective(self, weak=0.01) -> np.ndarray:
        """Quality with views that pass only the relaxed test kept at ``weak`` times theirs: used only where
        a face has no better view."""
        return np.where(self.quality > 0, self.quality, weak * self.relaxed).astype(np.float32)


def _tolerances(vertices, depth_tol, edge_tol):
    diag = float(np.linalg.norm(np.ptp(vertices, axis=0))) if len(vertices) else 1.0
    return depth_tol * diag, edge_tol * diag


def face_view_stats(vertices, faces, cameras: Cameras, frame: FrameImages, *, depth_tol=0.01, edge_tol=0.02,
                    edge_px=2, seen_frame: FrameImages | None = None, closed_parts=None) -> FaceViews:
    """Per view and face: quality and mean colour (kernel ``face_views`` over the z-buffer of kernels/raster.cl).
    ``depth_tol`` and ``edge_tol`` are fractions of the mesh's bounding-box diagonal. With ``seen_frame`` (the
    same images, other valid masks) also ``seen``: the relaxed test against its masks, over the same z-buffer.
    ``closed_parts`` (``Topology.closed_parts``): the z-buffers skip the faces turned away from a view where
    that keeps their depths (``MeshRaster.culls``: half the rasterizing on a closed mesh)."""
    import pyopencl as cl

    from nodes.common.raster import MeshRaster

    v = np.ascontiguousarray(vertices, np.float32)
    f = np.ascontiguousarray(faces, np.int32)
    nv, nf = len(cameras), len(f)
    quality = np.zeros((nv, nf), np.float32)
    relaxed = np.zeros((nv, nf), np.float32)
    colour = np.zeros((nv, nf, 3), np.float32)
    if nf == 0:
        return FaceViews(quality, colour, relaxed)
    dt, et = _tolerances(v, depth_tol, edge_tol)
    r = MeshRaster(v, f, cameras)
    tcl = TextureCL.get()
    d_img = frame.device_images(tcl)
    d_valid = frame.device_valid(tcl)
    d_q = tcl.buffer("fv_quality", 4 * nf * nv)
    d_r = tcl.buffer("fv_relaxed", 4 * nf * nv)
    d_c = tcl.buffer("fv_colour", 12 * nf * nv)
    centres = cameras.centers
    if seen_frame is not None:
        seen = np.zeros((nv, nf), np.float32)
        d_seen_valid = seen_frame.device_valid(tcl)
        d_s = [tcl.buffer(role, n * nf * nv) for role, n in (("fv_seen_q", 4), ("fv_seen", 4), ("fv_seen_c", 12))]
    culls = r.culls(closed_parts)
    for view in range(nv):
        zbuf, box = r.depth_box(view, culls[view])  # depths only, on the mesh's box: what the tests read
        box = cl.cltypes.make_int4(*box)
        off = int(frame.offsets[view])
        tcl.launch("face_views", (nf,), (64,), r.d_verts, r.d_faces, np.int32(nf), r.d_cams, np.int32(view),
                   cl.cltypes.make_float4(*centres[view], 0), zbuf, box, d_valid, d_img, np.int64(off), np.float32(dt),
                   np.float32(et), np.int32(edge_px), d_q, d_r, d_c)
        if seen_frame is not None:                 # same z-buffer, the other masks: its relaxed output is ``seen``
            tcl.launch("face_views", (nf,), (64,), r.d_verts, r.d_faces, np.int32(nf), r.d_cams, np.int32(view),
                       cl.cltypes.make_float4(*centres[view], 0), zbuf, box, d_seen_valid, d_img, np.int64(off),
                       np.float32(dt), np.float32(et), np.int32(0), *d_s)
    cl.enqueue_copy(tcl.queue, quality, d_q, is_blocking=False)
    cl.enqueue_copy(tcl.queue, relaxed, d_r, is_blocking=False)
    if seen_frame is not None:
        cl.enqueue_copy(tcl.queue, seen, d_s[1], is_blocking=False)
    cl.enqueue_copy(tcl.queue, colour, d_c, is_blocking=True)
    out = FaceViews(quality, colour, relaxed, seen if seen_frame is not None else None)
    out.device = (d_q, d_r, d_c)
    tcl.face_views_latest = weakref.ref(out)       # the buffers are shared: only the latest stats own them
    return out


def _sample_rgb_reference(img, p):
    h, w = img.shape[:2]
    x = np.clip(p[:, 0], 0, w - 1).astype(np.float32)
    y = np.clip(p[:, 1], 0, h - 1).astype(np.float32)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    f32 = np.float32
    return ((1 - fy) * ((1 - fx) * img[y0, x0].astype(f32) + fx * img[y0, x1].astype(f32))
            + fy * ((1 - fx) * img[y1, x0].astype(f32) + fx * img[y1, x1].astype(f32)))


def face_view_stats_reference(vertices, faces, cameras: Cameras, frame: FrameImages, *, depth_tol=0.01,
                              edge_tol=0.02, edge_px=2, seen_frame: FrameImages | None = None) -> FaceViews:
    """NumPy version of ``face_view_stats`` (z-buffer from raster.rasterize_reference)."""
    from nodes.common.raster import rasterize_reference

    seen_other = None
    if seen_frame is not None:
        seen_other = face_view_stats_reference(vertices, faces, cameras, seen_frame, depth_tol=depth_tol,
                                         edge_tol=edge_tol, edge_px=0).relaxed
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    nv, nf = len(cameras), len(f)
    quality = np.zeros((nv, nf), np.float32)
    relaxed = np.zeros((nv, nf), np.float32)
    colour = np.zeros((nv, nf, 3), np.float32)
    dt, et = _tolerances(v, depth_tol, edge_tol)
    A, B, C = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    G = (A + B + C) / 3
    n = np.cross(B - A, C - A)
    pts = [G, G + 0.8 * (A - G), G + 0.8 * (B - G), G + 0.8 * (C - G)]
    for view in range(nv):
        cam = cameras[view]
        w, h = cam.width, cam.height
        depth = rasterize_reference(v, f, cameras, view)[1]
        to_cam = cameras.centers[view] - G
        with np.errstate(invalid="ignore", divide="ignore"):
            cosine = np.einsum("ij,ij->i", n, to_cam) / (np.linalg.norm(n, axis=1) * np.linalg.norm(to_cam, axis=1))
        front = np.nan_to_num(cosine) > 0
        corners = [cameras.project(X, view) for X in (A, B, C)]
        for _, z in corners:
            front &= z > 1e-6
        (pa, _), (pb, _), (pc, _) = corners
        area = 0.5 * np.abs((pb[:, 0] - pa[:, 0]) * (pc[:, 1] - pa[:, 1]) - (pb[:, 1] - pa[:, 1]) * (pc[:, 0] - pa[:, 0]))
        acc = np.zeros((nf, 3), np.float32)
        strict = front.copy()
        valid = frame.valid[view]
        for s, X in enumerate(pts):
            p, z = cameras.project(X, view)
            inside = (p[:, 0] > -0.5) & (p[:, 1] > -0.5) & (p[:, 0] < w - 0.5) & (p[:, 1] < h - 0.5) & (z > 1e-6)
            x = np.where(inside, np.floor(p[:, 0] + 0.5), 0).astype(np.int64)
            y = np.where(inside, np.floor(p[:, 1] + 0.5), 0).astype(np.int64)
            seen = inside & (valid[y, x] != 0) & (z <= depth[y, x] + dt)
            c = _sample_rgb_reference(frame.images[view], p)
            if s == 0:
                centre_ok = front & seen
                first = c
            ok = seen.copy()
            for dx, dy in ((edge_px, 0), (-edge_px, 0), (0, edge_px), (0, -edge_px)):
                xx, yy = x + dx, y + dy
                inb = (xx >= 0) & (yy >= 0) & (xx < w) & (yy < h)
                d = depth[np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)]
                with np.errstate(invalid="ignore"):
                    ok &= inb & (np.abs(d - z) <= et)
            strict &= ok
            acc += c
        q = area * cosine
        quality[view] = np.where(strict, q, 0)
        relaxed[view] = np.where(centre_ok, q, 0)
        colour[view] = np.where(strict[:, None], acc * 0.25, np.where(centre_ok[:, None], first, 0))
    return FaceViews(quality, colour, relaxed, seen_other)


# ---------------------------------------------------------------- selection
def view_sharpness(images, valid, boxes=None) -> np.ndarray:
    """(V,) relative sharpness of each view: median gradient energy inside the valid region, divided by the
    median over views (1 = typical; a blurred or defocused view scores lower). (Per view on a few threads, and
    on the valid region's bounding box when the image's size is a whole number of the 1/k reduction's blocks:
    the same numbers as ``view_sharpness_reference``'s whole images; ``boxes``: per view a box the valid region
    lies in, where that bounding box is looked for.)"""
    from nodes.common.views import map_views

    return _relative(np.asarray(map_views(_sharpness_boxed, images, valid, boxes or [None] * len(images))))


def view_sharpness_reference(images, valid) -> np.ndarray:
    """``view_sharpness`` on whole images, one view after the other."""
    return _relative(np.asarray([_sharpness(im, m) for im, m in zip(images, valid)]))


def _relative(s):
    med = np.median(s[s > 0]) if np.any(s > 0) else 1.0
    return np.clip(s / med, 0.25, 2.0) if med > 0 else np.ones(len(s))


def _sharpness(im, m) -> float:
    """Mean |Laplacian| of the grey image inside the valid mask, judged at about 512 pixels across."""
    import cv2

    g = cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)
    k = max(1, g.shape[1] // 512)
    small = g if k == 1 else cv2.resize(g, (g.shape[1] // k, g.shape[0] // k), interpolation=cv2.INTER_AREA)
    ms = m if m.shape == small.shape else cv2.resize(m, small.shape[::-1], interpolation=cv2.INTER_NEAREST)
    lap = np.abs(cv2.Laplacian(small, cv2.CV_32F))
    vals = lap[ms > 0]
    return float(np.mean(vals)) if vals.size else 0.0


def _sharpness_boxed(im, m, hint=None) -> float:
    """``_sharpness`` on the valid mask's bounding box, grown by one pixel of the reduced image (the Laplacian's
    reach) and aligned to the reduction's k x k blocks (their means, and the mask's nearest samples, are then
    those of the whole image); the values inside the mask come in the same order, so their mean is the same."""
    import cv2

    h, w = m.shape
    k = max(1, w // 512)
    if h % k or w % k:                                    # the reduction is not by whole blocks: whole image
        return _sharpness(im, m)
    x, y, bw, bh = bounding_rect(m, hint)
    if not (bw and bh):
        return 0.0
    sx0, sy0 = max(x // k - 1, 0), max(y // k - 1, 0)     # the box in the reduced image, grown by one
    sx1, sy1 = min(-(-(x + bw) // k) + 1, w // k), min(-(-(y + bh) // k) + 1, h // k)
    return _sharpness(im[k * sy0:k * sy1, k * sx0:k * sx1], m[k * sy0:k * sy1, k * sx0:k * sx1]) if k == 1 else \
        _sharpness_reduced(im[k * sy0:k * sy1, k * sx0:k * sx1], m[k * sy0:k * sy1, k * sx0:k * sx1], k)


def _sharpness_reduced(im, m, k) -> float:
    """``_sharpness`` of a crop whose reduction factor is the whole image's ``k`` (not the crop's own width's)."""
    import cv2

    g = cv2.cvtColor(np.ascontiguousarray(im), cv2.COLOR_RGB2GRAY)
    small = cv2.resize(g, (g.shape[1] // k, g.shape[0] // k), interpolation=cv2.INTER_AREA)
    ms = cv2.resize(np.ascontiguousarray(m), small.shape[::-1], interpolation=cv2.INTER_NEAREST)
    lap = np.abs(cv2.Laplacian(small, cv2.CV_32F))
    vals = lap[ms > 0]
    return float(np.mean(vals)) if vals.size else 0.0


def data_cost(quality, colour, gains=None, *, consistency=40.0, return_spread=False):
    """(F, V) cost of painting face f from view v: 1 - q / max_q in [0, 1], +1 where the view's colour is
    further than ``consistency`` (0..255 units) from the face's mean colour over its views (the mean taken
    again without views beyond twice that; when it has at least three), INVISIBLE where the face is not
    usable. With ``return_spread`` also (F,) the mean distance of a face's view colours from that mean: how
    much its views disagree (0 with one view)."""
    q = np.asarray(quality, np.float32).T                    # (F, V)
    qmax = q.max(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = np.where(q > 0, 1 - q / np.where(qmax > 0, qmax, 1), INVISIBLE).astype(np.float32)
    c = np.transpose(colour, (1, 0, 2)).astype(np.float32)   # (F, V, 3)
    if gains is not None:
        c = c * np.asarray(gains, np.float32)[None]
    vis = q > 0
    nvis = vis.sum(axis=1)
    many = nvis >= 2
    spread = np.zeros(len(q), np.float32)
    if np.any(many):
        cs = c[many]
        vm = vis[many][..., None].astype(np.float32)
        n = nvis[many][:, None].astype(np.float32)
        centre = (cs * vm).sum(axis=1) / n                                   # mean colour of the views ...
        dist = np.linalg.norm(cs - centre[:, None], axis=2)
        if consistency > 0:                                                   # ... again without far outliers
            keep = vm[..., 0] * (dist <= 2 * consistency)
            kn = keep.sum(axis=1, keepdims=True)
            centre = np.where(kn > 0, (cs * keep[..., None]).sum(axis=1) / np.maximum(kn, 1), centre)
            dist = np.linalg.norm(cs - centre[:, None], axis=2)
        spread[many] = (dist * vm[..., 0]).sum(axis=1) / n[:, 0]
        if consistency > 0:
            bad = (vm[..., 0] > 0) & (dist > consistency) & (nvis[many] >= 3)[:, None]
            sub = cost[many]
            sub[bad] += 1.0
            cost[many] = sub
    return (cost, spread) if return_spread else cost


def hash32(x) -> np.ndarray:
    """lowbias32 integer hash on uint32 (kernel ``hash32``)."""
    x = np.asarray(x, np.uint32)
    with np.errstate(over="ignore"):
        x = x ^ (x >> np.uint32(16))
        x = x * np.uint32(0x7FEB352D)
        x = x ^ (x >> np.uint32(15))
        x = x * np.uint32(0x846CA68B)
        return x ^ (x >> np.uint32(16))


def round_key(seed: int, it: int) -> np.uint32:
    return hash32(np.uint32((0x9E3779B9 * (it + 1) + seed) & 0xFFFFFFFF))[()]


def select_views(cost, nbr, *, smoothness=0.5, iterations=12, seed=0) -> np.ndarray:
    """Labels (F,) minimising sum D(f, l_f) + smoothness * #{neighbours with another label} (Potts), by
    iterated conditional modes: each round updates a pseudo-random half of the faces (a hash of face and
    round) to their best label given their neighbours' labels. Faces with no usable view get -1. NumPy
    reference of ``select_views_cl``."""
    cost = np.asarray(cost, np.float32)
    nf, nv = cost.shape
    labels = np.argmin(cost, axis=1)
    none = cost[np.arange(nf), labels] >= INVISIBLE
    if smoothness > 0 and nf:
        rows = np.arange(nf)
        valid_nbr = nbr >= 0
        for it in range(iterations):
            agree = np.zeros((nf, nv), np.float32)
            for k in range(3):
                has = valid_nbr[:, k] & ~none[np.maximum(nbr[:, k], 0)]
                agree[rows[has], labels[nbr[has, k]]] += 1.0
            total = agree.sum(axis=1, keepdims=True)
            energy = cost + smoothness * (total - agree)
            best = np.argmin(energy, axis=1)
            move = ((hash32(rows.astype(np.uint32) ^ round_key(seed, it)) & 1) == 1) & (best != labels)
            if not np.any(move):
                break
            labels = np.where(move, best, labels)
    labels = np.where(none, -1, labels)
    return labels


def data_cost_cl(stats: "FaceViews", sharp, gains, *, weak=0.01, consistency=40.0):
    """Kernel ``face_cost`` over the visibility left on the device by ``face_view_stats``: (cost (F, V) device
    buffer, spread (F,), best view (F,) device buffer). Same numbers as ``data_cost(stats.effective(weak) *
    sharp, stats.colour, gains, consistency=...)``."""
    import pyopencl as cl

    tcl = TextureCL.get()
    nv, nf = stats.quality.shape
    latest = getattr(tcl, "face_views_latest", None)
    if stats.device is None or latest is None or latest() is not stats:    # not (or no longer) on the device
        d_q, d_r, d_c = (tcl.upload(n, np.ascontiguousarray(a, np.float32)) for n, a in
                         (("fv_quality", stats.quality), ("fv_relaxed", stats.relaxed), ("fv_colour", stats.colour)))
    else:
        d_q, d_r, d_c = stats.device
    d_cost = tcl.buffer("cost", 4 * max(nf * nv, 1))
    d_spread = tcl.buffer("spread", 4 * max(nf, 1))
    d_best = tcl.buffer("labels_a", 4 * max(nf, 1))
    spread = np.zeros(nf, np.float32)
    if nf:
        tcl.launch("face_cost", (nf,), (64,), np.int32(nf), np.int32(nv), d_q, d_r, d_c,
                   tcl.upload("sharp", np.asarray(sharp, np.float32)), tcl.upload("gain", np.asarray(gains, np.float32)),
                   np.float32(weak), np.float32(consistency), d_cost, d_spread, d_best)
        cl.enqueue_copy(tcl.queue, spread, d_spread, is_blocking=True)
    return d_cost, spread, d_best


def select_views_cl(d_cost, d_best, nbr, nviews, *, smoothness=0.5, iterations=12, seed=0) -> np.ndarray:
    """``select_views`` on the device (kernel ``icm_step``) from ``data_cost_cl``'s buffers: labels (F,)."""
    import pyopencl as cl

    tcl = TextureCL.get()
    nf = len(nbr)
    labels = np.empty(nf, np.int32)
    if nf == 0:
        return labels
    cur = d_best
    if smoothness > 0:
        d_nbr = tcl.upload("nbr", np.ascontiguousarray(nbr, np.int32))
        other = tcl.buffer("labels_b", 4 * nf)
        d_moved = tcl.buffer("moved", 4)
        moved = np.zeros(1, np.int32)
        for it in range(iterations):
            cl.enqueue_fill_buffer(tcl.queue, d_moved, np.int32(0), 0, 4)
            tcl.launch("icm_step", (nf,), (64,), np.int32(nf), np.int32(nviews), d_cost, d_nbr, cur, other,
                       np.float32(smoothness), np.uint32(round_key(seed, it)), d_moved)
            cur, other = other, cur
            cl.enqueue_copy(tcl.queue, moved, d_moved, is_blocking=True)
            if moved[0] == 0:
                break
    cl.enqueue_copy(tcl.queue, labels, cur, is_blocking=True)
    return labels


def camera_gains(quality, colour, *, iterations=6, min_level=8.0, max_faces=8000) -> np.ndarray:
    """(V, 3) per-camera, per-channel gains that make the views agree (exposure and white balance): the
    model colour[v, f] = a_v * t_f is fitted in log space over every face seen by at least two views
    (alternating robust means, residuals beyond 0.3 ignored), normalised so the gains' geometric mean is 1.
    Returns 1 / a_v. (Sums over faces by einsum: the same numbers as ``sum(axis=1)``, which reduced over a
    trailing axis of 3 four times slower.)"""
    q = np.asarray(quality)
    nv = q.shape[0]
    vis = q > 0
    both = np.flatnonzero(vis.sum(axis=0) >= 2)
    if len(both) > max_faces:                               # an even subsample is plenty for V x 3 unknowns
        both = both[np.linspace(0, len(both) - 1, max_faces).astype(np.int64)]
    c = np.ascontiguousarray(np.asarray(colour)[:, both], np.float32)   # (V, F', 3) (the indexing gives (F', V, 3) order)
    m = vis[:, both][..., None] & (c > min_level)           # (V, F', 3)
    if not np.any(m):
        return np.ones((nv, 3), np.float32)

    def over_faces(x):                                      # (V, 1, 3), = x.sum(axis=1, keepdims=True)
        return np.einsum("vfc->vc", x)[:, None]

    L = np.log(np.maximum(c, 1e-3))
    a = np.zeros((nv, 1, 3), np.float32)
    w = m.astype(np.float32)
    m_count = np.count_nonzero(m)
    La, r, tmp, wr = (np.empty_like(L) for _ in range(4))    # the (V, F', 3) temporaries, written in place
    near = np.empty(L.shape, bool)
    for _ in range(iterations):
        np.subtract(L, a, out=La)
        t = np.multiply(w, La, out=tmp).sum(axis=0) / np.maximum(w.sum(axis=0), 1e-9)   # (F', 3)
        np.subtract(La, t[None], out=r)
        np.less(np.abs(r, out=tmp), 0.3, out=near)
        np.multiply(w, near, out=wr)
        a = a + (over_faces(np.multiply(wr, r, out=tmp)) / np.maximum(over_faces(wr), 1e-9))
        seen = over_faces(w) > 0
        a = np.where(seen, a, 0.0)
        a -= a[seen[:, 0, 0]].mean(axis=0, keepdims=True) if np.any(seen) else 0
        if np.count_nonzero(wr) > 0.5 * m_count:                 # (0/1 values: the count is their sum)
            w, wr = wr, w
    return np.exp(-a[:, 0, :]).astype(np.float32)


def camera_gains_reference(quality, colour, *, iterations=6, min_level=8.0, max_faces=8000) -> np.ndarray:
    """``camera_gains`` written plainly (every sum a NumPy ``sum``): the tests check that both give the same
    numbers."""
    q = np.asarray(quality)
    nv = q.shape[0]
    vis = q > 0
    both = np.flatnonzero(vis.sum(axis=0) >= 2)
    if len(both) > max_faces:
        both = both[np.linspace(0, len(both) - 1, max_faces).astype(np.int64)]
    c = np.ascontiguousarray(np.asarray(colour)[:, both], np.float32)
    m = vis[:, both][..., None] & (c > min_level)
    if not np.any(m):
        return np.ones((nv, 3), np.float32)
    L = np.log(np.maximum(c, 1e-3))
    a = np.zeros((nv, 1, 3), np.float32)
    w = m.astype(np.float32)
    for _ in range(iterations):
        t = (w * (L - a)).sum(axis=0) / np.maximum(w.sum(axis=0), 1e-9)
        r = L - a - t[None]
        wr = w * (np.abs(r) < 0.3)
        a = a + ((wr * r).sum(axis=1, keepdims=True) / np.maximum(wr.sum(axis=1, keepdims=True), 1e-9))
        seen = w.sum(axis=1, keepdims=True) > 0
        a = np.where(seen, a, 0.0)
        a -= a[seen[:, 0, 0]].mean(axis=0, keepdims=True) if np.any(seen) else 0
        w = wr if wr.sum() > 0.5 * m.sum() else w
    return np.exp(-a[:, 0, :]).astype(np.float32)


# ---------------------------------------------------------------- blending and levelling
def blend_weights(labels, quality, faces, n_vertices, *, feather=2, K=4, spread=None, spread_range=(8.0, 24.0),
                  power=2.0, topo=None):
    """Soft labels that cross-fade between views over ``feather`` vertex rings on each side of a view seam.

    Per vertex, the share of its faces painted by each view is averaged ``feather`` times over the vertex
    neighbourhoods; per face the (at most K) views with the largest weight at its corners among those
    that see it are kept. Returns (face_view (F, K) int32, -1 = unused slot; weight (F, 3, K) float32,
    per corner). Inside a patch one view has weight 1: the texture stays as sharp as its best view.

    Where the views disagree (``spread``, the faces' colour disagreement, beyond ``spread_range[0]``; fully at
    ``spread_range[1]``) the geometry or calibration is off and no single view is right from elsewhere: there
    the weights move towards a quality^power weighted average of the views that see the surface, which is
    the least-squares guess for a view in between."""
    faces = np.asarray(faces, np.int64)
    nf = len(faces)
    nviews = quality.shape[0]
    K = min(K, nviews)
    face_view = np.full((nf, K), -1, np.int32)
    weight = np.zeros((nf, 3, K), np.float32)
    has = labels >= 0
    if not np.any(has):
        return face_view, weight
    from scipy.sparse import csr_matrix

    rows = faces[has].ravel()
    cols = np.repeat(labels[has], 3)
    W = np.bincount(rows * nviews + cols, minlength=n_vertices * nviews).reshape(n_vertices, nviews).astype(np.float64)
    s = W.sum(axis=1, keepdims=True)
    W = np.divide(W, s, out=np.zeros_like(W), where=s > 0)
    if feather > 0:
        A = topo.adjacency if topo is not None else ring_average(faces, n_vertices)
        for _ in range(feather):
            W = A @ W
    if spread is not None and len(faces):
        q = np.asarray(quality, np.float32).T                 # (F, V)
        qmax = q.max(axis=1, keepdims=True)
        qn = np.divide(q, qmax, out=np.zeros_like(q), where=qmax > 0) ** power
        inc = topo.incidence if topo is not None else csr_matrix(
            (np.ones(3 * nf), (faces.ravel(), np.repeat(np.arange(nf), 3))), shape=(n_vertices, nf))
        W_avg = np.asarray(inc @ qn)
        sw = W_avg.sum(axis=1, keepdims=True)
        W_avg = np.divide(W_avg, sw, out=np.zeros_like(W_avg), where=sw > 0)
        lo, hi = spread_range
        a_f = np.clip((np.asarray(spread, np.float32) - lo) / max(hi - lo, 1e-6), 0, 1)
        cnt = topo.corner_count if topo is not None else np.asarray(inc.sum(axis=1)).ravel()
        a_v = np.divide(inc @ a_f, cnt, out=np.zeros(n_vertices), where=cnt > 0)
        W = (1 - a_v[:, None]) * W + a_v[:, None] * W_avg
    W = W.astype(np.float32)
    visible = (np.asarray(quality).T > 0)                    # (F, V)
    score = (W[faces[:, 0]] + W[faces[:, 1]] + W[faces[:, 2]]) * visible
    score[np.flatnonzero(has), labels[has]] += 1e-3          # the face's own label always stays
    order = np.argpartition(-score, K - 1, axis=1)[:, :K] if nviews > K else np.tile(np.arange(nviews), (nf, 1))
    top = np.take_along_axis(score, order, axis=1)
    srt = np.argsort(-top, axis=1, kind="stable")          # the K best, best first
    order, top = np.take_along_axis(order, srt, axis=1), np.take_along_axis(top, srt, axis=1)
    keep = top > 0
    face_view[:] = np.where(keep, order, -1)
    cw = W[faces[:, :, None], order[:, None, :]]              # (F, 3, K): the kept views' corner weights
    cw *= keep[:, None, :]                                    # (weights are >= 0)
    own = (order == labels[:, None]) & has[:, None]           # corners where every kept weight is 0: own view
    dead = ~cw.any(axis=2)
    cw[dead[:, :, None] & own[:, None, :]] = 1.0
    weight[:] = cw
    return face_view, weight


def vertex_view_samples(vertices, index, views, cameras: Cameras, frame: FrameImages, radius=1.5):
    """Colour (N, 3) of vertex index[i] seen in view views[i] (mean of five bilinear samples within ``radius``
    pixels) and whether all five fell on valid pixels. (All samples at once from ``frame.packed``, sorted by
    view so the reads stay in one image at a time, one colour channel at a time: the arithmetic of
    ``_sample_rgb_reference``, the numbers of ``vertex_view_samples_reference``.)"""
    vertices = np.asarray(vertices, np.float64)
    views = np.asarray(views, np.int64)
    n = len(views)
    order = np.argsort(views, kind="stable")
    vs = views[order]
    bounds = np.searchsorted(vs, np.arange(len(cameras) + 1))
    pts = vertices[np.asarray(index)[order]]
    px, py = np.zeros(n), np.zeros(n)
    good = np.zeros(n, bool)
    for v in range(len(cameras)):
        a, b = bounds[v], bounds[v + 1]
        if a < b:
            p, z = cameras.project(pts[a:b], v)
            px[a:b], py[a:b] = p[:, 0], p[:, 1]
            good[a:b] = z > 1e-6
    w = np.array([c.width for c in cameras], np.int64)[vs]
    h = np.array([c.height for c in cameras], np.int64)[vs]
    img_off = frame.offsets[vs]
    val_off = img_off // 3
    packed, packed_valid = frame.packed, frame.packed_valid
    f32 = np.float32
    acc = [np.zeros(n, f32) for _ in range(3)]
    for dx, dy in ((0, 0), (radius, 0), (-radius, 0), (0, radius), (0, -radius)):
        qx, qy = px + dx, py + dy
        inside = (qx > -0.5) & (qy > -0.5) & (qx < w - 0.5) & (qy < h - 0.5)
        x = np.where(inside, np.floor(qx + 0.5), 0).astype(np.int64)
        y = np.where(inside, np.floor(qy + 0.5), 0).astype(np.int64)
        good &= inside & (packed_valid[val_off + y * w + x] != 0)
        xf = np.clip(np.nan_to_num(qx), 0, w - 1).astype(f32)
        yf = np.clip(np.nan_to_num(qy), 0, h - 1).astype(f32)
        x0, y0 = np.floor(xf).astype(np.int64), np.floor(yf).astype(np.int64)
        x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
        fx, fy = xf - x0, yf - y0
        gx, gy = 1 - fx, 1 - fy
        r0, r1 = img_off + 3 * (y0 * w), img_off + 3 * (y1 * w)
        i00, i01, i10, i11 = r0 + 3 * x0, r0 + 3 * x1, r1 + 3 * x0, r1 + 3 * x1
        for ch in range(3):
            acc[ch] += (gy * (gx * packed[i00 + ch].astype(f32) + fx * packed[i01 + ch].astype(f32))
                        + fy * (gx * packed[i10 + ch].astype(f32) + fx * packed[i11 + ch].astype(f32)))
    out = np.empty((n, 3), np.float32)
    ok = np.empty(n, bool)
    out[order] = np.stack(acc, axis=1) / 5
    ok[order] = good
    return out, ok


def vertex_view_samples_reference(vertices, index, views, cameras: Cameras, frame: FrameImages, radius=1.5):
    """``vertex_view_samples`` view by view on the (H, W, 3) images (the tests compare the two)."""
    vertices = np.asarray(vertices, np.float64)
    out = np.zeros((len(views), 3), np.float32)
    ok = np.zeros(len(views), bool)
    for v in np.unique(views):
        sel = np.flatnonzero(views == v)
        p, z = cameras.project(vertices[index[sel]], int(v))
        img, val = frame.images[v], frame.valid[v]
        h, w = val.shape
        good = z > 1e-6
        acc = np.zeros((len(sel), 3), np.float32)
        for dx, dy in ((0, 0), (radius, 0), (-radius, 0), (0, radius), (0, -radius)):
            q = p + (dx, dy)
            inside = (q[:, 0] > -0.5) & (q[:, 1] > -0.5) & (q[:, 0] < w - 0.5) & (q[:, 1] < h - 0.5)
            x = np.where(inside, np.floor(q[:, 0] + 0.5), 0).astype(np.int64)
            y = np.where(inside, np.floor(q[:, 1] + 0.5), 0).astype(np.int64)
            good &= inside & (val[y, x] != 0)
            acc += _sample_rgb_reference(img, np.nan_to_num(q))
        out[sel] = acc / 5
        ok[sel] = good
    return out, ok


def level_seams(vertices, faces, face_view, weight, cameras: Cameras, frame: FrameImages, gains, *,
                smoothness=0.3, regular=0.1, band=3, tol=1e-3, maxiter=100, min_weight=0.1, topo=None):
    """Seam levelling (after Waechter et al. 2014, sec. 5), within a band of ``band`` vertex rings around the
    view seams: an additive colour offset g per (vertex, view) pair used by the blend, such that at every
    vertex the views agree (f_va + g_va = f_vb + g_vb, f = the gain-corrected colour of the vertex in the
    view), offsets vary smoothly along the surface (smoothness * (g_va - g_wa) = 0 on mesh edges) and fade to
    0 at the band's edge (the per-camera gains already did the global part), and stay small (regular * g = 0).
    One sparse least-squares problem (normal equations by conjugate gradients, Jacobi preconditioner), three
    right-hand sides. Only slots weighing at least ``min_weight`` at their corner take part (the rest keep 0).
    Returns offsets (F, 3, K, 3) for the face slots (0..255 units)."""
    faces = np.asarray(faces, np.int64)
    nf, K = face_view.shape
    offset = np.zeros((nf, 3, K, 3), np.float32)
    nviews = len(cameras)
    nvert = len(vertices)
    slot_v = np.repeat(faces[:, :, None], K, axis=2)                     # (F, 3, K) vertex of each slot
    slot_view = np.repeat(face_view[:, None, :], 3, axis=1).astype(np.int64)
    used = np.flatnonzero((slot_view >= 0) & (weight >= min_weight))   # slots that matter at their corner
    used_keys = slot_v.reshape(-1)[used] * nviews + slot_view.reshape(-1)[used]
    present = np.zeros(nvert * nviews, bool)                             # sorted unique keys, by a table
    present[used_keys] = True
    keys = np.flatnonzero(present)
    kv = keys // nviews
    seam = np.zeros(nvert, bool)
    seam[kv[1:][kv[1:] == kv[:-1]]] = True                               # vertices with two or more views
    if not np.any(seam):
        return offset
    A_adj = topo.adjacency if topo is not None else ring_average(faces, nvert)
    inband = seam.astype(np.float64)
    for _ in range(band):
        inband = np.maximum(inband, (A_adj @ inband > 0).astype(np.float64))
    inband = inband > 0
    nodes = keys[inband[kv]]
    n = len(nodes)
    node_vertex, node_view = nodes // nviews, nodes % nviews
    colour, ok = vertex_view_samples(vertices, node_vertex, node_view, cameras, frame)
    colour = colour * np.asarray(gains, np.float32)[node_view]
    same = (node_vertex[1:] == node_vertex[:-1]) & ok[1:] & ok[:-1]      # nodes are sorted by vertex, then view
    i0 = np.flatnonzero(same)
    i1 = i0 + 1
    edges = topo.edges if topo is not None else unique_edges(faces)[0]
    edges = edges[inband[edges[:, 0]] | inband[edges[:, 1]]]
    pa, pb, pins = _edge_nodes(nodes, node_vertex, node_view, nviews, nvert, edges, inband)
    M, rhs = levelling_system(n, i0, i1, colour[i1] - colour[i0], pa, pb, pins, smoothness, regular)
    g = block_pcg(M, rhs, tol=tol, maxiter=maxiter)
    # offsets of the used slots: the node's value inside the band, 0 outside
    node, hit = _node_of(nodes, used_keys)
    offset.reshape(-1, 3)[used[hit]] = g[node[hit]].astype(np.float32)
    return offset


def _node_of(nodes, keys):
    """(index into the sorted ``nodes`` of each key, whether it is there)."""
    pos = np.searchsorted(nodes, keys)
    hit = pos < len(nodes)
    hit[hit] = nodes[pos[hit]] == keys[hit]
    return pos, hit


def _edge_nodes(nodes, node_vertex, node_view, nviews, nvert, edges, inband):
    """The levelling's edge rows from the band's nodes (sorted keys vertex * nviews + view): pairs (pa, pb) of
    nodes with the same view at the two ends of an edge, and ``pins``: the nodes at an edge's end whose other
    end is outside the band (offset 0 there: pinned towards 0). In the order of a dense (edge, view) table of
    node ids read row by row (``_edge_nodes_reference``), without making that table."""
    empty = np.zeros(0, np.int64)
    if not len(edges):
        return empty, empty, empty
    start = np.searchsorted(node_vertex, np.arange(nvert))
    count = np.bincount(node_vertex, minlength=nvert)

    def nodes_at(vert):                    # per vertex (in order) its nodes, by view: (which vertex, node)
        c = count[vert]
        first = np.cumsum(c) - c
        which = np.repeat(np.arange(len(vert)), c)
        return which, np.repeat(start[vert] - first, c) + np.arange(int(c.sum()))

    e, na = nodes_at(edges[:, 0])
    nb, found = _node_of(nodes, edges[e, 1] * nviews + node_view[na])
    a_out, b_out = ~inband[edges[:, 0]], ~inband[edges[:, 1]]
    pins = np.concatenate([nodes_at(edges[b_out, 0])[1], nodes_at(edges[a_out, 1])[1]]).astype(np.int64)
    return na[found].astype(np.int64), nb[found].astype(np.int64), pins


def _edge_nodes_reference(nodes, node_vertex, node_view, nviews, nvert, edges, inband):
    """``_edge_nodes`` by the dense (vertex, view) table of node ids."""
    table = np.full((nvert, nviews), -1, np.int64)
    table[node_vertex, node_view] = np.arange(len(nodes))
    ta, tb = table[edges[:, 0]], table[edges[:, 1]]                      # (E, views)
    a_out = ~inband[edges[:, 0]][:, None]
    b_out = ~inband[edges[:, 1]][:, None]
    both = (ta >= 0) & (tb >= 0)
    return ta[both], tb[both], np.concatenate([ta[(ta >= 0) & b_out], tb[(tb >= 0) & a_out]])


def levelling_system(n, i0, i1, diff, pa, pb, pins, smoothness, regular):
    """Normal equations (M = A^T A + regular^2 I sparse (n, n), rhs = A^T b (n, 3)) of ``level_seams``'s
    least-squares rows, built directly: a row g[i0] - g[i1] = diff per pair (i0, i1) (i0 sorted, increasing),
    smoothness * (g[pa] - g[pb]) = 0 per edge pair and smoothness * g[pin] = 0 per pin. The sums are added in
    the order a sparse product A^T A gives them (``levelling_system_reference``: the same numbers)."""
    from scipy.sparse import csr_matrix

    s2 = smoothness * smoothness
    d = (np.bincount(i0, minlength=n) + np.bincount(i1, minlength=n)).astype(np.float64)
    reps = np.bincount(pa, minlength=n) + np.bincount(pb, minlength=n) + np.bincount(pins, minlength=n)
    for k in range(int(reps.max()) if n else 0):                         # the edge rows' s^2, one at a time
        d[reps > k] += s2
    d += regular ** 2
    r = np.concatenate([np.arange(n), i0, i1, pa, pb])
    c = np.concatenate([np.arange(n), i1, i0, pb, pa])
    v = np.concatenate([d, np.full(2 * len(i0), -1.0), np.full(2 * len(pa), -s2)])
    M = csr_matrix((v, (r, c)), shape=(n, n))
    M.sort_indices()
    rhs = np.zeros((n, 3))
    diff = np.asarray(diff, np.float64)
    rhs[i1] -= diff                                                    # row order: i1's row comes first
    rhs[i0] += diff
    return M, rhs


def levelling_system_reference(n, i0, i1, diff, pa, pb, pins, smoothness, regular):
    """``levelling_system`` as the sparse product of the rows' matrix A."""
    from scipy.sparse import coo_matrix, csr_matrix, diags

    m0, ke, kp = len(i0), len(pa), len(pins)
    rows = [np.arange(m0), np.arange(m0), m0 + np.arange(ke), m0 + np.arange(ke), m0 + ke + np.arange(kp)]
    cols = [i0, i1, pa, pb, pins]
    vals = [np.ones(m0), -np.ones(m0), np.full(ke, smoothness), np.full(ke, -smoothness), np.full(kp, smoothness)]
    m = m0 + ke + kp
    A = csr_matrix(coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(m, n)))
    b = np.zeros((m, 3))
    b[:m0] = diff
    return (A.T @ A + diags(np.full(n, regular ** 2))).tocsr(), np.asarray(A.T @ b)


def block_pcg(M, B, *, tol=1e-4, maxiter=200):
    """Solve M X = B (M symmetric positive definite, sparse; B (n, k)) by conjugate gradients with a Jacobi
    preconditioner, all k columns at once. Stops when every column's residual is below tol * |b|. (The
    columns are kept as contiguous rows (k, n) and updated in place: elementwise work over a trailing axis
    of 3 ran at a third of the speed.)"""
    d = M.diagonal()
    inv = np.where(d > 0, 1.0 / np.where(d > 0, d, 1), 1.0)
    R = np.array(np.asarray(B, np.float64).T, order="C")                  # (k, n) residuals
    X = np.zeros_like(R)
    Z = inv * R
    P = Z.copy()
    Q = np.empty_like(P)
    T = np.empty_like(P)
    rz = np.einsum("ij,ij->i", R, Z)
    lim = tol * np.maximum(np.sqrt(np.einsum("ij,ij->i", R, R)), 1e-30)
    for _ in range(maxiter):
        if np.all(np.sqrt(np.einsum("ij,ij->i", R, R)) <= lim):
            break
        for j in range(len(P)):
            Q[j] = M @ P[j]
        pq = np.einsum("ij,ij->i", P, Q)
        alpha = np.divide(rz, pq, out=np.zeros_like(rz), where=pq != 0)[:, None]
        X += np.multiply(alpha, P, out=T)
        R -= np.multiply(alpha, Q, out=T)
        np.multiply(inv, R, out=Z)
        rz_new = np.einsum("ij,ij->i", R, Z)
        beta = np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz != 0)[:, None]
        P *= beta
        P += Z
        rz = rz_new
    return X.T


def fallback_vertex_colours(labels, colour, gains, faces, n_vertices, rounds=50, topo=None) -> np.ndarray:
    """(V, 3) colours for places no view may paint: each vertex averages the selected-view colours of its
    faces; vertices without any are filled by repeated neighbourhood averaging (a harmonic fill)."""
    faces = np.asarray(faces, np.int64)
    col = np.zeros((n_vertices, 3))
    cnt = np.zeros(n_vertices)
    has = labels >= 0
    if np.any(has):
        fc = np.repeat(colour[labels[has], np.flatnonzero(has)] * np.asarray(gains)[labels[has]], 3, axis=0)
        corners = faces[has].ravel()
        cnt = np.bincount(corners, minlength=n_vertices).astype(np.float64)
        for c in range(3):
            col[:, c] = np.bincount(corners, fc[:, c], minlength=n_vertices)
    known = cnt > 0
    col[known] /= cnt[known, None]
    if not np.all(known) and np.any(known) and len(faces):
        A = topo.adjacency if topo is not None else ring_average(faces, n_vertices)
        filled = known.astype(np.float64)
        unknown = np.flatnonzero(~known)
        Au = A[unknown]
        for _ in range(rounds):                    # masked averaging: grows inwards from the known vertices
            w = Au @ filled
            x = np.divide(Au @ (col * filled[:, None]), w[:, None], out=np.zeros((len(unknown), 3)), where=w[:, None] > 0)
            col[unknown] = x
            before = filled[unknown].sum()
            filled[unknown] = (w > 0).astype(np.float64)
            if filled[unknown].sum() == before == len(unknown):
                break
    if not np.any(known):
        col[:] = 128
    return col.astype(np.float32)

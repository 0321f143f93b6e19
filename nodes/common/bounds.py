"""The automatic capture box: an axis-aligned box around the captured object.

Automatic: the point nearest to the viewing rays through the silhouettes' centroids, a box sized from the
silhouettes' extents, then a coarse NumPy visual hull in that box, grown while the hull touches a side and
tightened to the occupied voxels (+ one voxel + a margin). Or an explicit ``bbox`` param. The coarse hull
keeps only voxels that at least ``min_seen`` views see (default: half the views, at least 2), so the box never
grows into what fewer views constrain (e.g. the far side of a zoomed or partial rig).
"""
from __future__ import annotations

import numpy as np

from nodegraph import NodeError
from .cameras import Cameras
from .silhouettes import BACKGROUND, IN, centre_states, check_masks, vote


def coarse_hull(masks: list[np.ndarray], cameras: Cameras, box: np.ndarray, resolution: int,
                min_seen: int | None = None) -> np.ndarray:
    """Boolean occupancy (nx, ny, nz) of voxel centres that fall inside the mask of every view that sees
    them and are seen by at least ``min_seen`` views (default: half the views, at least 2): the hull's vote
    with policy "ignore" (nodes.common.silhouettes). ``resolution`` voxels along the longest side of ``box``."""
    box = np.asarray(box, dtype=np.float64)
    size = box[1] - box[0]
    shape = np.maximum(1, np.round(size / size.max() * resolution)).astype(int)
    axes = [box[0, a] + (np.arange(n) + 0.5) * size[a] / n for a, n in enumerate(shape)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.float32)
    packed = cameras.pack()
    n_in = np.zeros(len(X), dtype=np.int32)
    n_bg = np.zeros(len(X), dtype=np.int32)
    for v, m in enumerate(masks):
        s = centre_states(m, packed[v], X)
        n_in += s == IN
        n_bg += s == BACKGROUND
    need = max(2, (len(masks) + 1) // 2) if min_seen is None else min_seen
    return vote(n_in, n_bg, len(masks), 0, "ignore", min_seen=need).reshape(tuple(shape))


def _occupied_box(occ: np.ndarray, box: np.ndarray):
    """(lo, hi) world box of the occupied voxels (whole voxels), and which sides of ``box`` they touch."""
    idx = np.argwhere(occ)
    vs = (box[1] - box[0]) / np.array(occ.shape)
    lo_i, hi_i = idx.min(0), idx.max(0) + 1
    touch_lo, touch_hi = lo_i == 0, hi_i == np.array(occ.shape)
    return np.array([box[0] + lo_i * vs, box[0] + hi_i * vs]), touch_lo, touch_hi


def initial_box(masks: list[np.ndarray], cameras: Cameras) -> np.ndarray:
    """A box around the point nearest to all rays through the silhouette centroids, sized by the
    silhouettes' extents at that distance. ``masks``: (H, W) uint8, foreground = non-zero."""
    import cv2

    origins, dirs, extents = [], [], []
    for v, m in enumerate(masks):
        # the centroid and box of the non-zero pixels by OpenCV's integer sums (np.nonzero's coordinates took 8 ms
        # an HD view): the same numbers, the sums being exact in float64
        m = np.ascontiguousarray(m, np.uint8)
        x0, y0, w, h = cv2.boundingRect(m)
        if w == 0:
            continue
        mom = cv2.moments(m[y0:y0 + h, x0:x0 + w], binaryImage=True)   # on the box: the whole image's sums less
        n = mom["m00"]                                                  # the box's offset times the count, exactly
        o, d = cameras.rays(v, [[(mom["m10"] + x0 * n) / n, (mom["m01"] + y0 * n) / n]])
        origins.append(o[0])
        dirs.append(d[0])
        extents.append(np.hypot(w - 1, h - 1) / 2)
    if len(origins) < 2:
        raise NodeError("bounds: fewer than two views have a non-empty silhouette; give the bbox param")
    # least squares: sum over rays of |(I - d d^T)(p - o)|^2
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for o, d in zip(origins, dirs):
        Pm = np.eye(3) - np.outer(d, d)
        A += Pm
        b += Pm @ o
    p0 = np.linalg.lstsq(A, b, rcond=None)[0]
    radius = 0.0
    for v, (o, ext) in enumerate(zip(origins, extents)):
        # pixels per world unit at p0: singular values of the projection's Jacobian
        eps = 1e-4 * np.linalg.norm(p0 - o)
        J = np.stack([(cameras.project(p0 + eps * e, v)[0] - cameras.project(p0 - eps * e, v)[0])[0] / (2 * eps) for e in np.eye(3)], axis=1)
        s = np.linalg.svd(J, compute_uv=False)[1]
        radius = max(radius, ext / s)
    return np.array([p0 - 1.5 * radius, p0 + 1.5 * radius])


def auto_bounds(masks: list[np.ndarray], cameras: Cameras, resolution: int = 64, margin: float = 0.05,
                min_seen: int = 0) -> np.ndarray:
    """Box [[xmin ymin zmin], [xmax ymax zmax]] around the object seen in ``masks`` (see module docstring);
    ``min_seen`` 0: the default rule of ``coarse_hull``."""
    masks = check_masks(masks, cameras, "bounds")
    if min_seen > len(cameras):
        raise NodeError(f"bounds: min_seen {min_seen} is more than the {len(cameras)} cameras")
    seen = min_seen or None
    box = initial_box(masks, cameras)
    for _ in range(6):
        occ = coarse_hull(masks, cameras, box, resolution, seen)
        if not occ.any():
            raise NodeError("bounds: the silhouettes do not intersect in space (wrong cameras or masks?)")
        occ_box, tlo, thi = _occupied_box(occ, box)
        if not (tlo.any() or thi.any()):
            break
        size = box[1] - box[0]
        box = box + np.array([-tlo.astype(float) * size * 0.5, thi.astype(float) * size * 0.5])
    # tighten: a second pass in the occupied box (+ one coarse voxel) at the same resolution
    vs = (box[1] - box[0]) / np.array(occ.shape)
    box = occ_box + np.array([-vs, vs])
    occ = coarse_hull(masks, cameras, box, resolution, seen)
    if occ.any():
        occ_box, _, _ = _occupied_box(occ, box)
    vs = (box[1] - box[0]) / np.array(occ.shape)
    extent = (occ_box[1] - occ_box[0]).max()
    return occ_box + np.array([-1, 1])[:, None] * (vs + margin * extent)

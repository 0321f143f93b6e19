"""Body landmarks seen in several views (key.person's table) triangulated into 3D points.

Triangulation: per landmark the point nearest (in angle) to the viewing rays of the views that see it with at
least ``min_visibility`` (rays through the undistorted pixels, Cameras.rays), each view weighted by its
visibility; with three views or more the view that reprojects worst is dropped while it lies beyond ``max_error``
pixels (a view that fitted another person, or the wrong arm), and the point is solved again. A landmark needs two
views. MediaPipe's sides are the person's own (left_* is the subject's left), told apart by the face: on the
synthetic figure, whose head has no face, they swap between views and frames (bench/humanoid.py)."""
from __future__ import annotations

import numpy as np

from nodes.common.cameras import Cameras

def _solve(origins: np.ndarray, dirs: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The point minimising the weighted squared angles to the rays: two rounds of distance-normalised least
    squares (the first round is the plain nearest point to the lines)."""
    x = None
    for _ in range(3):
        if x is None:
            scale = np.ones(len(w))
        else:
            scale = 1.0 / np.maximum(np.einsum("ij,ij->i", x - origins, dirs), 1e-6) ** 2
        A, b = np.zeros((3, 3)), np.zeros(3)
        for o, d, wi in zip(origins, dirs, w * scale):
            P = np.eye(3) - np.outer(d, d)
            A += wi * P
            b += wi * P @ o
        x = np.linalg.lstsq(A, b, rcond=None)[0]
    return x


def triangulate(points: dict, cameras: Cameras, min_visibility: float = 0.5, max_error: float = 30.0):
    """``points``: camera name -> (L, 3) array [x px, y px, visibility] or None. Returns (xyz (L, 3) with NaN where
    unseen, views (L,) used, rms (L,) reprojection error in pixels over the views used)."""
    index = {n: i for i, n in enumerate(cameras.names)}
    seen = [(index[n], np.asarray(p, np.float64)) for n, p in points.items() if p is not None and n in index]
    count = len(next(iter(p for _, p in seen))) if seen else 0
    xyz = np.full((count, 3), np.nan)
    views, rms = np.zeros(count, int), np.full(count, np.nan)
    rays = {v: cameras.rays(v, p[:, :2]) for v, p in seen}
    for j in range(count):
        use = [(v, p[j]) for v, p in seen if p[j, 2] >= min_visibility]
        while len(use) >= 2:
            o = np.array([rays[v][0][j] for v, _ in use])
            d = np.array([rays[v][1][j] for v, _ in use])
            x = _solve(o, d, np.array([q[2] for _, q in use]))
            err = np.array([np.linalg.norm(cameras.project(x[None], v)[0][0] - q[:2]) for v, q in use])
            if len(use) >= 3 and err.max() > max_error:
                use.pop(int(np.argmax(err)))
                continue
            if err.max() > max_error:       # two views that disagree: no point
                break
            xyz[j], views[j], rms[j] = x, len(use), float(np.sqrt(np.mean(err**2)))
            break
    return xyz, views, rms

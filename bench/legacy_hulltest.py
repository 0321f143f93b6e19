"""The seed's point test, exit and clamp (kernels/refine.cl through silhouette.h) and their NumPy references,
frozen as the benchmark's baseline (bench/legacy_surface.py) next to the benchmarks that use it: no node imports
it, so editing it changes no node's cache fingerprint. The vote rule, ``Silhouettes`` and ``inside_hull`` stay in
nodes.common.silhouettes.

    test = hull_test(Silhouettes.from_inputs(masks, cameras), "opencl")   # or "numpy"
    inside = test.inside(points); out = test.exit(a, b, steps); out = test.clamp(a, b, steps, dirs, reach)
"""
from __future__ import annotations

import numpy as np

from kernels import source
from nodegraph import clrt
from nodes.common.silhouettes import POLICIES, SilhouetteBits, Silhouettes, inside_hull


# ---------------------------------------------------------------- NumPy reference
def _bisect(a: np.ndarray, b: np.ndarray, views: Silhouettes, steps: int) -> tuple[np.ndarray, np.ndarray]:
    f = np.float32
    lo = np.zeros(len(a), f)
    hi = np.ones(len(a), f)
    d = b - a
    for _ in range(steps):
        t = f(0.5) * (lo + hi)
        ins = inside_hull(a + t[:, None] * d, views)
        lo = np.where(ins, t, lo)
        hi = np.where(ins, hi, t)
    return lo, hi


def exit_reference(a, b, views: Silhouettes, steps: int) -> np.ndarray:
    """Where each segment a[i] (inside) -> b[i] (outside) leaves the hull: middle of the last bisection interval."""
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    lo, hi = _bisect(a, b, views, steps)
    t = np.float32(0.5) * (lo + hi)
    return a + t[:, None] * (b - a)


def clamp_reference(a, b, views: Silhouettes, steps: int, dirs=None, reach: float = 0.0) -> np.ndarray:
    """Move from a[i] towards b[i]; where b[i] is outside the hull, go back to the last point found inside:
    along -dirs[i] from c = b[i] - reach * dirs[i] when reach > 0 and c is inside, else along the move."""
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    out = b.copy()
    bad = np.flatnonzero(~inside_hull(b, views))
    if len(bad):
        start = a[bad]
        if reach > 0:
            c = b[bad] - np.float32(reach) * np.asarray(dirs, np.float32)[bad]
            start = np.where(inside_hull(c, views)[:, None], c, start)
        lo, _ = _bisect(start, b[bad], views, steps)
        out[bad] = start + lo[:, None] * (b[bad] - start)
    return out


# ---------------------------------------------------------------- OpenCL
class PointTestCL(clrt.Runner):
    """kernels/refine.cl: the point test, exit (bisection) and clamp kernels."""

    source = source("refine.cl")


class HullTestCL:
    """The silhouettes of ``views`` on the device (binary masks as SilhouetteBits, soft alpha as floats) and the
    point test kernels: ``inside``, ``exit``, ``clamp`` (as the NumPy ``inside_hull``, ``exit_reference``,
    ``clamp_reference``)."""

    GROUP = 64

    def __init__(self, views: Silhouettes):
        self.run = PointTestCL.get()
        self.views = views
        self.d_cams = clrt.to_device(views.cams)
        if views.alpha is not None:
            sizes = [a.size for a in views.alpha]
            self.d_alpha = clrt.to_device(np.concatenate([a.ravel() for a in views.alpha]).astype(np.float32))
            self.d_alpha_off = clrt.to_device(np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int32))
            self.bits = None
            self.d_bits, self.d_bit_off = clrt.to_device(np.zeros(4, np.uint8)), clrt.to_device(np.zeros(len(sizes), np.int32))
        else:
            self.bits = SilhouetteBits.from_masks(views.masks)
            self.d_bits, self.d_bit_off = self.bits.bits, self.bits.bit_off_buf
            self.d_alpha = clrt.to_device(np.zeros(1, np.float32))
            self.d_alpha_off = clrt.to_device(np.zeros(len(views.masks), np.int32))

    def hull_args(self) -> tuple:
        v = self.views
        return (self.d_cams, np.int32(len(v.cams)), self.d_bits, self.d_bit_off, self.d_alpha, self.d_alpha_off,
                np.int32(v.alpha is not None), np.int32(v.min_views), np.int32(POLICIES.index(v.policy)))

    def _points(self, *arrays) -> list:
        return [np.ascontiguousarray(x, np.float32).reshape(-1, 3) for x in arrays]

    def exit(self, a, b, steps: int) -> np.ndarray:
        """As ``exit_reference``."""
        a, b = self._points(a, b)
        if len(a) == 0:
            return a.copy()
        out = self.run.buffer("out", a.nbytes)
        self.run.launch("hull_exit", len(a), self.GROUP, self.run.host(a), self.run.host(b), np.int32(len(a)),
                        np.int32(steps), *self.hull_args(), out)
        return self.run.read(out, a.shape, np.float32)

    def clamp(self, a, b, steps: int, dirs=None, reach: float = 0.0) -> np.ndarray:
        """As ``clamp_reference``."""
        a, b = self._points(a, b)
        if len(a) == 0:
            return a.copy()
        (d,) = self._points(np.zeros_like(a) if dirs is None else dirs)
        out = self.run.buffer("out", a.nbytes)
        self.run.launch("hull_clamp", len(a), self.GROUP, self.run.host(a), self.run.host(b), self.run.host(d),
                        np.float32(reach), np.int32(len(a)), np.int32(steps), *self.hull_args(), out)
        return self.run.read(out, a.shape, np.float32)

    def inside(self, points) -> np.ndarray:
        """Boolean per point, as ``inside_hull``."""
        (p,) = self._points(points)
        if len(p) == 0:
            return np.zeros(0, bool)
        out = self.run.buffer("inside", len(p))
        self.run.launch("hull_inside", len(p), self.GROUP, self.run.host(p), np.int32(len(p)), *self.hull_args(), out)
        return self.run.read(out, len(p), np.uint8).astype(bool)


class HullTestNumPy:
    """The NumPy reference with HullTestCL's methods (inside, exit, clamp)."""

    def __init__(self, views: Silhouettes):
        self.views = views

    def inside(self, points) -> np.ndarray:
        return inside_hull(points, self.views)

    def exit(self, a, b, steps: int) -> np.ndarray:
        return exit_reference(a, b, self.views, steps)

    def clamp(self, a, b, steps: int, dirs=None, reach: float = 0.0) -> np.ndarray:
        return clamp_reference(a, b, self.views, steps, dirs, reach)


def hull_test(views: Silhouettes, method: str = "opencl"):
    """HullTestCL (method "opencl") or HullTestNumPy ("numpy") for ``views``."""
    return HullTestCL(views) if method == "opencl" else HullTestNumPy(views)

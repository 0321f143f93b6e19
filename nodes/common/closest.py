"""Nearest points and closest points on a triangle mesh, on the OpenCL device (kernels/closest.cl) with their NumPy
references: ``PointGrid`` (the nearest of a point set: a uniform grid searched ring by ring; its reference is
scipy's cKDTree) and ``SurfaceQuery`` (the nearest vertex, then the closest point on the faces around it:
``closest``; ``closest_reference`` is the same in NumPy), each checked against its reference by a test. Track's
matches, detail, snap, unfold and residuals use them, and texture.transfer its texel lookup.

    q, d = SurfaceQuery(vertices, faces).closest(points)
    d, j = PointGrid(points).nearest(queries, upper)
"""
from __future__ import annotations

import numpy as np

from kernels import source
from nodegraph import clrt
from nodes.common.meshops import padded_rows, vertex_faces, vertex_normals


def used_vertices(faces: np.ndarray, count: int) -> np.ndarray:
    """Indices of the vertices some face uses, in increasing order."""
    return np.flatnonzero(np.bincount(np.asarray(faces, np.int64).ravel(), minlength=count) > 0)


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points on triangles (a, b, c) to points p, all (..., 3) (Ericson, Real-Time Collision
    Detection 5.1.5, vectorised): each region's point as a + v ab + w ac, the region tests on scalars and
    one combination at the end (half the time of choosing among seven (..., 3) candidate points)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("...i,...i", ab, ap), np.einsum("...i,...i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("...i,...i", ab, bp), np.einsum("...i,...i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("...i,...i", ab, cp), np.einsum("...i,...i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)                           # inside the face
        w = np.where(denom != 0, vc / denom, 0.0)
        t_ab = np.clip(np.where(d1 - d3 != 0, d1 / (d1 - d3), 0), 0, 1)
        t_ac = np.clip(np.where(d2 - d6 != 0, d2 / (d2 - d6), 0), 0, 1)
        t_bc = np.clip(np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) / ((d4 - d3) + (d5 - d6)), 0), 0, 1)
    # later tests win, as in Ericson's order (vertices first, then edges, else inside)
    for region, rv, rw in (((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), 1.0 - t_bc, t_bc),   # edge bc
                           ((vb <= 0) & (d2 >= 0) & (d6 <= 0), 0.0, t_ac),                        # edge ac
                           ((vc <= 0) & (d1 >= 0) & (d3 <= 0), t_ab, 0.0),                        # edge ab
                           ((d6 >= 0) & (d5 <= d6), 0.0, 1.0),                                    # vertex c
                           ((d3 >= 0) & (d4 <= d3), 1.0, 0.0),                                    # vertex b
                           ((d1 <= 0) & (d2 <= 0), 0.0, 0.0)):                                    # vertex a
        v, w = np.where(region, rv, v), np.where(region, rw, w)
    return a + v[..., None] * ab + w[..., None] * ac


FAR_CELLS = 4          # PointGrid: queries farther than this many cells outside the grid go to a k-d tree


def _finite(points: np.ndarray, what: str) -> np.ndarray:
    """``points``, or ValueError when one is NaN or infinite: the kernels would index cells (and the faces around
    a nearest vertex) from it and read outside their buffers (a simplified sequence's NaN vertices made
    texture.transfer's worker die of a segmentation fault)."""
    bad = ~np.isfinite(points)
    if bad.any():
        rows = np.flatnonzero(bad.any(axis=1))
        raise ValueError(f"{len(rows)} of {len(points)} of {what} are not finite (NaN or infinite; the first: "
                         f"row {rows[0]}, {points[rows[0]].tolist()})")
    return points


class PointGrid:
    """Nearest points by a uniform grid of cells searched on the OpenCL device (kernels/closest.cl,
    nearest_in_grid: exact, the same answers as a k-d tree up to ties); ``nearest_reference`` is scipy's cKDTree.
    Cells: about ``cells_per_point`` per point in the points' bounding box (on a surface a few points per occupied cell)."""

    def __init__(self, points: np.ndarray, cells_per_point: float = 8.0):
        self.points = _finite(np.ascontiguousarray(points, np.float64).reshape(-1, 3), "the grid's points")
        m = len(self.points)
        self.lo = self.points.min(axis=0) if m else np.zeros(3)
        extent = np.maximum((self.points.max(axis=0) if m else np.ones(3)) - self.lo, 1e-9)
        self.h = float(max(np.prod(extent) / (cells_per_point * max(m, 1)), 1e-27) ** (1 / 3))
        self.dims = np.minimum(np.floor(extent / self.h).astype(np.int64) + 1, 1 << 10)
        self.h = float(max(self.h, (extent / self.dims).max() * (1 + 1e-12)))   # a huge extent: fewer, larger cells
        cell = np.minimum(np.floor((self.points - self.lo) / self.h).astype(np.int64), self.dims - 1)
        lin = (cell[:, 2] * self.dims[1] + cell[:, 1]) * self.dims[0] + cell[:, 0]
        order = np.sort(lin * max(m, 1) + np.arange(m)) % max(m, 1)   # argsort(lin, kind="stable"), 5x faster (< 2^51)
        self.sorted = np.ascontiguousarray(self.points[order])
        self.ids = order.astype(np.int64)
        count = np.bincount(lin, minlength=int(np.prod(self.dims)))
        self.cell_start = np.r_[0, np.cumsum(count)].astype(np.int32)
        self.device = None
        self.tree = None

    def nearest(self, points: np.ndarray, upper: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(distance, index) of the nearest point closer than ``upper`` (inf and -1 where none is)."""
        points = _finite(np.ascontiguousarray(points, np.float64).reshape(-1, 3), "the query points")
        n = len(points)
        d, j = np.full(n, np.inf), np.full(n, -1, np.int64)
        if n == 0 or len(self.points) == 0:
            return d, j
        # a point far outside the grid would sweep most of its cells ring by ring: those few go to a k-d tree
        # (per column: a reduction along the length-3 axis costs 6x as much)
        reach = FAR_CELLS * self.h
        out = (points < self.lo - reach) | (points > self.lo + self.dims * self.h + reach)
        far = out[:, 0] | out[:, 1] | out[:, 2]
        near = np.flatnonzero(~far)
        if far.any():
            d[far], j[far] = self.nearest_reference(points[far], upper)
        if len(near) == 0:
            return d, j
        cl = ClosestCL.get()
        if self.device is None:
            self.device = (cl.host(self.sorted), cl.host(self.ids), cl.host(self.cell_start))
        m = len(near)
        db, jb = cl.buffer("grid_d", 8 * m), cl.buffer("grid_j", 8 * m)
        nx, ny, nz = (np.int32(x) for x in self.dims)
        cl.launch("nearest_in_grid", m, ClosestCL.GROUP, cl.upload("grid_points", points if m == n else points[near]),
                  np.int32(m), *self.device, nx, ny, nz, *(np.float64(x) for x in self.lo), np.float64(self.h),
                  np.float64(upper), db, jb)
        if m == n:
            cl.read(db, d.shape, np.float64, d)
            cl.read(jb, j.shape, np.int64, j)
        else:
            d[near] = cl.read(db, (m,), np.float64)
            j[near] = cl.read(jb, (m,), np.int64)
        return d, j

    def nearest_reference(self, points: np.ndarray, upper: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """``nearest`` by scipy's cKDTree (built once)."""
        from scipy.spatial import cKDTree

        if self.tree is None:
            self.tree = cKDTree(self.points)
        d, j = self.tree.query(np.asarray(points, np.float64).reshape(-1, 3), distance_upper_bound=upper)
        return d, np.where(np.isfinite(d), j, -1)


class SurfaceQuery:
    """Nearest points on a triangle mesh: the nearest vertex (PointGrid), then the closest point on the
    faces around it (exact wherever the closest face touches the nearest vertex, as on any mesh whose
    triangles are not much longer than the distances asked for)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None,
                 vf: np.ndarray | None = None, used: np.ndarray | None = None, with_normals: bool = True):
        self.vertices = np.asarray(vertices, np.float64)
        self.faces = np.asarray(faces, np.int64)
        self.normals = normals if normals is not None or not with_normals else vertex_normals(self.vertices, self.faces)
        self.used = used_vertices(self.faces, len(self.vertices)) if used is None else used
        self.grid = PointGrid(self.vertices[self.used])
        self.vf = padded_rows(*vertex_faces(self.faces, len(self.vertices))) if vf is None else vf
        self.corners = None
        self.device = None                                  # (host arrays kept alive, their buffers)

    def nearest_vertex(self, points: np.ndarray, upper: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(distance, vertex index) of the nearest used vertex (index -1 beyond ``upper``)."""
        d, j = self.grid.nearest(points, upper)
        return d, (np.where(j >= 0, self.used[np.maximum(j, 0)], -1) if len(self.used) else j)

    def closest(self, points: np.ndarray, with_faces: bool = False):
        """(closest points (P, 3), distances (P,)) on the surface, and their faces (P,) when ``with_faces``: the
        nearest vertex here, the faces around it on the OpenCL device (kernels/closest.cl, the same operations
        as ``closest_reference``, float64)."""
        points = np.ascontiguousarray(points, np.float64)
        if len(points) and not len(self.used):
            raise ValueError("closest points on a surface without faces")
        _, j = self.nearest_vertex(points)
        cl = ClosestCL.get()
        if self.device is None:                             # the mesh on the device once: corners and vertex -> faces
            corners = np.ascontiguousarray(self.vertices[self.faces].reshape(-1, 3))
            vf = np.ascontiguousarray(self.vf, np.int64)
            self.device = (corners, vf, cl.host(corners), cl.host(vf))
        n = len(points)
        q, d, f = np.empty((n, 3)), np.empty(n), np.empty(n, np.int64)
        if n:
            bufs = [cl.upload("points", points), cl.upload("nearest", j), *self.device[2:],
                    cl.buffer("q", q.nbytes), cl.buffer("d", d.nbytes), cl.buffer("face", f.nbytes)]
            cl.launch("closest_on_faces", n, ClosestCL.GROUP, bufs[0], bufs[1], bufs[3], np.int32(self.vf.shape[1]),
                      bufs[2], np.int32(n), *bufs[4:])
            cl.read(bufs[4], q.shape, np.float64, q)
            cl.read(bufs[5], d.shape, np.float64, d)
            cl.read(bufs[6], f.shape, np.int64, f)
        return (q, d, f) if with_faces else (q, d)

    def closest_reference(self, points: np.ndarray, with_faces: bool = False):
        """``closest`` in NumPy (what kernels/closest.cl computes)."""
        points = np.asarray(points, np.float64)
        _, j = self.nearest_vertex(points)
        cand = self.vf[j]                                   # (P, M), -1 padded: only the real faces are tried
        pi, mi = np.nonzero(cand >= 0)
        f = cand[pi, mi]
        if self.corners is None:                            # each corner of every face, contiguous: one gather each
            self.corners = [np.ascontiguousarray(self.vertices[self.faces[:, i]]) for i in range(3)]
        a, b, c = (np.take(x, f, axis=0) for x in self.corners)
        p = np.take(points, pi, axis=0)
        q = closest_on_triangles(p, a, b, c)
        d = np.linalg.norm(q - p, axis=1)
        table = np.full(cand.shape, np.inf)
        table[pi, mi] = d
        slot = np.full(cand.shape, -1, np.int64)
        slot[pi, mi] = np.arange(len(pi))
        best = slot[np.arange(len(points)), np.argmin(table, axis=1)]
        if with_faces:
            return q[best], d[best], f[best]
        return q[best], d[best]


class ClosestCL(clrt.Runner):
    """kernels/closest.cl: closest points on the faces around each point's nearest vertex."""

    source = source("closest.cl")
    GROUP = 64

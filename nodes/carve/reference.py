"""NumPy reference of kernels/carve.cl: the same steps with the same float32 operations in the same order,
vectorised over the voxels of a step. Run through the driver of carving.py (``carve(..., method="numpy")``)
it gives the same voxels as the kernels (exactly in the rgb colour space; lab goes through pow and cbrt,
whose last bits may differ). Meant for small grids and images: it is slow."""
from __future__ import annotations

import numpy as np

from nodes.common.cameras import camera_point_f32, project_camera_f32

from .photo import colour_space, dot3, spread

f32 = np.float32
SAMPLES = 8
EMPTY = np.uint64(0xFFFFFFFFFFFFFFFF)
NO_KEEPER = np.uint32(0xFFFFFFFF)
PROTECTED = 2
BACK_FACING = -0.5
COVER_EPS = f32(0.01)
ST_CAND, ST_KEEP, ST_GO = 1, 2, 3
FACES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
CUBE26 = np.argwhere(np.ones((3, 3, 3), bool)) - 1


def cross2(ax, ay, bx, by):
    return ax * by - ay * bx




def half_edge(cam, a, vs):
    """Kernel ``half_edge``: R[:, a] * vs[a] / 2 (float32)."""
    h = f32(0.5) * vs[a]
    return cam[a] * h, cam[4 + a] * h, cam[8 + a] * h


class CarveNumPy:
    def setup(self, grid, views, params):
        self.grid, self.views, self.p = grid, views, params
        self.occ = np.ascontiguousarray(grid.occ).ravel().copy()
        n = self.occ.size
        self.stamp = np.zeros(n, np.int64)
        self.counted = np.zeros(n, bool)
        self.fresh = np.zeros(n, bool)
        self.dims = grid.dims
        self.vs = grid.vs.astype(f32)
        self.px = [im.reshape(-1, 4) for im in views.images]
        self.inside = [(m[y0:y0 + h, x0:x0 + w] > 127).ravel() for m, (x0, y0, w, h) in zip(views.masks, views.wins)]
        self.items = [np.full(len(p), EMPTY, np.uint64) for p in self.px]
        self.cover = [np.zeros(len(p), np.int64) for p in self.px]
        self.keeper = [np.full(len(p), NO_KEEPER, np.uint32) for p in self.px]
        self.marks = [np.zeros(len(p), np.uint8) for p in self.px]
        self.cands = np.zeros(0, np.int64)
        self.surf = np.zeros(0, np.int64)
        self.count = 0
        self.lists = dict(grid.lists)
        surf = grid.lists["surface"][0].astype(np.int64)
        self.counted[surf] = True
        self.cover_add(surf, 1)

    # ---------------------------------------------------------------- geometry
    def ijk(self, v: np.ndarray) -> np.ndarray:
        nx, ny, nz = self.dims
        v = v.astype(np.int64)
        return np.stack([v // (ny * nz), (v // nz) % ny, v % nz], axis=1)

    def flat(self, ijk: np.ndarray) -> np.ndarray:
        nx, ny, nz = self.dims
        return (ijk[:, 0] * ny + ijk[:, 1]) * nz + ijk[:, 2]

    def in_grid(self, ijk: np.ndarray) -> np.ndarray:
        return np.all((ijk >= 0) & (ijk < np.array(self.dims)), axis=1)

    def centre(self, ijk: np.ndarray) -> np.ndarray:
        return ((ijk.astype(f32) + f32(0.5)) * self.vs).astype(f32)

    def occupied(self, ijk: np.ndarray, occ=None) -> np.ndarray:
        occ = self.occ if occ is None else occ
        ok = self.in_grid(ijk)
        out = np.zeros(len(ijk), bool)
        out[ok] = (occ[self.flat(ijk[ok])] & 1) > 0
        return out

    def surface(self, ijk: np.ndarray) -> np.ndarray:
        full = np.ones(len(ijk), bool)
        for d in FACES:
            full &= self.occupied(ijk + d)
        return ~full

    def normal(self, ijk: np.ndarray) -> np.ndarray:
        """Kernel ``voxel_normal``: minus the sum of the offsets of the occupied 26-neighbours (float32)."""
        g = np.zeros((len(ijk), 3), f32)
        for d in CUBE26:
            g[self.occupied(ijk + d)] -= d.astype(f32)
        return g

    def facing(self, g: np.ndarray, X: np.ndarray, c: int, cos_min=None) -> np.ndarray:
        """Kernel ``facing``: within the grazing limit of view c (or no normal direction)."""
        d = (self.views.centres[c, :3] - X).astype(f32)
        gg = dot3(g)
        cos_min = f32(self.p.cos_min if cos_min is None else cos_min)
        lhs = (g[:, 0] * d[:, 0] + g[:, 1] * d[:, 1]) + g[:, 2] * d[:, 2]
        return (gg == 0) | (lhs >= cos_min * np.sqrt(gg * dot3(d)))

    def in_cone(self, X: np.ndarray, c: int, axis: int, sign) -> np.ndarray:
        """Kernel ``in_cone``."""
        if axis < 0:
            return np.ones(len(X), bool)
        d = (X - self.views.centres[c, :3]).astype(f32)
        along = f32(sign) * d[:, axis]
        return (along > 0) & (along >= f32(self.p.cos_cone) * np.sqrt(dot3(d)))

    def active(self, axis: int, plane, sign) -> np.ndarray:
        if axis < 0:
            return np.ones(len(self.px), bool)
        return f32(sign) * (self.views.centres[:, axis] - f32(plane)) < f32(0)

    def window(self, c: int):
        x0, y0, w, h = (int(a) for a in self.views.wins[c])
        return x0, y0, w, h, f32(x0), f32(y0), f32(x0 + w - 1), f32(y0 + h - 1)

    def footprint(self, c: int, X: np.ndarray, scale: float) -> dict:
        """Kernel ``footprint`` per voxel centre: rectangle x0 x1 y0 y1 (int64, clipped to the window), ok,
        single, depth, and the hexagon (centre u v, half-edges e[k] = (eu, ev), limits lim[k])."""
        cam = self.views.cams[c].astype(f32)
        xc = camera_point_f32(cam, X)
        d, pts = [], []
        for a in range(-1, 3):
            Y = xc if a < 0 else tuple(x + h for x, h in zip(xc, half_edge(cam, a, self.vs)))
            u, v, depth = project_camera_f32(cam, Y)
            d.append(depth)
            pts.append((u, v))
        u0, v0 = pts[0]
        ok = (d[0] > 0) & (d[1] > 0) & (d[2] > 0) & (d[3] > 0)
        s = f32(scale)
        _, _, _, _, wx0, wy0, wx1, wy1 = self.window(c)
        with np.errstate(invalid="ignore", over="ignore"):
            e = [(s * (pts[k][0] - u0), s * (pts[k][1] - v0)) for k in (1, 2, 3)]
            hu = (np.abs(e[0][0]) + np.abs(e[1][0])) + np.abs(e[2][0])
            hv = (np.abs(e[0][1]) + np.abs(e[1][1])) + np.abs(e[2][1])
            ok &= np.isfinite(hu) & np.isfinite(hv) & np.isfinite(u0) & np.isfinite(v0)
            fx0, fx1 = np.ceil(u0 - hu), np.floor(u0 + hu)
            fy0, fy1 = np.ceil(v0 - hv), np.floor(v0 + hv)
            single = (fx0 > fx1) | (fy0 > fy1)
            fx0 = np.where(single, np.floor(u0 + f32(0.5)), fx0)
            fx1 = np.where(single, fx0, fx1)
            fy0 = np.where(single, np.floor(v0 + f32(0.5)), fy0)
            fy1 = np.where(single, fy0, fy1)
            fx0, fy0 = np.maximum(fx0, wx0), np.maximum(fy0, wy0)
            fx1, fy1 = np.minimum(fx1, wx1), np.minimum(fy1, wy1)
            fx0, fy0 = np.minimum(fx0, wx1 + f32(1)), np.minimum(fy0, wy1 + f32(1))
            fx1, fy1 = np.maximum(fx1, wx0 - f32(1)), np.maximum(fy1, wy0 - f32(1))
            lim = [np.abs(cross2(*e[0], *e[1])) + np.abs(cross2(*e[0], *e[2])),
                   np.abs(cross2(*e[1], *e[0])) + np.abs(cross2(*e[1], *e[2])),
                   np.abs(cross2(*e[2], *e[0])) + np.abs(cross2(*e[2], *e[1]))]
        conv = lambda a: np.where(ok, a, 0).astype(np.int64)  # noqa: E731
        return {"x0": conv(fx0), "x1": conv(fx1), "y0": conv(fy0), "y1": conv(fy1), "ok": ok, "depth": d[0],
                "single": single, "u": u0, "v": v0, "e": e, "lim": lim}

    @staticmethod
    def in_footprint(fp: dict, owner, xs, ys) -> np.ndarray:
        """Kernel ``in_footprint`` for pixels (xs, ys) of rectangles ``owner``."""
        qx = xs.astype(f32) - fp["u"][owner]
        qy = ys.astype(f32) - fp["v"][owner]
        inside = fp["single"][owner].copy()
        with np.errstate(invalid="ignore", over="ignore"):
            hexa = np.ones(len(owner), bool)
            for (eu, ev), lim in zip(fp["e"], fp["lim"]):
                hexa &= np.abs(eu[owner] * qy - ev[owner] * qx) <= lim[owner]
        return inside | hexa

    def index(self, c: int, xs, ys) -> np.ndarray:
        x0, y0, w, _, *_ = self.window(c)
        return (ys - y0) * w + (xs - x0)

    def pixels(self, c: int, X: np.ndarray, scale: float, strided: bool = False, rect_only: bool = False):
        """(owner, window pixel index, footprint) of every pixel of each voxel's footprint in view c (every
        stride-th row and column when ``strided``, as kernel ``photo`` samples; the whole rectangle when
        ``rect_only``)."""
        fp = self.footprint(c, X, scale)
        x0, x1, y0, y1, ok = fp["x0"], fp["x1"], fp["y0"], fp["y1"], fp["ok"]
        stride = None
        if strided:
            stride = np.maximum((np.maximum(x1 - x0 + 1, y1 - y0 + 1) + SAMPLES - 1) // SAMPLES, 1)
        owner, xs, ys = self.rect_pixels(x0, x1, y0, y1, ok, stride)
        if not rect_only:
            keep = self.in_footprint(fp, owner, xs, ys)
            owner, xs, ys = owner[keep], xs[keep], ys[keep]
        return owner, self.index(c, xs, ys), fp

    @staticmethod
    def rect_pixels(x0, x1, y0, y1, ok, stride=None):
        """Every pixel (or every stride-th) of each rectangle: (owner row, x, y), rows in y-then-x order."""
        nxr = np.where(ok, x1 - x0 + 1, 0)
        nyr = np.where(ok, y1 - y0 + 1, 0)
        nxr, nyr = np.maximum(nxr, 0), np.maximum(nyr, 0)
        if stride is not None:
            nxr = np.where(nxr > 0, (nxr + stride - 1) // stride, 0)
            nyr = np.where(nyr > 0, (nyr + stride - 1) // stride, 0)
        else:
            stride = np.ones(len(x0), np.int64)
        cnt = nxr * nyr
        owner = np.repeat(np.arange(len(x0)), cnt)
        local = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        w = nxr[owner]
        xs = x0[owner] + (local % np.maximum(w, 1)) * stride[owner]
        ys = y0[owner] + (local // np.maximum(w, 1)) * stride[owner]
        return owner, xs, ys

    def outline(self, c: int, X: np.ndarray) -> dict:
        """Kernel ``cube_outline`` per voxel centre."""
        cam = self.views.cams[c].astype(f32)
        xc = camera_point_f32(cam, X)
        hs = [half_edge(cam, a, self.vs) for a in range(3)]
        P, ok = [], np.ones(len(X), bool)
        for s in range(8):
            Y = []
            for i in range(3):
                a = xc[i] + hs[0][i] if s & 1 else xc[i] - hs[0][i]
                a = a + (hs[1][i] if s & 2 else -hs[1][i])
                Y.append(a + (hs[2][i] if s & 4 else -hs[2][i]))
            u, v, depth = project_camera_f32(cam, Y)
            with np.errstate(invalid="ignore"):
                ok &= (depth > 0) & np.isfinite(u) & np.isfinite(v)
            P.append((u, v))
        _, _, _, _, wx0, wy0, wx1, wy1 = self.window(c)
        eighth = f32(0.125)
        with np.errstate(invalid="ignore", over="ignore"):
            cx, cy = (sum_left([p[i] for p in P]) * eighth for i in (0, 1))
            pairs = [((1, 0), (3, 2), (5, 4), (7, 6)), ((2, 0), (3, 1), (6, 4), (7, 5)), ((4, 0), (5, 1), (6, 2), (7, 3))]
            e = []
            for pr in pairs:
                comp = []
                for i in (0, 1):
                    d = [P[a][i] - P[b][i] for a, b in pr]
                    comp.append(((d[0] + d[1]) + (d[2] + d[3])) * eighth)
                e.append(tuple(comp))
            dd = np.zeros(len(X), f32)
            lo = [P[0][0].copy(), P[0][1].copy()]
            hi = [P[0][0].copy(), P[0][1].copy()]
            for s in range(8):
                m = []
                for i in (0, 1):
                    c0 = (cx, cy)[i]
                    a = c0 + e[0][i] if s & 1 else c0 - e[0][i]
                    a = a + (e[1][i] if s & 2 else -e[1][i])
                    a = a + (e[2][i] if s & 4 else -e[2][i])
                    m.append(a)
                qx, qy = P[s][0] - m[0], P[s][1] - m[1]
                dd = np.maximum(dd, qx * qx + qy * qy)
                for i in (0, 1):
                    lo[i] = np.minimum(lo[i], P[s][i])
                    hi[i] = np.maximum(hi[i], P[s][i])
            d = np.sqrt(dd) + COVER_EPS
            lim = [np.abs(cross2(*e[0], *e[1])) + np.abs(cross2(*e[0], *e[2])),
                   np.abs(cross2(*e[1], *e[0])) + np.abs(cross2(*e[1], *e[2])),
                   np.abs(cross2(*e[2], *e[0])) + np.abs(cross2(*e[2], *e[1]))]
            mar = [d * np.sqrt(ex * ex + ey * ey) for ex, ey in e]
            x0 = np.maximum(np.ceil(lo[0] - COVER_EPS), wx0)
            x1 = np.minimum(np.floor(hi[0] + COVER_EPS), wx1)
            y0 = np.maximum(np.ceil(lo[1] - COVER_EPS), wy0)
            y1 = np.minimum(np.floor(hi[1] + COVER_EPS), wy1)
            x0, x1 = np.minimum(x0, wx1 + f32(1)), np.maximum(x1, wx0 - f32(1))
            y0, y1 = np.minimum(y0, wy1 + f32(1)), np.maximum(y1, wy0 - f32(1))
        depth = (xc[2] * cam[24]).astype(f32)
        ok &= depth > 0
        conv = lambda a: np.where(ok, a, 0).astype(np.int64)  # noqa: E731
        return {"x0": conv(x0), "x1": conv(x1), "y0": conv(y0), "y1": conv(y1), "ok": ok, "c": (cx, cy), "e": e,
                "lim": lim, "mar": mar, "key": depth.view(np.uint32)}

    def outline_pixels(self, c: int, X: np.ndarray, outer: bool, keys: bool = False):
        """(owner, window pixel index) of the silhouette pixels in each voxel's outer or inner outline in view c
        (and the voxels' bids, when ``keys``)."""
        o = self.outline(c, X)
        owner, xs, ys = self.rect_pixels(o["x0"], o["x1"], o["y0"], o["y1"], o["ok"])
        p = self.index(c, xs, ys)
        keep = self.inside[c][p]
        owner, xs, ys, p = owner[keep], xs[keep], ys[keep], p[keep]
        qx = xs.astype(f32) - o["c"][0][owner]
        qy = ys.astype(f32) - o["c"][1][owner]
        sel = np.ones(len(owner), bool)
        with np.errstate(invalid="ignore", over="ignore"):
            for (ex, ey), lim, mar in zip(o["e"], o["lim"], o["mar"]):
                a = np.abs(cross2(ex[owner], ey[owner], qx, qy))
                sel &= a <= (lim[owner] + mar[owner] if outer else lim[owner] - mar[owner])
        if keys:
            return owner[sel], p[sel], o["key"]
        return owner[sel], p[sel]

    # ---------------------------------------------------------------- the photo test
    def photo(self, v, X, g, axis, plane, sign, use_items: bool, marks=None):
        """Kernel ``photo`` for voxels v (centres X, normals g): (bad, mean colour, variance, views)."""
        n_vox = len(v)
        s1 = np.zeros((n_vox, 3), f32)
        rgb = np.zeros((n_vox, 3), f32)
        s2 = np.zeros(n_vox, f32)
        w2 = np.zeros(n_vox, f32)
        views = np.zeros(n_vox, np.int64)
        act = self.active(axis, plane, sign)
        for c in range(len(self.px)):
            if not act[c]:
                continue
            owner, p, _ = self.pixels(c, X, self.p.footprint, strided=True)
            face = self.facing(g, X, c) & self.in_cone(X, c, axis, sign)
            keep = face[owner]
            owner, p = owner[keep], p[keep]
            inside = self.inside[c][p]
            if use_items:
                seen = (self.items[c][p] & np.uint64(0xFFFFFFFF)) == v[owner].astype(np.uint64)
            else:
                seen = marks[c][p] == 0
            seen &= inside
            total = np.bincount(owner[inside], minlength=n_vox)
            n = np.bincount(owner[seen], minlength=n_vox)
            col = self.px[c][p[seen], :3].astype(np.float64)
            sums = np.stack([np.bincount(owner[seen], col[:, a], minlength=n_vox) for a in range(3)], axis=1)
            sqs = np.stack([np.bincount(owner[seen], col[:, a] ** 2, minlength=n_vox) for a in range(3)], axis=1)
            use = (n > 0) & (2 * n >= total)
            nf = n[use].astype(f32)[:, None]
            m = (sums[use].astype(f32) / nf).astype(f32)
            sd = np.sqrt(np.maximum(sqs[use].astype(f32) / nf - m * m, f32(0))).astype(f32)
            m, sd = m * self.views.gains[c, :3], sd * self.views.gains[c, :3]
            rgb[use] += m
            q = colour_space(m, self.p.space)
            s1[use] += q
            s2[use] += dot3(q)
            w2[use] += spread(m, sd, q, self.p.space)
            views[use] += 1
        var = np.full(n_vox, f32(-1), f32)
        bad = np.zeros(n_vox, bool)
        two = views >= 2
        vf = views[two].astype(f32)
        mean = s1[two] / vf[:, None]
        var[two] = s2[two] / vf - dot3(mean)
        within = w2[two] / vf
        limit = f32(self.p.threshold) + f32(self.p.adaptive) * np.sqrt(within)
        contrast = f32(self.p.contrast)
        bad[two] = (views[two] >= self.p.min_views) & (var[two] > limit * limit) & (var[two] > (contrast * contrast) * within)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_rgb = np.where(views[:, None] > 0, rgb / np.maximum(views, 1).astype(f32)[:, None], f32(0))
        return bad, mean_rgb, var, views

    # ---------------------------------------------------------------- the guard
    def cover_add(self, vox: np.ndarray, delta: int):
        if len(vox) == 0:
            return
        X = self.centre(self.ijk(vox))
        for c in range(len(self.px)):
            _, p = self.outline_pixels(c, X, False)
            np.add.at(self.cover[c], p, delta)

    def candidates(self, v: np.ndarray, step: int):
        """Kernel ``candidate``: stamp, list, claim (out of the counts when counted; bids for the pixels)."""
        v = np.asarray(v, np.int64)
        self.stamp[v] = (step << 2) | ST_CAND
        self.cands = np.concatenate([self.cands, v])
        X = self.centre(self.ijk(v))
        was = self.counted[v]
        for c in range(len(self.px)):
            owner, p, key = self.outline_pixels(c, X, False, keys=True)
            np.subtract.at(self.cover[c], p[was[owner]], 1)
            np.minimum.at(self.keeper[c], p, key[owner])

    def guard(self, step: int, n: int, use_items: bool):
        """Kernels ``carve_expose``, ``carve_decide`` and ``carve_apply`` over the step's candidates (the kernels
        read ``step`` from each candidate's stamp)."""
        v = self.cands
        assert len(v) == n
        nb = (self.ijk(v)[:, None, :] + FACES[None]).reshape(-1, 3)
        u = np.unique(self.flat(nb[self.in_grid(nb)]))
        u = u[((self.occ[u] & 1) > 0) & ((self.stamp[u] >> 2) != step) & ~self.counted[u]]
        self.counted[u] = True
        self.cover_add(u, 1)
        X = self.centre(self.ijk(v))
        needed = np.zeros(len(v), bool)
        for c in range(len(self.px)):
            owner, p, key = self.outline_pixels(c, X, True, keys=True)
            k = self.keeper[c][p]
            bad = (self.cover[c][p] == 0) & ((k == key[owner]) | (k == NO_KEEPER))
            needed[owner[bad]] = True
        self.stamp[v] = (step << 2) | np.where(needed, ST_KEEP, ST_GO)
        keep = needed
        for c in range(len(self.px)):
            owner, p = self.outline_pixels(c, X, False)
            self.keeper[c][p] = NO_KEEPER
            np.add.at(self.cover[c], p[keep[owner]], 1)
        self.occ[v[keep]] = 1 | PROTECTED
        self.counted[v[keep]] = True
        gone = v[~keep]
        self.occ[gone] = 0
        self.count += len(gone)
        if len(gone) == 0:
            return
        gX = X[~keep]
        gijk = self.ijk(gone)
        self.flag_around(gijk)
        if not use_items:
            return
        limit = 2 * sum(self.dims) + 4
        for c in range(len(self.px)):
            owner, p, _ = self.pixels(c, gX, 1.0, rect_only=True)
            mine = (self.items[c][p] & np.uint64(0xFFFFFFFF)) == gone[owner].astype(np.uint64)
            self.items[c][p[mine]] = EMPTY
            given = np.zeros(len(gone), bool)
            given[owner[mine]] = True
            if given.any():
                self.reveal(gone[given], gX[given], c, step, limit)

    def flag_around(self, ijk: np.ndarray):
        """Kernel ``flag_around``: the 3x3x3 blocks around ``ijk`` flagged (occupied ones count)."""
        nb = (ijk[:, None, :] + CUBE26[None]).reshape(-1, 3)
        self.fresh[self.flat(nb[self.in_grid(nb)])] = True

    def reveal(self, v, X, c, step, limit):
        """Kernel ``reveal`` for removed voxels v (centres X) in view c."""
        d = (X - self.views.centres[c, :3]).astype(f32)
        vmin = f32(0.5) * min(self.vs[0], self.vs[1], self.vs[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            dt = (vmin / np.maximum(np.maximum(np.abs(d[:, 0]), np.abs(d[:, 1])), np.abs(d[:, 2]))).astype(f32)
        walking = np.isfinite(dt)
        go = (step << 2) | ST_GO
        found = []
        for n in range(1, limit + 1):
            if not walking.any():
                break
            idx = np.flatnonzero(walking)
            tn = f32(n) * dt[idx]
            P = X[idx] + tn[:, None] * d[idx]
            q = np.floor(P / self.vs).astype(np.int64)
            out = ~self.in_grid(q)
            walking[idx[out]] = False
            idx, q = idx[~out], q[~out]
            u = self.flat(q)
            hit = (u != v[idx]) & ((self.occ[u] & 1) > 0) & (self.stamp[u] != go)
            walking[idx[hit]] = False
            found.append(q[hit])
        if found:
            self.flag_around(np.concatenate(found))

    # ---------------------------------------------------------------- steps
    def sweeps(self, step0: int):
        """Kernels ``carve_sweep_test``, the guard's three and ``carve_sweep_mark``: six sweeps in order, per plane
        test, guard, marks (the same planes and steps as carving.sweep_planes)."""
        sw = self.lists["sweep"]
        lists, offs, base = sw["lists"].astype(np.int64), sw["offs"].astype(np.int64), sw["base"]
        for s in range(6):
            axis, direction = s >> 1, (-1 if s & 1 else 1)
            sign = f32(direction)
            n = self.dims[axis]
            self.reset_marks()
            for t in range(n):
                p = t if direction > 0 else n - 1 - t
                plane = f32(p if direction > 0 else p + 1) * self.vs[axis]
                step = step0 + 1024 * s + t
                work = lists[offs[base[axis] + p]:offs[base[axis] + p + 1]]
                tv = work[(self.occ[work] & (1 | PROTECTED)) == 1]
                tv = tv[self.surface(self.ijk(tv))]
                self.cands = np.zeros(0, np.int64)
                if len(tv):
                    ijk = self.ijk(tv)
                    bad = self.photo(tv, self.centre(ijk), self.normal(ijk), axis, plane, sign, False, self.marks)[0]
                    if bad.any():
                        self.candidates(tv[bad], step)
                        self.guard(step, len(self.cands), False)
                kept = work[(self.occ[work] & 1) > 0]
                self.mark(kept[self.surface(self.ijk(kept))], axis, plane, sign, self.marks)

    def mark(self, vox, axis, plane, sign, marks):
        """Kernel ``mark_footprint`` for voxels ``vox`` (cameras behind the plane; every camera for axis < 0)."""
        if len(vox) == 0:
            return
        X = self.centre(self.ijk(vox))
        act = self.active(axis, plane, sign)
        for c in range(len(self.px)):
            if act[c]:
                _, p, _ = self.pixels(c, X, 1.0)
                marks[c][p] = 1

    def reset_marks(self):
        for m in self.marks:
            m[:] = 0

    def reset_items(self):
        for it in self.items:
            it[:] = EMPTY

    def compact(self, fresh_only: bool) -> int:
        """Kernel ``carve_compact`` over list "x" (in list order: the order does not matter)."""
        lst = self.lists["x"][0].astype(np.int64)
        flagged = self.fresh[lst]
        self.fresh[lst] = False
        sel = lst[flagged] if fresh_only else lst
        sel = sel[(self.occ[sel] & 1) > 0]
        self.surf = sel[self.surface(self.ijk(sel))]
        return len(self.surf)

    def splat(self, n: int):
        v = self.surf[:n]
        ijk = self.ijk(v)
        X = self.centre(ijk)
        g = self.normal(ijk)
        for c in range(len(self.px)):
            owner, p, fp = self.pixels(c, X, 1.0)
            keep = self.inside[c][p] & self.facing(g, X, c, BACK_FACING)[owner]
            key = (fp["depth"].astype(f32).view(np.uint32).astype(np.uint64) << np.uint64(32)) | v.astype(np.uint64)
            np.minimum.at(self.items[c], p[keep], key[owner[keep]])

    def _tested(self, lst, write_colors=False):
        """The list entries kernel ``carve_test`` tests: (positions, voxels, ijk)."""
        lst = np.asarray(lst, np.int64)
        pos = np.arange(len(lst))
        ok = (self.occ[lst] & 1) > 0
        if not write_colors:
            ok &= (self.occ[lst] & PROTECTED) == 0
        pos, v = pos[ok], lst[ok]
        ijk = self.ijk(v)
        s = self.surface(ijk)
        return pos[s], v[s], ijk[s]

    def _test(self, lst, step, use_items):
        _, v, ijk = self._tested(lst)
        self.cands = np.zeros(0, np.int64)
        if len(v):
            bad = self.photo(v, self.centre(ijk), self.normal(ijk), -1, 0.0, 0.0, use_items, self.marks)[0]
            if bad.any():
                self.candidates(v[bad], step)
        return len(self.cands)

    def test(self, n: int, step: int) -> int:
        return self._test(self.surf[:n], step, True)

    def test_layer(self, first: int, count: int, step: int) -> int:
        return self._test(self.lists["layers"][0][first:first + count], step, False)

    def mark_layer(self, first: int, count: int):
        v = self.lists["layers"][0][first:first + count].astype(np.int64)
        v = v[(self.occ[v] & 1) > 0]
        self.mark(v[self.surface(self.ijk(v))], -1, 0.0, 0.0, self.marks)

    def removed(self) -> int:
        n, self.count = self.count, 0
        return n

    def occupancy(self) -> np.ndarray:
        return (self.occ & 1).reshape(self.dims)

    def colours(self, reuse: bool = False):
        if not reuse:
            self.reset_items()
            self.compact(False)
            self.splat(len(self.surf))
        lst = self.surf
        n = len(lst)
        pos, v, ijk = self._tested(lst, write_colors=True)
        colors = np.zeros((n, 4), np.uint8)
        variance = np.full(n, f32(-1), f32)
        if len(v):
            _, rgb, var, views = self.photo(v, self.centre(ijk), self.normal(ijk), -1, 0.0, 0.0, True)
            colors[pos, :3] = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
            colors[pos, 3] = np.minimum(views, 255).astype(np.uint8)
            variance[pos] = var
        return lst.astype(np.uint32), colors, variance


def sum_left(xs):
    """x0 + x1 + ... summed left to right (the kernel's order)."""
    out = xs[0]
    for x in xs[1:]:
        out = out + x
    return out

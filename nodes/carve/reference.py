"""NumPy reference of kernels/carve.cl: the same steps with the same float32 operations in the same order,
vectorised over the voxels of a step. Run through the driver of carving.py (``carve(..., method="numpy")``)
it gives the same voxels as the kernels (exactly in the rgb colour space; lab goes through pow and cbrt,
whose last bits may differ). Meant for small grids and images: it is slow."""
from __future__ import annotations

import numpy as np

from nodes.common.cameras import project_packed_f32

from .photo import colour_space, dot3, spread

f32 = np.float32
SAMPLES = 8
EMPTY = np.uint64(0xFFFFFFFFFFFFFFFF)
PROTECTED = 2
BACK_FACING = -0.5
GUARD_OFFSET = f32(0.4)


class CarveNumPy:
    def setup(self, grid, views, params):
        self.grid, self.views, self.p = grid, views, params
        self.occ = np.ascontiguousarray(grid.occ).ravel().copy()
        self.stamp = np.full(self.occ.size, -1, np.int64)
        self.dims = grid.dims
        self.vs = grid.vs.astype(f32)
        self.px = [im.reshape(-1, 4) for im in views.images]
        self.inside = [p[:, 3] > 127 for p in self.px]
        self.marks = [np.zeros(len(p), np.uint8) for p in self.px]
        self.items = [np.full(len(p), EMPTY, np.uint64) for p in self.px]
        self.count = 0
        self.out = None
        self.fresh = np.zeros(self.occ.size, bool)
        self.lists = dict(grid.lists)

    # ---------------------------------------------------------------- geometry
    def ijk(self, v: np.ndarray) -> np.ndarray:
        nx, ny, nz = self.dims
        v = v.astype(np.int64)
        return np.stack([v // (ny * nz), (v // nz) % ny, v % nz], axis=1)

    def centre(self, ijk: np.ndarray) -> np.ndarray:
        return ((ijk.astype(f32) + f32(0.5)) * self.vs).astype(f32)

    def occupied(self, ijk: np.ndarray, occ=None) -> np.ndarray:
        occ = self.occ if occ is None else occ
        nx, ny, nz = self.dims
        ok = np.all((ijk >= 0) & (ijk < np.array(self.dims)), axis=1)
        out = np.zeros(len(ijk), bool)
        q = ijk[ok]
        out[ok] = (occ[(q[:, 0] * ny + q[:, 1]) * nz + q[:, 2]] & 1) > 0
        return out

    def staying(self, ijk: np.ndarray, step: int) -> np.ndarray:
        nx, ny, nz = self.dims
        ok = np.all((ijk >= 0) & (ijk < np.array(self.dims)), axis=1)
        out = np.zeros(len(ijk), bool)
        q = ijk[ok]
        w = (q[:, 0] * ny + q[:, 1]) * nz + q[:, 2]
        out[ok] = (self.stamp[w] != step) & ((self.occ[w] & 1) > 0)
        return out

    def surface(self, ijk: np.ndarray, test) -> np.ndarray:
        full = np.ones(len(ijk), bool)
        for a in range(3):
            for s in (-1, 1):
                q = ijk.copy()
                q[:, a] += s
                full &= test(q)
        return ~full

    def normal(self, ijk: np.ndarray) -> np.ndarray:
        """Kernel ``voxel_normal``: minus the sum of the offsets of the occupied 26-neighbours (float32)."""
        g = np.zeros((len(ijk), 3), f32)
        for a in (-1, 0, 1):
            for b in (-1, 0, 1):
                for c in (-1, 0, 1):
                    hit = self.occupied(ijk + np.array([a, b, c]))
                    g[hit] -= np.array([a, b, c], f32)
        return g

    def facing(self, g: np.ndarray, X: np.ndarray, c: int, cos_min=None) -> np.ndarray:
        """Kernel ``facing``: within the grazing limit of view c (or no normal direction)."""
        d = (self.views.centres[c, :3] - X).astype(f32)
        gg = dot3(g)
        cos_min = f32(self.p.cos_min if cos_min is None else cos_min)
        lhs = (g[:, 0] * d[:, 0] + g[:, 1] * d[:, 1]) + g[:, 2] * d[:, 2]
        return (gg == 0) | (lhs >= cos_min * np.sqrt(gg * dot3(d)))

    def in_cone(self, X: np.ndarray, c: int, axis: int, sign: float) -> np.ndarray:
        """Kernel ``in_cone``."""
        if axis < 0:
            return np.ones(len(X), bool)
        d = (X - self.views.centres[c, :3]).astype(f32)
        along = f32(sign) * d[:, axis]
        return (along > 0) & (along >= f32(self.p.cos_cone) * np.sqrt(dot3(d)))

    def active(self, axis: int, plane: float, sign: float) -> np.ndarray:
        if axis < 0:
            return np.ones(len(self.px), bool)
        return f32(sign) * (self.views.centres[:, axis] - f32(plane)) < f32(0)

    def footprint(self, c: int, X: np.ndarray, scale: float) -> dict:
        """Kernel ``footprint`` per voxel centre: rectangle x0 x1 y0 y1 (int64), ok, single, depth, and the
        hexagon (centre u v, half-edges e[k] = (eu, ev), limits lim[k])."""
        cam = self.views.cams[c]
        vs = self.vs
        u0, v0, _ = project_packed_f32(cam, X)
        d, pts = [], []
        for a in range(-1, 3):
            Y = X.copy()
            if a >= 0:
                Y[:, a] = Y[:, a] + f32(0.5) * vs[a]
            u, v, _ = project_packed_f32(cam, Y)
            zc = ((cam[8] * Y[:, 0] + cam[9] * Y[:, 1]) + cam[10] * Y[:, 2]) + cam[11]
            d.append(zc * cam[24])
            pts.append((u, v))
        ok = (d[0] > 0) & (d[1] > 0) & (d[2] > 0) & (d[3] > 0)
        s = f32(scale)
        with np.errstate(invalid="ignore", over="ignore"):
            e = [(s * (pts[k][0] - u0), s * (pts[k][1] - v0)) for k in (1, 2, 3)]
            hu = (np.abs(e[0][0]) + np.abs(e[1][0])) + np.abs(e[2][0])
            hv = (np.abs(e[0][1]) + np.abs(e[1][1])) + np.abs(e[2][1])
            ok &= np.isfinite(hu) & np.isfinite(hv) & np.isfinite(u0) & np.isfinite(v0)
            W, H = cam[22], cam[23]
            fx0, fx1 = np.ceil(u0 - hu), np.floor(u0 + hu)
            fy0, fy1 = np.ceil(v0 - hv), np.floor(v0 + hv)
            single = (fx0 > fx1) | (fy0 > fy1)
            fx0 = np.where(single, np.floor(u0 + f32(0.5)), fx0)
            fx1 = np.where(single, fx0, fx1)
            fy0 = np.where(single, np.floor(v0 + f32(0.5)), fy0)
            fy1 = np.where(single, fy0, fy1)
            fx0, fy0 = np.maximum(fx0, f32(0)), np.maximum(fy0, f32(0))
            fx1, fy1 = np.minimum(fx1, W - f32(1)), np.minimum(fy1, H - f32(1))
            fx0, fy0 = np.minimum(fx0, W), np.minimum(fy0, H)
            fx1, fy1 = np.maximum(fx1, f32(-1)), np.maximum(fy1, f32(-1))
            cr = lambda a, b: a[0] * b[1] - a[1] * b[0]  # noqa: E731
            lim = [np.abs(cr(e[0], e[1])) + np.abs(cr(e[0], e[2])), np.abs(cr(e[1], e[0])) + np.abs(cr(e[1], e[2])),
                   np.abs(cr(e[2], e[0])) + np.abs(cr(e[2], e[1]))]
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

    def pixels(self, c: int, X: np.ndarray, scale: float, strided: bool = False):
        """(owner, pixel index, footprint) of every pixel of each voxel's footprint in view c (every
        stride-th row and column when ``strided``, as kernel ``carve_test`` samples)."""
        fp = self.footprint(c, X, scale)
        x0, x1, y0, y1, ok = fp["x0"], fp["x1"], fp["y0"], fp["y1"], fp["ok"]
        stride = None
        if strided:
            stride = np.maximum((np.maximum(x1 - x0 + 1, y1 - y0 + 1) + SAMPLES - 1) // SAMPLES, 1)
        owner, xs, ys = self.rect_pixels(x0, x1, y0, y1, ok, stride)
        keep = self.in_footprint(fp, owner, xs, ys)
        owner, xs, ys = owner[keep], xs[keep], ys[keep]
        return owner, ys * int(self.views.cams[c][22]) + xs, fp

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

    # ---------------------------------------------------------------- steps
    def reset_marks(self):
        for c in range(len(self.px)):
            self.marks[c] = np.where(self.inside[c], 0, 1).astype(np.uint8)

    def reset_items(self):
        for c in range(len(self.px)):
            self.items[c][:] = EMPTY

    def _surface_voxels(self, name, first, count):
        v = self.lists[name][0][first:first + count].astype(np.int64)
        v = v[(self.occ[v] & 1) > 0]
        ijk = self.ijk(v)
        s = self.surface(ijk, self.occupied)
        return v[s], ijk[s]

    def splat(self, name, first, count):
        v, ijk = self._surface_voxels(name, first, count)
        X = self.centre(ijk)
        g = self.normal(ijk)
        for c in range(len(self.px)):
            owner, p, fp = self.pixels(c, X, 1.0)
            keep = self.inside[c][p] & self.facing(g, X, c, BACK_FACING)[owner]
            key = (fp["depth"].astype(f32).view(np.uint32).astype(np.uint64) << np.uint64(32)) | v.astype(np.uint64)
            np.minimum.at(self.items[c], p[keep], key[owner[keep]])

    def test(self, name, first, count, axis, plane, sign, use_items, step, write_colors=False):
        lst = self.lists[name][0][first:first + count].astype(np.int64)
        v, ijk = self._surface_voxels(name, first, count)
        if not write_colors:
            fresh = (self.occ[v] & PROTECTED) == 0
            v, ijk = v[fresh], ijk[fresh]
        X = self.centre(ijk)
        g = self.normal(ijk)
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
                seen = self.marks[c][p] == 0
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
        limit = np.zeros(n_vox, f32)
        two = views >= 2
        vf = views[two].astype(f32)
        mean = s1[two] / vf[:, None]
        var[two] = s2[two] / vf - dot3(mean)
        limit[two] = f32(self.p.threshold) + f32(self.p.adaptive) * np.sqrt(w2[two] / vf)
        if write_colors:
            with np.errstate(invalid="ignore", divide="ignore"):
                c = np.where(views[:, None] > 0, rgb / np.maximum(views, 1).astype(f32)[:, None], f32(0))
            colors = np.zeros((len(lst), 4), np.uint8)
            variance = np.full(len(lst), f32(-1), f32)
            order = np.argsort(lst)
            rows = order[np.searchsorted(lst[order], v)]      # positions of the voxels in the step's list
            colors[rows, :3] = np.clip(np.rint(c), 0, 255).astype(np.uint8)
            colors[rows, 3] = np.minimum(views, 255).astype(np.uint8)
            variance[rows] = var
            self.out = (colors, variance)
            return
        bad = (views >= self.p.min_views) & (views >= 2) & (var > limit * limit)
        self.stamp[v[bad]] = step

    def ray_needs(self, ijk, X, c, step, limit) -> np.ndarray:
        """Kernel ``ray_needs`` for the rays from view c through the points X of voxels ijk."""
        cam = self.views.cams[c]
        vs = self.vs
        u, w, _ = project_packed_f32(cam, X)
        zc = ((cam[8] * X[:, 0] + cam[9] * X[:, 1]) + cam[10] * X[:, 2]) + cam[11]
        with np.errstate(invalid="ignore"):
            fu, fv = u + f32(0.5), w + f32(0.5)
            seen = (zc * cam[24] > 0) & (fu >= 0) & (fu < cam[22]) & (fv >= 0) & (fv < cam[23])
        pix = np.zeros(len(X), np.int64)
        pix[seen] = fv[seen].astype(np.int64) * int(cam[22]) + fu[seen].astype(np.int64)
        seen[seen] = self.inside[c][pix[seen]]
        d = (X - self.views.centres[c, :3]).astype(f32)
        vmin = f32(0.5) * min(vs[0], vs[1], vs[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            dt = vmin / np.maximum(np.maximum(np.abs(d[:, 0]), np.abs(d[:, 1])), np.abs(d[:, 2]))
        seen &= np.isfinite(dt)
        covered = np.zeros(len(X), bool)
        for direction in (1, -1):
            walking = seen & ~covered
            for n in range(1, limit + 1):
                if not walking.any():
                    break
                idx = np.flatnonzero(walking)
                tn = f32(direction * n) * dt[idx]
                P = X[idx] + tn[:, None] * d[idx]
                q = np.floor(P / vs).astype(np.int64)
                out = np.any((q < 0) | (q >= np.array(self.dims)), axis=1)
                walking[idx[out]] = False
                idx, q = idx[~out], q[~out]
                same = np.all(q == ijk[idx], axis=1)
                idx, q = idx[~same], q[~same]
                hit = self.staying(q, step)
                covered[idx[hit]] = True
                walking[idx[hit]] = False
        return seen & ~covered

    def last_on_a_ray(self, v, ijk, X, step) -> np.ndarray:
        """Per candidate: True when some view needs it (kernel ``last_on_a_ray``)."""
        nx, ny, nz = self.dims
        limit = 2 * (nx + ny + nz) + 4
        needed = np.zeros(len(v), bool)
        for c in range(len(self.px)):
            for q in range(7):
                P = X.copy()
                if q:
                    a = (q - 1) // 2
                    o = -GUARD_OFFSET if q & 1 else GUARD_OFFSET
                    P[:, a] = X[:, a] + o * self.vs[a]
                needed |= self.ray_needs(ijk, P, c, step, limit)
        return needed

    def commit(self, name, first, count, axis, plane, sign, do_marks, step):
        v = self.lists[name][0][first:first + count].astype(np.int64)
        v = v[(self.occ[v] & 1) > 0]
        ijk = self.ijk(v)
        X = self.centre(ijk)
        cand = self.stamp[v] == step
        gone = np.zeros(len(v), bool)
        if cand.any():
            ci = np.flatnonzero(cand)
            gone[ci] = ~self.last_on_a_ray(v[ci], ijk[ci], X[ci], step)
        if do_marks:
            stay = self.surface(ijk, lambda q: self.staying(q, step)) & ~gone
            act = self.active(axis, plane, sign)
            Xs = X[stay]
            for c in range(len(self.px)):
                if not act[c]:
                    continue
                _, p, _ = self.pixels(c, Xs, 1.0)
                self.marks[c][p] = 1
        if axis < 0 and not do_marks and gone.any():
            # item pass: give back the removed voxels' pixels, flag their neighbours
            rv, rX = v[gone], X[gone]
            for c in range(len(self.px)):
                owner, p, _ = self.pixels(c, rX, 1.0)
                mine = (self.items[c][p] & np.uint64(0xFFFFFFFF)) == rv[owner].astype(np.uint64)
                self.items[c][p[mine]] = EMPTY
            nb = (ijk[gone][:, None, :] + (np.argwhere(np.ones((3, 3, 3), bool)) - 1)[None]).reshape(-1, 3)
            nb = nb[np.all((nb >= 0) & (nb < np.array(self.dims)), axis=1)]
            self.fresh[np.ravel_multi_index(nb.T, self.dims)] = True
        self.occ[v[gone]] = 0
        self.occ[v[cand & ~gone]] = 1 | PROTECTED
        self.count += int(gone.sum())

    def compact(self) -> int:
        """Kernel ``carve_compact`` over list "x" (in list order: the order does not matter)."""
        lst = self.lists["x"][0].astype(np.int64)
        flagged = lst[self.fresh[lst]]
        self.fresh[flagged] = False
        flagged = flagged[(self.occ[flagged] & 1) > 0]
        keep = self.surface(self.ijk(flagged), self.occupied)
        out = flagged[keep].astype(np.uint32)
        self.lists["fresh"] = (out, np.array([0, len(out)]))
        return len(out)

    def removed(self) -> int:
        n, self.count = self.count, 0
        return n

    def occupancy(self) -> np.ndarray:
        return (self.occ & 1).reshape(self.dims)

    def set_occupancy(self, occ: np.ndarray):
        self.occ = np.ascontiguousarray(occ, np.uint8).ravel().copy()

    def colours(self, count):
        return self.out

